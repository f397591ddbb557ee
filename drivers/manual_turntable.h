// A table turned by hand: the study's own protocol (a lazy Susan, a person
// turning it by about the step between shots taken on a fixed schedule).
//
// Nothing moves and nothing is measured here. Homing and every move complete
// at once, so the capture loop's schedule (a view due every interval) runs as
// with a motor; each move to a new angle is a prompt to the person, passed to
// `on_turn` (the capture service tells the operator; the sim's hand turns the
// sim platter). The status reports the plan's angle with angle_measured
// false: the worker measures each view's real angle from the labels on the
// disc with the rig calibration.
#pragma once

#include <functional>
#include <mutex>

#include "drivers/turntable.h"

namespace aggscan {

class ManualTurntable final : public Turntable {
 public:
  /// Called from StartMoveTo with the plan's previous and new angle (deg).
  using TurnPrompt = std::function<void(double from_deg, double to_deg)>;
  /// Called from StartHome: a side begins (the sim's walker starts a round).
  using HomeNote = std::function<void()>;

  explicit ManualTurntable(TurnPrompt on_turn = {}, HomeNote on_home = {});
  ~ManualTurntable() override;

  TurntableInfo Info() const override;

 protected:
  Status DoOpen() override;
  Status DoStartHome() override;
  Status DoStartMoveTo(double angle_deg) override;
  Status DoStop() override;
  Result<TurntableStatus> DoReadStatus() override;
  void DoClose() override;

 private:
  TurnPrompt on_turn_;
  HomeNote on_home_;
  mutable std::mutex mu_;   // the health probe reads while the capture loop moves
  double angle_deg_ = 0.0;  // the plan's angle of the view being shot
  bool homed_ = false;
};

}  // namespace aggscan
