// Sim button: presses from software take the base's debounced path.
#include <gtest/gtest.h>

#include <vector>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/sim/sim_button.h"

namespace aggscan::sim {
namespace {

TEST(SimButton, PressesBeforeStartAreIgnored) {
  VirtualClock clock;
  SimButton b(clock, ButtonConfig{});
  std::vector<ButtonPress> got;
  b.Press();
  ASSERT_TRUE(b.Start([&](const ButtonPress& p) { got.push_back(p); }).ok());
  EXPECT_TRUE(got.empty());
  EXPECT_EQ(b.Start([](const ButtonPress&) {}).error().cls, ErrorClass::kInvalidState);
  b.Press();
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(got[0].source, "sim");
  EXPECT_EQ(got[0].time, clock.Now());
  EXPECT_FALSE(b.Describe().empty());
}

TEST(SimButton, DebounceMergesPressesWithin50ms) {
  VirtualClock clock;
  ButtonConfig cfg;
  cfg.debounce = 50 * kNsPerMs;
  SimButton b(clock, cfg);
  std::vector<ButtonPress> got;
  ASSERT_TRUE(b.Start([&](const ButtonPress& p) { got.push_back(p); }).ok());
  clock.AdvanceTo(1 * kNsPerSec);
  b.Press();
  clock.AdvanceTo(1 * kNsPerSec + 30 * kNsPerMs);
  b.Press();  // bounce: dropped
  clock.AdvanceTo(1 * kNsPerSec + 49 * kNsPerMs);
  b.InjectPress("api");  // still within 50 ms of the accepted press
  ASSERT_EQ(got.size(), 1u);
  clock.AdvanceTo(1 * kNsPerSec + 50 * kNsPerMs);
  b.InjectPress("api");
  ASSERT_EQ(got.size(), 2u);
  EXPECT_EQ(got[1].source, "api");
  EXPECT_EQ(got[1].time, 1 * kNsPerSec + 50 * kNsPerMs);
}

TEST(SimButton, StopEndsDelivery) {
  VirtualClock clock;
  SimButton b(clock, ButtonConfig{});
  int n = 0;
  ASSERT_TRUE(b.Start([&](const ButtonPress&) { ++n; }).ok());
  b.Press();
  b.Stop();
  clock.AdvanceTo(kNsPerSec);
  b.Press();
  EXPECT_EQ(n, 1);
  ASSERT_TRUE(b.Start([&](const ButtonPress&) { ++n; }).ok());  // restartable
  b.Press();
  EXPECT_EQ(n, 2);
}

}  // namespace
}  // namespace aggscan::sim
