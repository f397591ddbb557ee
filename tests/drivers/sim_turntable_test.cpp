// Sim-turntable specifics beyond the contract: the physical platter model
// (settling oscillation, backlash) and each injected fault.
#include "drivers/sim/sim_turntable.h"

#include <gtest/gtest.h>

#include <cmath>

#include "common/clock.h"
#include "config/config.h"

namespace aggscan::sim {
namespace {

constexpr TimeNs kPoll = 20 * kNsPerMs;

class SimTurntableTest : public ::testing::Test {
 protected:
  void Make(const TurntableConfig& cfg, uint64_t seed = 1) {
    tt_ = std::make_unique<SimTurntable>(clock_, cfg, seed);
  }

  void Advance(TimeNs dt) { clock_.AdvanceTo(clock_.Now() + dt); }

  // Polls until in_position; fails the test after `timeout`.
  TurntableStatus WaitInPosition(TimeNs timeout = 30 * kNsPerSec) {
    const TimeNs deadline = clock_.Now() + timeout;
    while (clock_.Now() < deadline) {
      auto st = tt_->ReadStatus();
      EXPECT_TRUE(st.ok()) << st.error().ToString();
      if (!st.ok()) return {};
      if (st->in_position) return *st;
      Advance(kPoll);
    }
    ADD_FAILURE() << "not in position within the timeout";
    return {};
  }

  void OpenAndHome() {
    ASSERT_TRUE(tt_->Open().ok());
    ASSERT_TRUE(tt_->StartHome().ok());
    WaitInPosition();
  }

  VirtualClock clock_;
  std::unique_ptr<SimTurntable> tt_;
};

TEST_F(SimTurntableTest, HomingTakesHomeDuration) {
  TurntableConfig cfg;
  cfg.home_duration = 1500 * kNsPerMs;
  Make(cfg);
  ASSERT_TRUE(tt_->Open().ok());
  ASSERT_TRUE(tt_->StartHome().ok());
  Advance(1490 * kNsPerMs);
  EXPECT_FALSE(tt_->ReadStatus()->in_position);
  EXPECT_FALSE(tt_->ReadStatus()->homed);
  Advance(10 * kNsPerMs);
  EXPECT_TRUE(tt_->ReadStatus()->in_position);
  EXPECT_TRUE(tt_->ReadStatus()->homed);
  EXPECT_EQ(tt_->ReadStatus()->angle_deg, 0.0);
}

TEST_F(SimTurntableTest, SettlingOscillationDecays) {
  TurntableConfig cfg;
  cfg.repeatability_deg = 0.0;
  cfg.backlash_deg = 0.0;
  Make(cfg);
  OpenAndHome();
  ASSERT_TRUE(tt_->StartMoveTo(30.0).ok());
  const TimeNs end = clock_.Now() + static_cast<TimeNs>((30.0 / 60.0 + 60.0 / 180.0) * kNsPerSec);
  // Measured angle is exactly the target from the end of the move on, while
  // the platter rings around it.
  EXPECT_NEAR(tt_->MeasuredAngleAt(end), 30.0, 1e-9);
  EXPECT_NEAR(tt_->PhysicalAngleAt(end) - 30.0, cfg.settle_amplitude_deg, 1e-6);
  auto max_dev = [&](TimeNs from, TimeNs to) {
    double m = 0;
    for (TimeNs t = from; t < to; t += kNsPerMs)
      m = std::max(m, std::fabs(tt_->PhysicalAngleAt(t) - 30.0));
    return m;
  };
  const TimeNs tau = cfg.settle_time_constant;
  const double d0 = max_dev(end, end + tau);
  const double d1 = max_dev(end + tau, end + 2 * tau);
  const double d3 = max_dev(end + 3 * tau, end + 4 * tau);
  EXPECT_NEAR(d0, cfg.settle_amplitude_deg, 1e-6);
  EXPECT_LT(d1, d0 * std::exp(-1.0) + 1e-6);
  EXPECT_LT(d3, d0 * std::exp(-3.0) + 1e-6);
  EXPECT_GT(d3, 0.0);
  // The daemon's default 300 ms settle leaves under 0.03 deg of ringing.
  EXPECT_LT(max_dev(end + 300 * kNsPerMs, end + 2 * kNsPerSec), 0.03);
  // It crosses zero: an oscillation, not only a decay.
  bool below = false;
  for (TimeNs t = end; t < end + tau; t += kNsPerMs) below |= tt_->PhysicalAngleAt(t) < 30.0;
  EXPECT_TRUE(below);
  // Callable through the camera's function, which outlives the turntable.
  auto fn = tt_->PhysicalAngleFunction();
  const double at = tt_->PhysicalAngleAt(end + 50 * kNsPerMs);
  tt_.reset();
  EXPECT_EQ(fn(end + 50 * kNsPerMs), at);
}

TEST_F(SimTurntableTest, PhysicalAngleIsContinuousDuringTheMove) {
  TurntableConfig cfg;
  Make(cfg);
  OpenAndHome();
  const TimeNs start = clock_.Now();
  ASSERT_TRUE(tt_->StartMoveTo(90.0).ok());
  double prev = tt_->PhysicalAngleAt(start);
  for (TimeNs t = start; t < start + 3 * kNsPerSec; t += kNsPerMs) {
    const double p = tt_->PhysicalAngleAt(t);
    // 60 deg/s = 0.06 deg/ms; the decel lead adds at most 0.3 deg over 1/3 s.
    EXPECT_LT(std::fabs(p - prev), 0.075) << "at " << (t - start) / kNsPerMs << " ms";
    prev = p;
  }
}

TEST_F(SimTurntableTest, BacklashWhenApproachingFromAbove) {
  TurntableConfig cfg;
  cfg.repeatability_deg = 0.0;
  cfg.backlash_deg = 0.25;
  Make(cfg);
  OpenAndHome();
  ASSERT_TRUE(tt_->StartMoveTo(90.0).ok());
  EXPECT_EQ(WaitInPosition().angle_deg, 90.0);
  ASSERT_TRUE(tt_->StartMoveTo(60.0).ok());  // reversal
  EXPECT_NEAR(WaitInPosition().angle_deg, 60.25, 1e-12);
  ASSERT_TRUE(tt_->StartMoveTo(30.0).ok());  // same direction: same lost motion
  EXPECT_NEAR(WaitInPosition().angle_deg, 30.25, 1e-12);
  ASSERT_TRUE(tt_->StartMoveTo(45.0).ok());  // reversal back
  EXPECT_NEAR(WaitInPosition().angle_deg, 45.0, 1e-12);
}

TEST_F(SimTurntableTest, RepeatabilityMatchesSigma) {
  TurntableConfig cfg;
  cfg.repeatability_deg = 0.05;
  cfg.max_speed_deg_s = 600;
  cfg.accel_deg_s2 = 6000;
  Make(cfg, 99);
  OpenAndHome();
  double sum = 0, sum2 = 0;
  const int n = 400;
  for (int i = 1; i <= n; ++i) {
    ASSERT_TRUE(tt_->StartMoveTo(30.0 * i).ok());
    const double e = WaitInPosition().angle_deg - 30.0 * i;
    sum += e;
    sum2 += e * e;
  }
  const double mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
  EXPECT_NEAR(mean, 0.0, 4 * 0.05 / std::sqrt(n));
  EXPECT_NEAR(sd, 0.05, 0.008);
}

TEST_F(SimTurntableTest, StallFreezesMotionAndNeverReachesPosition) {
  TurntableConfig cfg;
  cfg.faults.stall_at_deg = 45.0;
  Make(cfg);
  OpenAndHome();
  ASSERT_TRUE(tt_->StartMoveTo(30.0).ok());  // short of the stall point
  EXPECT_NEAR(WaitInPosition().angle_deg, 30.0, 0.5);
  ASSERT_TRUE(tt_->StartMoveTo(90.0).ok());
  Advance(5 * kNsPerSec);
  auto st = tt_->ReadStatus();
  ASSERT_TRUE(st.ok());
  EXPECT_TRUE(st->moving);
  EXPECT_FALSE(st->in_position);
  EXPECT_EQ(st->angle_deg, 45.0);
  Advance(5 * kNsPerSec);
  EXPECT_EQ(tt_->ReadStatus()->angle_deg,
            45.0);  // position does not advance: the daemon's stall signal
  EXPECT_TRUE(tt_->ReadStatus()->moving);
  ASSERT_TRUE(tt_->Stop().ok());
  EXPECT_FALSE(tt_->ReadStatus()->moving);
  EXPECT_FALSE(tt_->ReadStatus()->in_position);
}

TEST_F(SimTurntableTest, TimeoutEveryNthMoveUntilHomed) {
  TurntableConfig cfg;
  cfg.faults.timeout_every_n_moves = 3;
  Make(cfg);
  OpenAndHome();
  ASSERT_TRUE(tt_->StartMoveTo(30.0).ok());
  WaitInPosition();
  ASSERT_TRUE(tt_->StartMoveTo(60.0).ok());
  WaitInPosition();
  Status s = tt_->StartMoveTo(90.0);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kTimeout);
  EXPECT_EQ(s.error().message,
            "sim turntable: no answer to status request (communication timeout)");
  for (int i = 0; i < 3; ++i) {
    auto st = tt_->ReadStatus();
    ASSERT_FALSE(st.ok());
    EXPECT_EQ(st.error().cls, ErrorClass::kTimeout);
    Advance(kNsPerSec);
  }
  EXPECT_EQ(tt_->Stop().error().cls, ErrorClass::kTimeout);
  // Re-homing resets the controller; the count goes on (6th move times out).
  ASSERT_TRUE(tt_->StartHome().ok());
  WaitInPosition();
  for (double a : {30.0, 60.0}) {
    ASSERT_TRUE(tt_->StartMoveTo(a).ok());
    WaitInPosition();
  }
  EXPECT_EQ(tt_->StartMoveTo(90.0).error().cls, ErrorClass::kTimeout);
  // Reopening also clears it.
  tt_->Close();
  ASSERT_TRUE(tt_->Open().ok());
  EXPECT_TRUE(tt_->ReadStatus().ok());
}

TEST_F(SimTurntableTest, DisconnectAfterTime) {
  TurntableConfig cfg;
  cfg.faults.disconnect_after = 10 * kNsPerSec;
  Make(cfg);
  Advance(kNsPerSec);  // the timer starts at Open, not at construction
  OpenAndHome();
  ASSERT_TRUE(tt_->StartMoveTo(30.0).ok());
  WaitInPosition();
  clock_.AdvanceTo(11 * kNsPerSec - 1);
  EXPECT_TRUE(tt_->ReadStatus().ok());
  Advance(1);
  auto st = tt_->ReadStatus();
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().cls, ErrorClass::kDisconnected);
  EXPECT_EQ(st.error().message, "sim turntable disconnected: check the cable / USB connection");
  EXPECT_EQ(tt_->StartHome().error().cls, ErrorClass::kDisconnected);
  EXPECT_EQ(tt_->StartMoveTo(60).error().cls, ErrorClass::kDisconnected);
  EXPECT_EQ(tt_->Stop().error().cls, ErrorClass::kDisconnected);
  // Plugged back in: a reopened controller answers and must be homed again.
  tt_->Close();
  ASSERT_TRUE(tt_->Open().ok());
  auto again = tt_->ReadStatus();
  ASSERT_TRUE(again.ok());
  EXPECT_FALSE(again->homed);
  EXPECT_EQ(tt_->StartMoveTo(60).error().cls, ErrorClass::kInvalidState);
}

TEST_F(SimTurntableTest, RetargetDuringMoveAndInfo) {
  Make(TurntableConfig{});
  EXPECT_EQ(tt_->Info().backend, "sim");
  OpenAndHome();
  ASSERT_TRUE(tt_->StartMoveTo(90.0).ok());
  Advance(500 * kNsPerMs);
  const double mid = tt_->MeasuredAngle();
  ASSERT_TRUE(tt_->StartMoveTo(10.0).ok());
  EXPECT_NEAR(tt_->MeasuredAngle(), mid, 1e-9);  // no jump at the new command
  EXPECT_NEAR(WaitInPosition().angle_deg, 10.0, 4 * 0.05 + 0.1);
}

}  // namespace
}  // namespace aggscan::sim
