// Where a turntable move goes on a step-counting controller, shared by the
// Modbus and USB (Tic) backends. Pure functions: no device, no clock.
//
//  - shortest_path: the target's position modulo 360 nearest the controller's
//    current one; the backend keeps the whole-turn difference as an offset so
//    the angles it reports stay the interface's cumulative ones.
//  - backlash compensation: every target is finally approached in one
//    direction, so the gear's lost motion is always taken up the same way. A
//    move against that direction is split in two legs: past the target by the
//    compensation, then back to it.
#pragma once

#include <cstdint>
#include <string>

namespace aggscan {

/// The direction every target is finally approached in (config
/// backlash_approach: "positive" | "negative").
enum class BacklashApproach { kPositive, kNegative };

/// "negative" is kNegative; anything else (the validated default
/// "positive") kPositive.
BacklashApproach ParseBacklashApproach(const std::string& name);

/// A move's target on the controller, in its steps.
struct ControllerTarget {
  int64_t steps = 0;             // where the controller must end
  double turn_offset_deg = 0.0;  // reported angle = controller angle + this, once there
};

/// The controller target for the interface's cumulative `angle_deg`, given
/// the backend's current whole-turn offset and the controller's position.
/// With shortest_path the target is moved by whole turns to at most 180 deg
/// from `current_steps` and the offset takes up the difference. |angle_deg|
/// <= 1e6 (the interface's limit), so the result fits int64 at any scaling.
ControllerTarget PlanControllerTarget(double angle_deg, double turn_offset_deg,
                                      int64_t current_steps, double steps_per_deg,
                                      bool shortest_path);

/// The legs of one move, in controller steps.
struct MoveLegs {
  int64_t first = 0;  // target of the leg started now
  int64_t final = 0;  // target of the whole move
  /// A second leg (from `first` back to `final`) follows the first.
  bool two_legs() const { return first != final; }
  /// Both targets fit a controller's int32 position register.
  bool fit_int32() const;
};

/// The legs of a move from `current` to `target` (steps) with a backlash
/// compensation of `comp` steps (0 = off): one leg when the move already goes
/// in the approach direction (or stays put), else first to `target` moved
/// `comp` steps against the approach direction, then to `target`.
MoveLegs PlanBacklashLegs(int64_t current, int64_t target, int64_t comp, BacklashApproach approach);

}  // namespace aggscan
