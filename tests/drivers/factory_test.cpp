// Explicit device factory: backend names from the config.
#include "drivers/factory.h"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <vector>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/sim/sim_button.h"
#include "drivers/sim/sim_camera.h"
#include "drivers/sim/sim_hand.h"
#include "drivers/sim/sim_turntable.h"
#include "drivers/sim/sim_walker.h"

namespace aggscan {
namespace {

TEST(Factory, UnknownBackendNamesTheKeyAndTheKnownOnes) {
  VirtualClock clock;
  Config c;
  c.camera.backend = "foo";
  auto r = CreateRig(c, clock);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_EQ(r.error().message,
            "camera.backend \"foo\" is not known; available: sim, v4l2, libcamera");

  c = Config{};
  c.turntable.backend = "usb";
  c.button.backend = "knob";
  r = CreateRig(c, clock);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().message,
            "turntable.backend \"usb\" is not known; available: sim, modbus-tcp, modbus-rtu, "
            "usb-tic, manual; "
            "button.backend \"knob\" is not known; available: sim, gpio, evdev, modbus");
}

// A table turned by hand: every move completes at once and nothing is
// measured; with the sim camera, the sim's hand turns the platter it draws.
TEST(Factory, ManualTurntableCompletesAtOnceAndMeasuresNothing) {
  VirtualClock clock;
  Config c;
  c.turntable.backend = "manual";
  Result<RigDevices> r = CreateRig(c, clock);
  ASSERT_TRUE(r) << r.error().ToString();
  Turntable& t = *r->turntable;
  EXPECT_EQ(t.Info().backend, "manual");
  ASSERT_TRUE(t.Open().ok());
  ASSERT_TRUE(t.StartHome().ok());
  ASSERT_TRUE(t.StartMoveTo(30.0).ok());
  auto st = t.ReadStatus();
  ASSERT_TRUE(st);
  EXPECT_TRUE(st->in_position && st->homed && !st->moving);
  EXPECT_FALSE(st->angle_measured);
  EXPECT_DOUBLE_EQ(st->angle_deg, 30.0);
  t.Close();
}

// The sim's hand: reaction, a smooth turn by the step +- the error, and a
// late turn whose middle falls on the next view's mid-exposure.
TEST(SimHand, TurnsByTheStepWithinTheErrorAndIsLateWhenTold) {
  VirtualClock clock;
  Config c;
  c.sim.hand_angle_error_deg = 5.0;
  c.sim.hand_late_every = 2;
  sim::SimHand hand(clock, c);
  const double start = hand.AngleAt(0);
  EXPECT_LE(std::abs(start), 15.0);
  hand.Turn(0.0, 30.0);
  EXPECT_DOUBLE_EQ(hand.AngleAt(c.sim.hand_reaction_min - 1), start) << "not before its reaction";
  const TimeNs done = c.sim.hand_reaction_max + c.sim.hand_turn_max;
  const double first = hand.AngleAt(done) - start;
  EXPECT_GE(first, 25.0);
  EXPECT_LE(first, 35.0);
  // The second turn is late: prompted 2 s later, it is under way at the next
  // view's mid-exposure (4 s + half the shutter), not before.
  clock.AdvanceTo(2 * kNsPerSec);
  hand.Turn(30.0, 60.0);
  const TimeNs mid = 2 * kNsPerSec + c.capture.interval +
                     static_cast<TimeNs>(c.camera.exposure.exposure_us * 500.0);
  EXPECT_DOUBLE_EQ(hand.AngleAt(mid - c.sim.hand_turn_max / 2 - 1), start + first);
  const double during = hand.AngleAt(mid) - (start + first);
  EXPECT_GT(during, 5.0);
  EXPECT_LT(during, 30.0);
  EXPECT_EQ(hand.turns(), 2);
  EXPECT_EQ(hand.late_turns(), 1);
  // The function the camera keeps outlives the hand.
  auto f = hand.AngleFunction();
  EXPECT_DOUBLE_EQ(f(mid), hand.AngleAt(mid));
}

// The sim's walker: a rough ring of camera positions round the still disc,
// elevations alternating about the tripod's, a new round at each homing,
// shuffled when asked, each taken after the reaction and walk times.
TEST(SimWalker, WalksARoughRingInAShuffledOrder) {
  VirtualClock clock;
  Config c;
  c.capture.views_per_side = 12;
  c.capture.step_deg = 30;
  c.sim.walk_shuffle = true;
  sim::SimWalker walker(clock, c);
  walker.Home();
  auto centre = [](const sim::Rigid& w2c) { return w2c.Inverse().t; };
  auto polar = [&](const sim::Rigid& w2c, double* az, double* el, double* dist) {
    const sim::Vec3 C = w2c.Inverse().t - sim::Vec3{0, 0, sim::kAimHeightMm};
    *dist = sim::Norm(C);
    *el = std::atan2(C.z, std::hypot(C.x, C.y)) * 180 / M_PI;
    *az = std::atan2(C.x, -C.y) * 180 / M_PI;
  };
  std::set<int> seen;
  std::vector<sim::Rigid> ring;
  for (int j = 0; j < 12; ++j) ring.push_back(walker.PositionOfCurrentSide(j));
  for (int j = 0; j < 12; ++j) {
    double az = 0, el = 0, dist = 0;
    polar(ring[j], &az, &el, &dist);
    // The plan's angle turned the other way round, +-6 deg.
    EXPECT_LT(std::abs(std::remainder(az + 30.0 * j, 360.0)), 6.5) << j;
    const double want_el = c.sim.camera_elevation_deg + (j % 2 ? 12.0 : -12.0);
    EXPECT_LT(std::abs(el - want_el), 6.0) << j;  // the aim point moves the centre's elevation too
    // +-8 %, and the aim point's +-12 mm.
    EXPECT_LT(std::abs(dist / c.sim.camera_distance_mm - 1.0), 0.08 + 20.0 / 650) << j;
  }
  EXPECT_DOUBLE_EQ(centre(walker.CameraAt(clock.Now())).z, centre(ring[0]).z);
  int out_of_order = 0;
  for (int k = 1; k < 12; ++k) {
    clock.AdvanceTo(k * 2 * kNsPerSec);
    walker.Step();
    const TimeNs before = clock.Now() + c.sim.hand_reaction_min - 1;
    const TimeNs after = clock.Now() + c.sim.hand_reaction_max + c.sim.hand_turn_max;
    const sim::Rigid at = walker.CameraAt(after);
    EXPECT_NE(centre(walker.CameraAt(before)).x, centre(at).x) << "moved before the reaction";
    int which = -1;
    for (int j = 0; j < 12; ++j)
      if (centre(ring[j]).x == centre(at).x && centre(ring[j]).y == centre(at).y) which = j;
    ASSERT_GE(which, 1) << k;
    seen.insert(which);
    if (which != k) ++out_of_order;
  }
  EXPECT_EQ(seen.size(), 11u) << "every position once";
  EXPECT_GT(out_of_order, 5);
  // A new side: a new round.
  const sim::Vec3 before = centre(walker.PositionOfCurrentSide(3));
  walker.Home();
  EXPECT_NE(centre(walker.PositionOfCurrentSide(3)).x, before.x);
  auto f = walker.CameraFunction();
  EXPECT_EQ(centre(f(clock.Now())).x, centre(walker.CameraAt(clock.Now())).x);
}

TEST(Factory, ModbusTurntableFromConfigAndProfile) {
  VirtualClock clock;
  Config c;
  const std::string rock = ::testing::TempDir() + "/factory_rock_mb.obj";
  std::ofstream(rock) << "v 60 0 0\nv -60 0 0\nv 0 35 0\nv 0 -35 0\nv 0 0 25\nv 0 0 -25\n"
                         "f 1 3 5\nf 3 2 5\nf 2 4 5\nf 4 1 5\nf 3 1 6\nf 2 3 6\nf 4 2 6\nf 1 4 6\n";
  c.sim.rock_mesh = rock;
  c.turntable.backend = "modbus-rtu";
  c.turntable.modbus.device = "/dev/ttyUSB7";
  c.turntable.modbus.profile_dir = std::string(AGGSCAN_SOURCE_DIR) + "/config/turntables";
  c.turntable.modbus.profile = "leadshine-iem-rs";
  auto r = CreateRig(c, clock);
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->turntable->Info().backend, "modbus-rtu");
  EXPECT_EQ(r->turntable->Info().id, "/dev/ttyUSB7/1");
  EXPECT_NE(r->turntable->Info().model.find("Leadshine"), std::string::npos);
  EXPECT_FALSE(r->turntable->is_open());  // created, not opened: no device needed yet

  // A profile that is not there stops the rig with the file named.
  c.turntable.backend = "modbus-tcp";
  c.turntable.modbus.host = "127.0.0.1";
  c.turntable.modbus.profile = "no-such-controller";
  r = CreateRig(c, clock);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_NE(r.error().message.find("config/turntables/no-such-controller.toml"), std::string::npos)
      << r.error().message;
  std::filesystem::remove(rock);
}

TEST(Factory, AllSimSharesOneWorld) {
  VirtualClock clock;
  Config c;
  // A small rock from a file keeps world construction quick (the procedural
  // rock is tested with the world itself): an elongated octahedron, 8 faces.
  const std::string rock = ::testing::TempDir() + "/factory_rock.obj";
  std::ofstream(rock) << "v 60 0 0\nv -60 0 0\nv 0 35 0\nv 0 -35 0\nv 0 0 25\nv 0 0 -25\n"
                         "f 1 3 5\nf 3 2 5\nf 2 4 5\nf 4 1 5\nf 3 1 6\nf 2 3 6\nf 4 2 6\nf 1 4 6\n";
  c.sim.rock_mesh = rock;
  auto r = CreateRig(c, clock);
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_NE(r->world, nullptr);
  ASSERT_NE(r->camera, nullptr);
  ASSERT_NE(r->turntable, nullptr);
  ASSERT_NE(r->button, nullptr);
  EXPECT_NE(dynamic_cast<sim::SimTurntable*>(r->turntable.get()), nullptr);
  EXPECT_NE(dynamic_cast<sim::SimCamera*>(r->camera.get()), nullptr);
  EXPECT_NE(dynamic_cast<sim::SimButton*>(r->button.get()), nullptr);
  EXPECT_EQ(r->turntable->Info().backend, "sim");
  EXPECT_EQ(r->camera->Info().backend, "sim");
  EXPECT_EQ(r->camera->state(), Camera::State::kClosed);  // created, not opened
  EXPECT_FALSE(r->turntable->is_open());
  std::filesystem::remove(rock);
}

}  // namespace
}  // namespace aggscan

namespace aggscan {
namespace {

TEST(Factory, DefaultConfigBuildsTheProceduralRig) {
  VirtualClock clock;
  auto r = CreateRig(Config{}, clock);
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_NE(r->world, nullptr);
}

}  // namespace
}  // namespace aggscan
