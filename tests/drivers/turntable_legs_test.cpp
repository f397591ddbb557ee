// The move planning both step-counting turntable backends share
// (drivers/turntable_legs.h): shortest path with cumulative angles, and the
// legs of a backlash-compensated move.
#include "drivers/turntable_legs.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <limits>

namespace aggscan {
namespace {

constexpr auto kPos = BacklashApproach::kPositive;
constexpr auto kNeg = BacklashApproach::kNegative;

TEST(BacklashLegs, ArrivingFromTheApproachSideIsOneLeg) {
  const MoveLegs legs = PlanBacklashLegs(100, 900, 40, kPos);
  EXPECT_FALSE(legs.two_legs());
  EXPECT_EQ(legs.first, 900);
  EXPECT_EQ(legs.final, 900);
}

TEST(BacklashLegs, ArrivingFromTheOtherSideOvershootsThenReturns) {
  const MoveLegs legs = PlanBacklashLegs(900, 450, 40, kPos);
  EXPECT_TRUE(legs.two_legs());
  EXPECT_EQ(legs.first, 410);  // below the target, so the last leg goes up
  EXPECT_EQ(legs.final, 450);
  // Across zero as well.
  const MoveLegs below = PlanBacklashLegs(10, -20, 40, kPos);
  EXPECT_EQ(below.first, -60);
  EXPECT_EQ(below.final, -20);
}

TEST(BacklashLegs, NoCompensationIsAlwaysOneLeg) {
  for (const auto approach : {kPos, kNeg}) {
    for (const int64_t target : {-500, 0, 450, 900}) {
      const MoveLegs legs = PlanBacklashLegs(450, target, 0, approach);
      EXPECT_FALSE(legs.two_legs()) << target;
      EXPECT_EQ(legs.first, target);
      EXPECT_EQ(legs.final, target);
    }
  }
}

TEST(BacklashLegs, NegativeApproachOvershootsUpwardMoves) {
  const MoveLegs up = PlanBacklashLegs(100, 300, 25, kNeg);
  EXPECT_TRUE(up.two_legs());
  EXPECT_EQ(up.first, 325);  // above the target, so the last leg goes down
  EXPECT_EQ(up.final, 300);
  const MoveLegs down = PlanBacklashLegs(300, 100, 25, kNeg);
  EXPECT_FALSE(down.two_legs());
  EXPECT_EQ(down.first, 100);
}

TEST(BacklashLegs, StayingPutIsOneLeg) {
  for (const auto approach : {kPos, kNeg}) {
    const MoveLegs legs = PlanBacklashLegs(450, 450, 40, approach);
    EXPECT_FALSE(legs.two_legs());
    EXPECT_EQ(legs.first, 450);
  }
}

TEST(BacklashLegs, Int32RangeCoversTheOvershootLeg) {
  constexpr int64_t kMin = std::numeric_limits<int32_t>::min();
  constexpr int64_t kMax = std::numeric_limits<int32_t>::max();
  EXPECT_TRUE(PlanBacklashLegs(0, kMax, 10, kPos).fit_int32());
  // The target fits; the overshoot past it does not.
  EXPECT_FALSE(PlanBacklashLegs(0, kMin + 5, 10, kPos).fit_int32());
  EXPECT_TRUE(PlanBacklashLegs(0, kMin + 5, 10, kNeg).fit_int32());
  EXPECT_FALSE(PlanBacklashLegs(0, kMax + 1, 0, kPos).fit_int32());
}

TEST(BacklashLegs, ApproachFromConfigName) {
  EXPECT_EQ(ParseBacklashApproach("positive"), kPos);
  EXPECT_EQ(ParseBacklashApproach("negative"), kNeg);
}

// 1600 microsteps per turn: 40/9 steps per degree.
constexpr double kSpd = 1600.0 / 360.0;

TEST(ControllerTarget, WithoutShortestPathUnwindsWholeTurns) {
  const ControllerTarget t = PlanControllerTarget(350.0, 0.0, 0, kSpd, false);
  EXPECT_EQ(t.steps, 1556);  // 350 * 40/9 = 1555.6, rounded
  EXPECT_EQ(t.turn_offset_deg, 0.0);
  const ControllerTarget back = PlanControllerTarget(10.0, 720.0, 0, kSpd, false);
  EXPECT_EQ(back.steps, std::llround((10.0 - 720.0) * kSpd));
  EXPECT_EQ(back.turn_offset_deg, 720.0);
}

TEST(ControllerTarget, ShortestPathGoesTheShorterWayAndKeepsTheTurnInTheOffset) {
  // 350 from 0: 10 deg back; the reported angle (controller + offset) is 350.
  const ControllerTarget t = PlanControllerTarget(350.0, 0.0, 0, kSpd, true);
  EXPECT_EQ(t.steps, std::llround(-10.0 * kSpd));
  EXPECT_EQ(t.turn_offset_deg, 360.0);
  EXPECT_NEAR(static_cast<double>(t.steps) / kSpd + t.turn_offset_deg, 350.0, 0.5 / kSpd);
  // Then 720: 10 deg forward to the controller's 0 plus two turns.
  const ControllerTarget u = PlanControllerTarget(720.0, t.turn_offset_deg, t.steps, kSpd, true);
  EXPECT_EQ(u.steps, 0);
  EXPECT_EQ(u.turn_offset_deg, 720.0);
  // Under half a turn away: no whole turn taken out.
  const ControllerTarget v = PlanControllerTarget(170.0, 0.0, 0, kSpd, true);
  EXPECT_EQ(v.steps, std::llround(170.0 * kSpd));
  EXPECT_EQ(v.turn_offset_deg, 0.0);
}

}  // namespace
}  // namespace aggscan
