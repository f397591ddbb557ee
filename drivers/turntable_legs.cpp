#include "drivers/turntable_legs.h"

#include <cmath>
#include <limits>

namespace aggscan {

BacklashApproach ParseBacklashApproach(const std::string& name) {
  return name == "negative" ? BacklashApproach::kNegative : BacklashApproach::kPositive;
}

ControllerTarget PlanControllerTarget(double angle_deg, double turn_offset_deg,
                                      int64_t current_steps, double steps_per_deg,
                                      bool shortest_path) {
  double controller_deg = angle_deg - turn_offset_deg;
  if (shortest_path) {
    const double current_deg = static_cast<double>(current_steps) / steps_per_deg;
    const double turns = std::round((controller_deg - current_deg) / 360.0);
    controller_deg -= 360.0 * turns;
    turn_offset_deg += 360.0 * turns;
  }
  return {std::llround(controller_deg * steps_per_deg), turn_offset_deg};
}

bool MoveLegs::fit_int32() const {
  constexpr int64_t kMax = std::numeric_limits<int32_t>::max();
  constexpr int64_t kMin = std::numeric_limits<int32_t>::min();
  return first >= kMin && first <= kMax && final >= kMin && final <= kMax;
}

MoveLegs PlanBacklashLegs(int64_t current, int64_t target, int64_t comp,
                          BacklashApproach approach) {
  const int64_t dir = approach == BacklashApproach::kNegative ? -1 : 1;
  // Against the approach direction: overshoot, so the last leg runs with it.
  const bool against = (target - current) * dir < 0;
  return {against && comp > 0 ? target - dir * comp : target, target};
}

}  // namespace aggscan
