// The GPIO button and light backends against the kernel's gpio-sim driver,
// and the issue's proof that a simulated press starts a capture in the real
// aggscand. Meant to run inside the throwaway VM of tests/vm/run-in-vm.sh
// (gpio-sim built out of tree, loaded with --modprobe gpio-sim, configfs on
// /sys/kernel/config); exits 77 (skipped) where gpio-sim is not there.
//
// The chip (tests/drivers/gpio_sim_chip.h): bank0 with 4 lines, line 0
// named "start" (the button) and line 1 "lamp" (the light). A press is
// gpio-sim's simulated pull; the light's output level is read back from
// sim_gpioN/value.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstring>
#include <fstream>
#include <mutex>
#include <string>
#include <thread>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/gpio/gpio_button.h"
#include "drivers/gpio/gpio_light.h"
#include "tests/drivers/gpio_sim_chip.h"
#include "tests/scenario/process.h"
#include "tests/util/eventually.h"

namespace aggscan::gpio {
namespace {

namespace gpiosim = test::gpiosim;
using test::Eventually;
using test::WriteFile;

gpiosim::Chip g_sim;                     // the simulated bank, made in main()
const std::string& g_chip = g_sim.name;  // "gpiochipN"

// The simulated level of a line's input (what a switch would do to it).
void Pull(int offset, bool high) { ASSERT_TRUE(gpiosim::SetPull(g_sim, offset, high)); }
int Value(int offset) { return gpiosim::Value(g_sim, offset); }

ButtonConfig Config(const std::string& line, bool active_low, TimeNs debounce,
                    const std::string& bias = "as-is") {
  ButtonConfig c;
  c.backend = "gpio";
  c.debounce = debounce;
  c.gpio.chip = g_chip;
  c.gpio.line = line;
  c.gpio.active_low = active_low;
  c.gpio.bias = bias;
  return c;
}

// Counts the presses a button delivers.
struct Presses {
  std::atomic<int> n{0};
  std::string source;
  std::mutex mu;
  PressCallback cb() {
    return [this](const ButtonPress& p) {
      std::lock_guard<std::mutex> l(mu);
      source = p.source;
      ++n;
    };
  }
};

TEST(GpioSim, PressIsTheRisingEdgeOfTheNamedLine) {
  RealClock clock;
  Pull(0, false);
  GpioButton b(clock, Config("start", false, 20 * kNsPerMs));
  Presses got;
  ASSERT_TRUE(b.Start(got.cb()).ok());
  EXPECT_TRUE(b.Health().ok());
  Pull(0, true);
  ASSERT_TRUE(Eventually([&] { return got.n == 1; })) << "no press seen";
  EXPECT_EQ(got.source, "gpio");
  Pull(0, false);  // release: the falling edge is no press
  ASSERT_TRUE(Eventually([&] { return b.edges_seen() == 2; }));
  std::this_thread::sleep_for(std::chrono::milliseconds(50));  // past the debounce
  Pull(0, true);
  ASSERT_TRUE(Eventually([&] { return b.edges_seen() == 3; }));
  EXPECT_TRUE(Eventually([&] { return got.n == 2; }));
  Pull(0, false);
  ASSERT_TRUE(Eventually([&] { return b.edges_seen() == 4; }));
  EXPECT_EQ(got.n, 2);
  b.Stop();
}

// Sets the simulated input and waits until the button has seen the edge:
// irq_sim merges edges that come faster than its irq_work runs, so a burst
// written at once may reach the kernel as fewer edges.
void Edge(const GpioButton& b, bool high) {
  const int before = b.edges_seen();
  Pull(0, high);
  ASSERT_TRUE(Eventually([&] { return b.edges_seen() == before + 1; })) << "edge not seen";
}

TEST(GpioSim, BounceTrainIsOnePress) {
  RealClock clock;
  Pull(0, false);
  const TimeNs debounce = 1 * kNsPerSec;
  ButtonConfig c = Config("0", false, debounce);
  c.gpio.chip = "/dev/" + g_chip;  // the chip by path, the line by offset
  GpioButton b(clock, c);
  Presses got;
  ASSERT_TRUE(b.Start(got.cb()).ok());
  // A contact closing with bounce: five edges (three of them rising), all
  // within the debounce time.
  const TimeNs t0 = MonotonicNs();
  for (bool high : {true, false, true, false, true}) Edge(b, high);
  ASSERT_LT(MonotonicNs() - t0, debounce) << "the bounce train took longer than the debounce time";
  EXPECT_EQ(b.edges_seen(), 5);
  EXPECT_EQ(got.n, 1);
  // Released with bounce too: no press from the rising bounce edge.
  for (bool high : {false, true, false}) Edge(b, high);
  EXPECT_EQ(got.n, 1);
  // A clean press after a quiet line counts again.
  std::this_thread::sleep_for(std::chrono::nanoseconds(debounce + 100 * kNsPerMs));
  Edge(b, true);
  EXPECT_TRUE(Eventually([&] { return got.n == 2; }));
  Edge(b, false);
  b.Stop();
}

TEST(GpioSim, ActiveLowPressIsTheFallingEdge) {
  RealClock clock;
  // A switch to ground with the pull-up requested on the line: idle high.
  ButtonConfig c = Config("start", true, 20 * kNsPerMs, "pull-up");
  c.gpio.chip = "aggscan-sim";  // the chip by its label
  GpioButton b(clock, c);
  Presses got;
  ASSERT_TRUE(b.Start(got.cb()).ok());
  ASSERT_TRUE(Eventually([&] { return Value(0) == 1; })) << "bias pull-up not applied";
  std::this_thread::sleep_for(std::chrono::milliseconds(50));
  const int before = b.edges_seen();
  Pull(0, false);  // pressed: pulled to ground
  ASSERT_TRUE(Eventually([&] { return got.n == 1; })) << "falling edge not taken as a press";
  Pull(0, true);  // released
  ASSERT_TRUE(Eventually([&] { return b.edges_seen() >= before + 2; }));
  EXPECT_EQ(got.n, 1) << "the rising edge of an active-low button must not press";
  b.Stop();
  Pull(0, false);
}

TEST(GpioSim, BusyMissingAndUnknownLinesAreClassified) {
  RealClock clock;
  GpioButton a(clock, Config("start", false, 20 * kNsPerMs));
  ASSERT_TRUE(a.Start([](const ButtonPress&) {}).ok());
  GpioButton b(clock, Config("start", false, 20 * kNsPerMs));
  Status s = b.Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kConflict);
  EXPECT_NE(s.error().message.find("busy (used by 'aggscan-button')"), std::string::npos)
      << s.error().ToString();
  a.Stop();
  EXPECT_TRUE(b.Start([](const ButtonPress&) {}).ok()) << "the line must be free after Stop()";
  b.Stop();

  GpioButton noline(clock, Config("stop", false, 20 * kNsPerMs));
  s = noline.Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_NE(s.error().message.find("has no line 'stop'; check [button.gpio]"), std::string::npos)
      << s.error().ToString();
  GpioButton far(clock, Config("9", false, 20 * kNsPerMs));
  s = far.Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_NE(s.error().message.find("has 4 lines; no line 9"), std::string::npos)
      << s.error().ToString();

  ButtonConfig c = Config("start", false, 20 * kNsPerMs);
  c.gpio.chip = "gpiochip77";
  GpioButton nochip(clock, c);
  s = nochip.Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_NE(s.error().message.find("no GPIO chip 'gpiochip77'"), std::string::npos)
      << s.error().ToString();
}

TEST(GpioSim, LightLineFollowsThePattern) {
  for (bool active_low : {false, true}) {
    SCOPED_TRACE(active_low ? "active low" : "active high");
    GpioLineConfig c;
    c.chip = g_chip;
    c.line = "lamp";
    c.active_low = active_low;
    const int lit = active_low ? 0 : 1;
    GpioLight light(c);
    ASSERT_TRUE(light.Open().ok());
    EXPECT_EQ(Value(1), 1 - lit) << "dark after open";
    light.Show(LightPattern::kReady);
    EXPECT_TRUE(Eventually([&] { return Value(1) == lit; })) << "ready is steady on";
    light.Show(LightPattern::kOff);
    EXPECT_TRUE(Eventually([&] { return Value(1) == 1 - lit; })) << "off is dark";
    // Blinking: the level goes both ways while the pattern runs.
    light.Show(LightPattern::kFlip);
    EXPECT_TRUE(Eventually([&] { return Value(1) == lit; }));
    EXPECT_TRUE(Eventually([&] { return Value(1) == 1 - lit; }));
    EXPECT_TRUE(Eventually([&] { return Value(1) == lit; }));
    EXPECT_TRUE(light.Health().ok());
    light.Show(LightPattern::kOff);
    EXPECT_TRUE(Eventually([&] { return Value(1) == 1 - lit; })) << "off is dark";
    light.Close();
  }
}

// The issue's proof: the real aggscand with the sim camera and turntable and
// this GPIO button (and lamp); a gpio-sim press starts the armed capture.
TEST(GpioSim, SimulatedPressStartsACaptureInAggscand) {
  using json = nlohmann::json;
  Pull(0, false);
  test::TempDir t;
  const std::string config = test::WriteConfig(
      t.path(),
      "[button]\nbackend = \"gpio\"\ndebounce = \"50ms\"\n[button.gpio]\nchip = \"" + g_chip +
          "\"\nline = \"start\"\n\n[light]\nbackend = \"gpio\"\n[light.gpio]\nchip = \"" + g_chip +
          "\"\nline = \"lamp\"\n\n[turntable]\nmax_speed_deg_s = 360.0\naccel_deg_s2 = 1440.0\n",
      1,
      "profile = \"custom\"\nsides = 1\nviews_per_side = 2\nstep_deg = 90.0\ninterval = \"2s\"\n"
      "settle = \"50ms\"\n");
  test::Daemon d(config, t.path(), 60);
  ASSERT_TRUE(d.ok()) << test::ReadAll(d.log());
  int code = 0;
  json h;
  ASSERT_TRUE(Eventually(
      [&] {
        h = d.Get("/api/v1/health", &code);
        return h.is_object() && h["devices"]["button"].value("state", "") == "ok";
      },
      60))
      << h.dump() << test::ReadAll(d.log());
  EXPECT_EQ(h["devices"]["button"]["backend"], "gpio");
  EXPECT_TRUE(Eventually([&] { return Value(1) == 1; })) << "the lamp shows ready (steady on)";

  json r = d.Post("/api/v1/samples", R"({"id": "rock-gpio"})", &code);
  ASSERT_EQ(code, 200) << r.dump();
  json st = d.Get("/api/v1/status");
  ASSERT_EQ(st["state"], "armed") << st.dump();
  EXPECT_EQ(st["views_captured"], 0);

  Pull(0, true);  // the operator presses start
  ASSERT_TRUE(d.WaitFor([](const json& s) { return s.value("state", "") != "armed"; }, 60, &st))
      << st.dump() << test::ReadAll(d.log());
  EXPECT_EQ(st["side"], 1) << st.dump();
  EXPECT_NE(test::ReadAll(d.log()).find("start button pressed (gpio)"), std::string::npos);
  Pull(0, false);
  // The lamp blinks while the side runs.
  EXPECT_TRUE(Eventually([&] { return Value(1) == 0; }, 60)) << "no blink while capturing";
  ASSERT_TRUE(d.WaitFor(
      [](const json& s) {
        return s.value("state", "") == "idle" && s.value("views_captured", 0) == 2;
      },
      120, &st))
      << st.dump() << test::ReadAll(d.log());
  EXPECT_TRUE(Eventually([&] { return Value(1) == 1; })) << "steady again when idle";
  EXPECT_EQ(d.Stop(), 0);
}

// Last: takes the simulated chip down under a running button, as an
// unplugged USB GPIO adapter would.
TEST(GpioSim, ChipGoneWhileRunningIsADisconnect) {
  RealClock clock;
  GpioButton b(clock, Config("start", false, 20 * kNsPerMs));
  ASSERT_TRUE(b.Start([](const ButtonPress&) {}).ok());
  ASSERT_TRUE(WriteFile(std::string(gpiosim::kChipDir) + "/live", "0"));
  ASSERT_TRUE(Eventually([&] { return !b.Health().ok(); })) << "chip removal not noticed";
  EXPECT_EQ(b.Health().error().cls, ErrorClass::kDisconnected) << b.Health().error().ToString();
  EXPECT_NE(b.Health().error().message.find("stopped delivering edges"), std::string::npos);
  b.Stop();
}

}  // namespace
}  // namespace aggscan::gpio

int main(int argc, char** argv) {
  namespace gpiosim = aggscan::test::gpiosim;
  ::testing::InitGoogleTest(&argc, argv);
  if (!gpiosim::Available()) {
    std::fprintf(stderr,
                 "gpio_sim_test: SKIP: no %s (gpio-sim not loaded or configfs not mounted; "
                 "tests/vm/run-in-vm.sh --modules DIR --modprobe gpio-sim does both in a VM)\n",
                 gpiosim::kConfigfs);
    return 77;
  }
  gpiosim::BringUpLoopback();
  const std::string err = gpiosim::MakeChip(&aggscan::gpio::g_sim);
  if (!err.empty()) {
    std::fprintf(stderr, "gpio_sim_test: cannot create the gpio-sim chip: %s\n", err.c_str());
    return 1;
  }
  std::fprintf(stderr, "gpio_sim_test: gpio-sim chip %s at %s\n", aggscan::gpio::g_sim.name.c_str(),
               aggscan::gpio::g_sim.sysfs.c_str());
  return RUN_ALL_TESTS();
}
