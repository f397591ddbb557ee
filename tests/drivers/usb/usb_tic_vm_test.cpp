// The USB turntable backend against the emulated Tic (tic_gadget.cpp) on
// dummy_hcd, inside the VM lane (tic_vm.sh sets the environment): hotplug and
// error classification. The contract suite runs there too
// (turntable_contract_test, backend usb_tic).
//
//   AGGSCAN_TIC_SERIAL       the gadget's serial number
//   AGGSCAN_TIC_UDC_FILE     the gadget's configfs UDC file (unbind = unplug)
//   AGGSCAN_TIC_UDC          the UDC to bind it to again (re-plug)
//   AGGSCAN_TIC_GADGET_PID   the gadget program (SIGUSR1: motor driver error)
//   AGGSCAN_TIC_UDEVD        set when a udev daemon runs (libusb hotplug events flow)
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <signal.h>

#include <algorithm>
#include <chrono>
#include <cstdlib>
#include <fstream>
#include <string>
#include <thread>

#include "drivers/usb/usb_tic_turntable.h"
#include "tests/scenario/process.h"

namespace aggscan {
namespace {

using ::testing::HasSubstr;
using Clock = std::chrono::steady_clock;

std::string Env(const char* name) {
  const char* v = std::getenv(name);
  return v ? v : "";
}

class UsbTicVm : public ::testing::Test {
 protected:
  void SetUp() override {
    serial_ = Env("AGGSCAN_TIC_SERIAL");
    if (serial_.empty()) GTEST_SKIP() << "not in the VM lane (tests/drivers/usb/tic_vm.sh)";
    cfg_.backend = "usb-tic";
    cfg_.usb.serial_number = serial_;
    cfg_.usb.microsteps = 8;
    cfg_.max_speed_deg_s = 180;
    cfg_.accel_deg_s2 = 720;
    cfg_.usb.timeout = 2 * kNsPerSec;  // QEMU/TCG under CI load can pause the guest a moment
  }
  void TearDown() override { Plug(true); }

  // Binds or unbinds the gadget: a cable plugged in or pulled.
  void Plug(bool in) {
    if (serial_.empty() || plugged_ == in) return;
    std::ofstream(Env("AGGSCAN_TIC_UDC_FILE")) << (in ? Env("AGGSCAN_TIC_UDC") : "") << "\n";
    plugged_ = in;
  }

  void HomeAndWait(Turntable& t) {
    ASSERT_TRUE(t.StartHome().ok());
    const auto deadline = Clock::now() + std::chrono::seconds(20);
    while (Clock::now() < deadline) {
      auto st = t.ReadStatus();
      ASSERT_TRUE(st.ok()) << st.error().ToString();
      if (st->in_position) {
        EXPECT_TRUE(st->homed);
        EXPECT_FALSE(st->alarm);
        return;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    FAIL() << "homing did not finish";
  }

  // Moves to `angle` and polls until in position; *lo / *hi: the least and
  // greatest angle reported on the way (the end included).
  void MoveAndTrack(Turntable& t, double angle, double* lo, double* hi, TurntableStatus* end) {
    ASSERT_TRUE(t.StartMoveTo(angle).ok());
    *lo = 1e9;
    *hi = -1e9;
    Result<TurntableStatus> st = MakeError(ErrorClass::kInternal, "not polled");
    const auto deadline = Clock::now() + std::chrono::seconds(10);
    do {
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      st = t.ReadStatus();
      ASSERT_TRUE(st.ok()) << st.error().ToString();
      *lo = std::min(*lo, st->angle_deg);
      *hi = std::max(*hi, st->angle_deg);
    } while (!st->in_position && Clock::now() < deadline);
    ASSERT_TRUE(st->in_position) << "not in position at " << angle << " deg: " << st->angle_deg;
    *end = *st;
  }

  std::string serial_;
  TurntableConfig cfg_;
  bool plugged_ = true;
};

TEST_F(UsbTicVm, UnplugWhileOpenIsDisconnectedAndReplugReopens) {
  usb::UsbTicTurntable t(cfg_);
  ASSERT_TRUE(t.Open().ok());
  HomeAndWait(t);
  ASSERT_TRUE(t.StartMoveTo(90).ok());

  Plug(false);
  // Give the host (and udev, where it runs) a moment to notice the unplug.
  std::this_thread::sleep_for(std::chrono::milliseconds(1500));
  auto gone = t.ReadStatus();
  ASSERT_FALSE(gone.ok()) << "ReadStatus still answered 1.5 s after the unplug";
  EXPECT_EQ(gone.error().cls, ErrorClass::kDisconnected) << gone.error().ToString();
  EXPECT_THAT(gone.error().message, HasSubstr("serial " + serial_));
  // With a udev daemon running, libusb's hotplug event told the backend
  // before any transfer failed.
  if (!Env("AGGSCAN_TIC_UDEVD").empty()) {
    EXPECT_EQ(t.hotplug_departures(), 1);
  }
  // Still away: disconnected, saying what to check.
  auto away = t.ReadStatus();
  ASSERT_FALSE(away.ok());
  EXPECT_EQ(away.error().cls, ErrorClass::kDisconnected) << away.error().ToString();
  EXPECT_THAT(away.error().message, HasSubstr("1ffb"));
  EXPECT_EQ(t.StartMoveTo(10).error().cls, ErrorClass::kDisconnected);

  // Re-plug: the next requests find it again; its position is unknown now.
  Plug(true);
  Result<TurntableStatus> back = MakeError(ErrorClass::kInternal, "not polled");
  const auto replug_deadline = Clock::now() + std::chrono::seconds(10);
  while (Clock::now() < replug_deadline) {
    back = t.ReadStatus();
    if (back.ok()) break;
    EXPECT_EQ(back.error().cls, ErrorClass::kDisconnected) << back.error().ToString();
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  ASSERT_TRUE(back.ok()) << "not back 10 s after re-plug: " << back.error().ToString();
  EXPECT_FALSE(back->homed);
  EXPECT_EQ(t.StartMoveTo(10).error().cls, ErrorClass::kInvalidState);
  HomeAndWait(t);
  ASSERT_TRUE(t.StartMoveTo(45).ok());
  t.Close();
}

TEST_F(UsbTicVm, OpenWithoutTheDeviceIsMissingAndNamesTheSelection) {
  Plug(false);
  // Wait until the host has dropped it (the hub notices the disconnect).
  usb::UsbTicTurntable t(cfg_);
  Status s = OkStatus();
  const auto deadline = Clock::now() + std::chrono::seconds(5);
  do {
    s = t.Open();
    if (s) t.Close();
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  } while (s && Clock::now() < deadline);
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing) << s.error().ToString();
  EXPECT_THAT(s.error().message, HasSubstr("Tic (USB 1ffb:any Tic model, serial " + serial_ + ")"));
  EXPECT_THAT(s.error().message, HasSubstr("not found"));
  EXPECT_THAT(s.error().message, HasSubstr("lsusb"));

  // Another serial number, device present: missing too.
  Plug(true);
  TurntableConfig other = cfg_;
  other.usb.serial_number = "00999999";
  usb::UsbTicTurntable wrong(other);
  Status w = wrong.Open();
  ASSERT_FALSE(w.ok());
  EXPECT_EQ(w.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_THAT(w.error().message, HasSubstr("serial 00999999"));
  // Re-plugged, the right one opens.
  const auto open_deadline = Clock::now() + std::chrono::seconds(10);
  Status again = t.Open();
  while (!again && Clock::now() < open_deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    again = t.Open();
  }
  EXPECT_TRUE(again.ok()) << again.error().ToString();
}

TEST_F(UsbTicVm, MotorDriverErrorIsAnAlarmAndHomingRecovers) {
  usb::UsbTicTurntable t(cfg_);
  ASSERT_TRUE(t.Open().ok());
  HomeAndWait(t);
  const int pid = std::atoi(Env("AGGSCAN_TIC_GADGET_PID").c_str());
  ASSERT_GT(pid, 0);
  ASSERT_EQ(kill(pid, SIGUSR1), 0);
  Result<TurntableStatus> st = MakeError(ErrorClass::kInternal, "not polled");
  const auto deadline = Clock::now() + std::chrono::seconds(5);
  do {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    st = t.ReadStatus();
    ASSERT_TRUE(st.ok()) << st.error().ToString();
  } while (!st->alarm && Clock::now() < deadline);
  ASSERT_TRUE(st->alarm);
  EXPECT_THAT(st->alarm_text, HasSubstr("motor driver error"));
  EXPECT_EQ(st->alarm_code, 1 << 1);
  Status move = t.StartMoveTo(30);
  ASSERT_FALSE(move.ok());
  EXPECT_EQ(move.error().cls, ErrorClass::kDeviceFault);
  EXPECT_THAT(move.error().message, HasSubstr("home again"));
  HomeAndWait(t);  // clears the driver error
  ASSERT_TRUE(t.StartMoveTo(30).ok());
}

// No homing switch (home = "here": angle 0 where it stands) and the shorter
// way round: 350 deg is reached by going 10 deg back, never through 180.
TEST_F(UsbTicVm, HomeHereAndShortestPath) {
  cfg_.usb.home = "here";
  cfg_.usb.shortest_path = true;
  usb::UsbTicTurntable t(cfg_);
  ASSERT_TRUE(t.Open().ok());
  HomeAndWait(t);
  double lo = 0, hi = 0;
  TurntableStatus st;
  ASSERT_NO_FATAL_FAILURE(MoveAndTrack(t, 350, &lo, &hi, &st));
  EXPECT_NEAR(st.angle_deg, 350.0, 360.0 / 1600 / 2 + 1e-9);  // the nearest microstep
  EXPECT_GE(lo, 349.9);  // reported cumulatively: from 360 down to 350
  EXPECT_LE(hi, 360.1);
}

// Backlash compensation, approach "positive": every target is reached going
// up. A move down first goes 5 deg past the target, then back up; in position
// only after that. Shortest path on too: angles stay cumulative through it.
TEST_F(UsbTicVm, BacklashCompensationApproachesFromOneSide) {
  cfg_.usb.backlash_comp_deg = 5;
  cfg_.usb.backlash_approach = "positive";
  cfg_.usb.shortest_path = true;
  usb::UsbTicTurntable t(cfg_);
  ASSERT_TRUE(t.Open().ok());
  HomeAndWait(t);
  constexpr double kMicrostep = 360.0 / 1600;  // 200 steps x 8 microsteps per turn
  double lo = 0, hi = 0;
  TurntableStatus st;
  ASSERT_NO_FATAL_FAILURE(MoveAndTrack(t, 90, &lo, &hi, &st));  // up: straight there
  EXPECT_NEAR(st.angle_deg, 90.0, kMicrostep);
  EXPECT_LE(hi, 90.0 + kMicrostep);

  // Down: to 40, then up to 45. The turn-around is seen by a status read (it
  // starts the second leg), so the least angle reported is 40.
  ASSERT_NO_FATAL_FAILURE(MoveAndTrack(t, 45, &lo, &hi, &st));
  EXPECT_NEAR(st.angle_deg, 45.0, kMicrostep);
  EXPECT_NEAR(lo, 40.0, kMicrostep);
  EXPECT_LE(hi, 90.0 + kMicrostep);

  // Up again: no overshoot, no dip.
  ASSERT_NO_FATAL_FAILURE(MoveAndTrack(t, 90, &lo, &hi, &st));
  EXPECT_NEAR(st.angle_deg, 90.0, kMicrostep);
  EXPECT_LE(hi, 90.0 + kMicrostep);
  EXPECT_GE(lo, 45.0 - kMicrostep);

  // 350 the shorter way is 100 deg down: past it to 345, then up to 350.
  // The whole turn is in the offset from the start, so the angles reported
  // run from 450 (90 + a turn) down to 345 (never near 0 or -10).
  ASSERT_NO_FATAL_FAILURE(MoveAndTrack(t, 350, &lo, &hi, &st));
  EXPECT_NEAR(st.angle_deg, 350.0, kMicrostep);
  EXPECT_NEAR(lo, 345.0, kMicrostep);
  EXPECT_LE(hi, 450.0 + kMicrostep);
}

// The real aggscand with its turntable on the emulated Tic: GET /api/v1/health
// and `aggscan selftest` follow an unplug and a re-plug by themselves.
TEST_F(UsbTicVm, DaemonHealthFollowsUnplugAndReplug) {
  using json = nlohmann::json;
  std::ifstream flags("/sys/class/net/lo/flags");
  unsigned lo_flags = 0;
  flags >> std::hex >> lo_flags;
  if (!(lo_flags & 1u)) GTEST_SKIP() << "loopback is down in the guest (no ip/ifconfig?)";
  test::TempDir dir;
  const std::string config = dir.path() + "/usb.toml";
  std::ofstream(config)
      << "[daemon]\nstate_dir = \"" << dir.path() << "/state\"\nlisten_port = 0\n"
      << "reopen_backoff_min = \"100ms\"\nreopen_backoff_max = \"400ms\"\n"
      << "health_probe_interval = \"200ms\"\n\n[camera]\nwidth = 640\nheight = 480\n\n"
      << "[turntable]\nbackend = \"usb-tic\"\nmax_speed_deg_s = 180.0\naccel_deg_s2 = 720.0\n"
      << "[turntable.usb]\nserial_number = \"" << serial_
      << "\"\nmicrosteps = 8\ntimeout = \"2s\"\n";
  test::Daemon d(config, dir.path());
  ASSERT_TRUE(d.ok()) << test::ReadAll(d.log());
  auto turntable_state = [&](json* h) {
    *h = d.Get("/api/v1/health");
    return h->is_object() ? (*h)["devices"]["turntable"].value("state", "") : std::string();
  };
  auto wait_state = [&](auto pred, int seconds, json* h) {
    const auto deadline = Clock::now() + std::chrono::seconds(seconds);
    while (Clock::now() < deadline) {
      if (pred(turntable_state(h))) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    return false;
  };
  json h;
  ASSERT_TRUE(wait_state([](const std::string& s) { return s == "ok"; }, 20, &h))
      << h.dump() << test::ReadAll(d.log());
  EXPECT_EQ(h["devices"]["turntable"]["backend"], "usb-tic") << h.dump();

  Plug(false);
  ASSERT_TRUE(wait_state([](const std::string& s) { return !s.empty() && s != "ok"; }, 10, &h))
      << h.dump();
  // Disconnected while open; once the daemon reopens it, missing: both name it.
  const std::string state = h["devices"]["turntable"]["state"];
  EXPECT_TRUE(state == "disconnected" || state == "device_missing") << h.dump();
  const std::string msg = h["devices"]["turntable"]["message"];
  EXPECT_THAT(msg, HasSubstr("1ffb")) << msg;
  EXPECT_THAT(msg, HasSubstr("serial " + serial_)) << msg;
  const std::string cli_log = dir.path() + "/cli.log";
  const int rc =
      test::WaitExit(test::Spawn({test::Bin("cli/aggscan"), "--url",
                                  "http://127.0.0.1:" + std::to_string(d.port()), "selftest"},
                                 cli_log));
  EXPECT_EQ(rc, 4) << test::ReadAll(cli_log);
  EXPECT_THAT(test::ReadAll(cli_log), HasSubstr("turntable: FAIL"));

  Plug(true);
  EXPECT_TRUE(wait_state([](const std::string& s) { return s == "ok"; }, 20, &h))
      << h.dump() << test::ReadAll(d.log());
}

}  // namespace
}  // namespace aggscan
