#include "drivers/manual_turntable.h"

#include <utility>

namespace aggscan {

ManualTurntable::ManualTurntable(TurnPrompt on_turn, HomeNote on_home)
    : on_turn_(std::move(on_turn)), on_home_(std::move(on_home)) {}

ManualTurntable::~ManualTurntable() { Close(); }

TurntableInfo ManualTurntable::Info() const {
  return {"hand", "manual", "hand-turned table (no motor, no encoder)"};
}

Status ManualTurntable::DoOpen() {
  std::lock_guard<std::mutex> l(mu_);
  homed_ = false;
  angle_deg_ = 0.0;
  return OkStatus();
}

// Wherever the person left the table is the side's first view: the labels
// give its angle, so there is nothing to turn to.
Status ManualTurntable::DoStartHome() {
  {
    std::lock_guard<std::mutex> l(mu_);
    angle_deg_ = 0.0;
    homed_ = true;
  }
  if (on_home_) on_home_();
  return OkStatus();
}

Status ManualTurntable::DoStartMoveTo(double angle_deg) {
  double from = 0;
  {
    std::lock_guard<std::mutex> l(mu_);
    from = angle_deg_;
    angle_deg_ = angle_deg;
  }
  if (on_turn_ && angle_deg != from) on_turn_(from, angle_deg);
  return OkStatus();
}

Status ManualTurntable::DoStop() { return OkStatus(); }

Result<TurntableStatus> ManualTurntable::DoReadStatus() {
  std::lock_guard<std::mutex> l(mu_);
  TurntableStatus s;
  s.enabled = true;
  s.moving = false;
  s.in_position = true;
  s.homed = homed_;
  s.angle_deg = angle_deg_;
  s.angle_measured = false;
  return s;
}

void ManualTurntable::DoClose() {}

}  // namespace aggscan
