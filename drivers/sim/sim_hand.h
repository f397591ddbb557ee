// The sim's operator at a hand-turned table (turntable.backend = "manual"):
// the platter angle the sim camera sees when a person turns the table after
// each prompt, as in the study (a phone shooting on a timer, the table turned
// by about the step between shots).
//
// After each prompt (Turn) the hand waits a reaction time, then turns the
// table by the plan's step plus a uniform error within
// +-sim.hand_angle_error_deg, over a turn time with a smooth start and stop
// (a half-cosine: the speed peaks at pi/2 x the mean speed mid-turn). Every
// sim.hand_late_every-th turn the hand is late: the turn's middle falls on
// the next view's exposure, which the sim camera then blurs. The table starts
// where the operator put it, within +-15 deg of the disc's zero. Reaction and
// turn times are drawn uniformly from the config's ranges. Deterministic for
// a seed. Thread-safe.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>

#include "common/clock.h"
#include "config/config.h"

namespace aggscan::sim {

class SimHand {
 public:
  /// `clock` must outlive this object (AngleFunction does not need it).
  SimHand(Clock& clock, const Config& config);
  ~SimHand();
  SimHand(const SimHand&) = delete;
  SimHand& operator=(const SimHand&) = delete;

  /// The prompt, now: turn the table by (to_deg - from_deg) of the plan.
  void Turn(double from_deg, double to_deg);
  /// The platter's angle at clock time t (deg, cumulative).
  double AngleAt(TimeNs t) const;
  /// AngleAt as a function that stays valid after this object is destroyed.
  std::function<double(TimeNs)> AngleFunction() const;
  /// Turns so far, and how many of them were late (blurred views).
  int turns() const;
  int late_turns() const;

 private:
  struct Model;
  Clock& clock_;
  SimConfig cfg_;
  TimeNs interval_;
  TimeNs half_exposure_;
  std::shared_ptr<Model> m_;  // shared with AngleFunction
};

}  // namespace aggscan::sim
