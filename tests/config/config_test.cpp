// Config loading, validation, profiles, durations and the TOML round trip.
#include "config/config.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <filesystem>
#include <string>
#include <vector>

namespace aggscan {
namespace {

using ::testing::HasSubstr;

struct Loaded {
  Result<Config> result;
  std::vector<ConfigProblem> problems;
};

Loaded Load(const std::string& text) {
  std::vector<ConfigProblem> problems;
  Result<Config> r = LoadConfigString(text, "t.toml", &problems);
  return Loaded{std::move(r), std::move(problems)};
}

std::string Dump(const std::vector<ConfigProblem>& problems) {
  std::string s;
  for (const auto& p : problems) s += p.ToString() + "\n";
  return s;
}

// Exactly one problem, on `key` at `line`, whose message contains `text`.
void ExpectOneProblem(const std::string& toml, int line, const std::string& key,
                      const std::string& text) {
  SCOPED_TRACE(toml);
  Loaded l = Load(toml);
  EXPECT_FALSE(l.result.ok());
  ASSERT_EQ(l.problems.size(), 1u) << Dump(l.problems);
  EXPECT_EQ(l.problems[0].file, "t.toml");
  EXPECT_EQ(l.problems[0].line, line);
  EXPECT_EQ(l.problems[0].key, key);
  EXPECT_THAT(l.problems[0].message, HasSubstr(text));
  if (!l.result.ok()) {
    EXPECT_EQ(l.result.error().cls, ErrorClass::kInvalidConfig);
  }
}

TEST(Config, DefaultsAreValid) {
  std::vector<ConfigProblem> problems;
  ValidateConfig(Config{}, "defaults", &problems);
  EXPECT_TRUE(problems.empty()) << Dump(problems);
  Config c;
  ApplyProfile(&c);
  EXPECT_EQ(c, Config{});  // the defaults are the paper profile
}

TEST(Config, EmptyFileGivesDefaults) {
  Loaded l = Load("");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);
  EXPECT_TRUE(l.problems.empty());
  EXPECT_EQ(*l.result, Config{});
}

TEST(Config, ShippedConfigsLoadWithoutProblems) {
  int count = 0;
  for (const auto& entry :
       std::filesystem::directory_iterator(std::string(AGGSCAN_SOURCE_DIR) + "/config")) {
    if (entry.path().extension() != ".toml") continue;
    SCOPED_TRACE(entry.path().string());
    std::vector<ConfigProblem> problems;
    Result<Config> r = LoadConfigFile(entry.path().string(), &problems);
    EXPECT_TRUE(r.ok()) << Dump(problems);
    EXPECT_TRUE(problems.empty()) << Dump(problems);
    ++count;
  }
  EXPECT_GE(count, 2);  // sim.toml and aggscand.toml at least
}

TEST(Config, ShippedConfigsHaveServiceFriendlyValues) {
  std::string dir = std::string(AGGSCAN_SOURCE_DIR) + "/config/";
  Result<Config> sim = LoadConfigFile(dir + "sim.toml", nullptr);
  ASSERT_TRUE(sim.ok());
  EXPECT_EQ(sim->daemon.state_dir, "/tmp/aggscan-sim");
  EXPECT_EQ(sim->daemon.listen_port, 8470);
  EXPECT_EQ(sim->camera.backend, "sim");
  EXPECT_EQ(sim->turntable.backend, "sim");
  EXPECT_EQ(sim->button.backend, "sim");
  EXPECT_GT(sim->daemon.time_scale, 1.0);
  Result<Config> svc = LoadConfigFile(dir + "aggscand.toml", nullptr);
  ASSERT_TRUE(svc.ok());
  EXPECT_EQ(svc->daemon.state_dir, "/var/lib/aggscan");
  EXPECT_EQ(svc->daemon.time_scale, 1.0);
}

TEST(Config, SimTomlListsEveryField) {
  // The shipped sim config is the complete example: loading it must give
  // back what it says, and every key of the effective config appears in it.
  std::string path = std::string(AGGSCAN_SOURCE_DIR) + "/config/sim.toml";
  Result<Config> sim = LoadConfigFile(path, nullptr);
  ASSERT_TRUE(sim.ok());
  std::string text;
  {
    FILE* f = std::fopen(path.c_str(), "r");
    ASSERT_NE(f, nullptr);
    char buf[4096];
    size_t n;
    while ((n = std::fread(buf, 1, sizeof(buf), f)) > 0) text.append(buf, n);
    std::fclose(f);
  }
  std::string dump = ConfigToToml(*sim);
  size_t pos = 0;
  while ((pos = dump.find('\n', pos)) != std::string::npos) {
    size_t end = dump.find('\n', pos + 1);
    std::string line =
        dump.substr(pos + 1, end == std::string::npos ? std::string::npos : end - pos - 1);
    pos = pos + 1;
    if (line.empty()) continue;
    std::string key;
    if (line.rfind("# ", 0) == 0 && line.find(" =   (not set)") != std::string::npos) {
      key = line.substr(2, line.find(' ', 2) - 2);  // optional, shown commented out
    } else if (line[0] != '#' && line[0] != '[') {
      key = line.substr(0, line.find(' '));
    }
    if (!key.empty()) {
      EXPECT_THAT(text, HasSubstr(key + " =")) << "sim.toml does not mention " << key;
    }
  }
}

TEST(Config, SyntaxErrorHasLine) {
  Loaded l = Load("[daemon]\nlisten_port = 8470\nlog_level = \"info\n");
  ASSERT_EQ(l.problems.size(), 1u) << Dump(l.problems);
  EXPECT_EQ(l.problems[0].line, 3);
  EXPECT_THAT(l.problems[0].message, HasSubstr("TOML syntax error"));
  EXPECT_FALSE(l.result.ok());

  Loaded dup = Load("[capture]\nsides = 2\nsides = 2\n");
  ASSERT_EQ(dup.problems.size(), 1u) << Dump(dup.problems);
  EXPECT_EQ(dup.problems[0].line, 3);
}

TEST(Config, UnknownKeyHasLineAndSuggestion) {
  ExpectOneProblem("[capture]\nsides = 2\nviews_per_sid = 30\n", 3, "capture.views_per_sid",
                   "did you mean capture.views_per_side?");
  ExpectOneProblem("\n[capure]\nsides = 2\n", 2, "capure", "did you mean capture?");
  // A transposition is one edit.
  ExpectOneProblem("[camera]\nwidht = 640\n", 2, "camera.widht", "did you mean camera.width?");
  // Right name, wrong table.
  ExpectOneProblem("[camera]\ninterval = \"2s\"\n", 2, "camera.interval",
                   "did you mean capture.interval?");
  // Nothing close: no suggestion.
  Loaded l = Load("[daemon]\ncompletely_unrelated = 1\n");
  ASSERT_EQ(l.problems.size(), 1u);
  EXPECT_EQ(l.problems[0].line, 2);
  EXPECT_THAT(l.problems[0].message, ::testing::Not(HasSubstr("did you mean")));
  // Unknown key inside a marker.
  ExpectOneProblem("[[rig.markers]]\ncolor = \"red\"\ncolour = \"red\"\n", 3,
                   "rig.markers[0].colour", "did you mean color?");
}

TEST(Config, WrongTypeHasLine) {
  ExpectOneProblem("[capture]\nviews_per_side = \"30\"\n", 2, "capture.views_per_side",
                   "expected an integer");
  ExpectOneProblem("[capture]\n\ninterval = 2\n", 3, "capture.interval",
                   "duration string with a unit");
  ExpectOneProblem("[capture]\ninterval = \"2 fortnights\"\n", 2, "capture.interval",
                   "is not a duration");
  ExpectOneProblem("[camera.exposure]\nmanual = 1\n", 2, "camera.exposure.manual",
                   "expected a boolean");
  ExpectOneProblem("[camera]\nwidth = 2016.5\n", 2, "camera.width",
                   "expected an integer, got a float");
  ExpectOneProblem("[daemon]\nstate_dir = 5\n", 2, "daemon.state_dir", "expected a string");
  ExpectOneProblem("camera = 5\n", 1, "camera", "expected a table");
  ExpectOneProblem("[rig]\nmarkers = 5\n", 2, "rig.markers", "expected an array of tables");
  ExpectOneProblem("[sim]\nseed = -1\n", 2, "sim.seed", ">= 0");
  // An integer is a fine float.
  Loaded l = Load("[capture]\nprofile = \"custom\"\nstep_deg = 12\n");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);
  EXPECT_EQ(l.result->capture.step_deg, 12.0);
}

struct RangeCase {
  std::string toml;  // the offending key on line 2
  std::string key;
  std::string text;
};

TEST(Config, V4l2CameraSection) {
  Result<Config> c = LoadConfigString(
      "[camera]\nbackend = \"v4l2\"\ndevice = \"usb-Acme_Cam-video-index0\"\n"
      "[camera.v4l2]\npixel_format = \"yuyv\"\nbuffers = 5\nframe_timeout = \"750ms\"\n"
      "gain_unit = 16\nfocus = 120\nstrict_controls = false\n",
      "t.toml", nullptr);
  ASSERT_TRUE(c.ok()) << c.error().ToString();
  EXPECT_EQ(c->camera.backend, "v4l2");
  EXPECT_EQ(c->camera.v4l2.pixel_format, "yuyv");
  EXPECT_EQ(c->camera.v4l2.buffers, 5);
  EXPECT_EQ(c->camera.v4l2.frame_timeout, 750 * kNsPerMs);
  EXPECT_EQ(c->camera.v4l2.gain_unit, 16);
  EXPECT_EQ(c->camera.v4l2.focus, 120);
  EXPECT_FALSE(c->camera.v4l2.strict_controls);
  // Defaults: MJPEG when offered, strict locking.
  EXPECT_EQ(Config{}.camera.v4l2.pixel_format, "auto");
  EXPECT_TRUE(Config{}.camera.v4l2.strict_controls);
  ExpectOneProblem("[camera.v4l2]\nbufers = 4\n", 2, "camera.v4l2.bufers",
                   "did you mean camera.v4l2.buffers?");
}

// The scaled clock is the sim rig's: it drives a real device's deadlines
// and timers too, so a faster clock with any real device is refused.
TEST(Config, TimeScaleIsRefusedWithARealDevice) {
  ExpectOneProblem(
      "[daemon]\ntime_scale = 10\n[turntable]\nbackend = \"modbus-tcp\"\n"
      "[turntable.modbus]\nhost = \"10.0.0.5\"\n",
      2, "daemon.time_scale",
      "10.0 runs the clock faster than real time, which only the sim rig can follow; "
      "turntable.backend = \"modbus-tcp\" is a real device: set daemon.time_scale = 1");
  ExpectOneProblem(
      "[daemon]\ntime_scale = 2.5\n[camera]\nbackend = \"v4l2\"\ndevice = \"/dev/video0\"\n"
      "[button]\nbackend = \"gpio\"\n",
      2, "daemon.time_scale",
      "camera.backend = \"v4l2\", button.backend = \"gpio\" are real devices");
  ExpectOneProblem("[daemon]\ntime_scale = 20\n[light]\nbackend = \"gpio\"\n", 2,
                   "daemon.time_scale", "light.backend = \"gpio\" is a real device");
  // The all-sim rig may run fast; real devices at time_scale 1 are fine.
  Loaded sim = Load("[daemon]\ntime_scale = 1000\n");
  EXPECT_TRUE(sim.result.ok()) << Dump(sim.problems);
  Loaded real = Load(
      "[daemon]\ntime_scale = 1\n[turntable]\nbackend = \"modbus-rtu\"\n"
      "[turntable.modbus]\ndevice = \"/dev/ttyUSB0\"\n");
  EXPECT_TRUE(real.result.ok()) << Dump(real.problems);
  // The struct validator (what --check-config and the daemon run) agrees.
  Config c;
  c.daemon.time_scale = 10;
  c.turntable.backend = "usb-tic";
  std::vector<ConfigProblem> problems;
  ValidateConfig(c, "struct", &problems);
  ASSERT_EQ(problems.size(), 1u) << Dump(problems);
  EXPECT_EQ(problems[0].key, "daemon.time_scale");
}

// A hand-turned table: the person needs time to turn between the prompt and
// the hands-off moment; a person is not sped up by time_scale, the sim's hand is.
TEST(Config, ManualTurntableNeedsTimeToTurn) {
  Config c;
  c.turntable.backend = "manual";
  std::vector<ConfigProblem> problems;
  ValidateConfig(c, "struct", &problems);
  EXPECT_TRUE(problems.empty()) << Dump(problems);
  c.turntable.manual_hands_off = 1500 * kNsPerMs;  // of a 2 s interval
  c.sim.hand_reaction_max = 100 * kNsPerMs;        // shorter than the minimum
  ValidateConfig(c, "struct", &problems);
  ASSERT_EQ(problems.size(), 2u) << Dump(problems);
  EXPECT_EQ(problems[0].key, "turntable.manual_hands_off");
  EXPECT_NE(problems[0].message.find("to turn the table by hand"), std::string::npos);
  EXPECT_EQ(problems[1].key, "sim.hand_reaction_max");
  problems.clear();
  Config fast;
  fast.turntable.backend = "manual";
  fast.daemon.time_scale = 10;
  ValidateConfig(fast, "struct", &problems);
  EXPECT_TRUE(problems.empty()) << Dump(problems);
  fast.camera.backend = "v4l2";
  ValidateConfig(fast, "struct", &problems);
  ASSERT_EQ(problems.size(), 1u) << Dump(problems);
  EXPECT_NE(problems[0].message.find("turntable.backend = \"manual\""), std::string::npos)
      << Dump(problems);
}

TEST(Config, MovingCameraDrivesNothing) {
  Config c;
  c.capture.mode = "moving_camera";
  std::vector<ConfigProblem> problems;
  ValidateConfig(c, "struct", &problems);
  ASSERT_EQ(problems.size(), 1u) << Dump(problems);
  EXPECT_EQ(problems[0].key, "capture.mode");
  EXPECT_NE(problems[0].message.find("set turntable.backend = \"manual\" (now \"sim\")"),
            std::string::npos)
      << Dump(problems);
  problems.clear();
  c.turntable.backend = "manual";
  ValidateConfig(c, "struct", &problems);
  EXPECT_TRUE(problems.empty()) << Dump(problems);
  auto bad = LoadConfigString("[capture]\nmode = \"walking\"\n", "test.toml", &problems);
  EXPECT_FALSE(bad.ok());
  ASSERT_FALSE(problems.empty());
  EXPECT_EQ(problems[0].key, "capture.mode");
}

TEST(Config, OutOfRangeHasLine) {
  const RangeCase cases[] = {
      {"[capture]\nviews_per_side = 0\nprofile = \"custom\"\n", "capture.views_per_side",
       "must be in 1..360, got 0"},
      {"[capture]\nviews_per_side = 361\nprofile = \"custom\"\n", "capture.views_per_side",
       "1..360"},
      {"[capture]\ninterval = \"0s\"\nprofile = \"custom\"\n", "capture.interval", "must be > 0s"},
      {"[capture]\ninterval = \"-2s\"\nprofile = \"custom\"\n", "capture.interval", "got -2s"},
      {"[capture]\nprofile = \"fast\"\n", "capture.profile", "paper | full-turn | custom"},
      {"[camera]\nwidth = 15\n", "camera.width", "16..16384"},
      {"[camera]\nheight = 16385\n", "camera.height", "16..16384"},
      {"[camera]\njpeg_quality = 0\n", "camera.jpeg_quality", "1..100"},
      {"[camera]\njpeg_quality = 101\n", "camera.jpeg_quality", "1..100"},
      {"[daemon]\ntime_scale = 0.5\n", "daemon.time_scale", "1..1000"},
      {"[daemon]\ntime_scale = 1001\n", "daemon.time_scale", "1..1000"},
      {"[daemon]\nlisten_port = 65536\n", "daemon.listen_port", "0..65535"},
      {"[daemon]\nlisten_port = -1\n", "daemon.listen_port", "0..65535"},
      {"[daemon]\nlog_level = \"verbose\"\n", "daemon.log_level",
       "error | warning | notice | info | debug"},
      {"[daemon]\nstate_dir = \"\"\n", "daemon.state_dir", "must not be empty"},
      {"[sim]\ncamera_elevation_deg = 9\n", "sim.camera_elevation_deg", "10..80"},
      {"[sim]\ncamera_elevation_deg = 80.5\n", "sim.camera_elevation_deg", "10..80"},
      {"[sim]\nrock_unit = \"inch\"\n", "sim.rock_unit", "mm | cm | m"},
      {"[sim]\nk1 = nan\n", "sim.k1", "got nan"},
      {"[camera]\nbackend = \"v4l9\"\n", "camera.backend",
       "unknown camera backend \"v4l9\"; known: sim, v4l2"},
      {"[camera.v4l2]\npixel_format = \"h264\"\n", "camera.v4l2.pixel_format",
       "auto | mjpeg | yuyv | uyvy | nv12 | rgb24 | bgr24 | grey"},
      {"[camera.v4l2]\nbuffers = 1\n", "camera.v4l2.buffers", "2..32"},
      {"[camera.v4l2]\nbuffers = 33\n", "camera.v4l2.buffers", "2..32"},
      {"[camera.v4l2]\nframe_timeout = \"0s\"\n", "camera.v4l2.frame_timeout", "must be > 0s"},
      {"[camera.v4l2]\nfocus = -2\n", "camera.v4l2.focus", "-1..1000000"},
      {"[camera.v4l2]\ngain_unit = -1\n", "camera.v4l2.gain_unit", "0..1000000"},
      {"[turntable]\nbackend = \"modbus\"\n", "turntable.backend",
       "unknown turntable backend \"modbus\"; known: sim, modbus-tcp, modbus-rtu"},
      {"[button]\nbackend = \"gpio9\"\n", "button.backend", "unknown button backend"},
      {"[turntable.faults]\ndisconnect_after = \"0s\"\n", "turntable.faults.disconnect_after",
       "must be > 0s"},
      {"[worker]\nnice = 20\n", "worker.nice", "0..19"},
      {"[worker]\nmax_attempts = 0\n", "worker.max_attempts", "1..100, got 0"},
      {"[worker]\nmax_interruptions = 0\n", "worker.max_interruptions", "1..1000, got 0"},
      {"[mask]\nmethod = \"dnn\"\n", "mask.method", "classical | onnx"},
      {"[mask]\noutput = \"softmax\"\n", "mask.output", "probability | logits"},
      {"[mask]\ninput_width = 4\n", "mask.input_width", "8..4096"},
      {"[mask]\nstd_g = 0\n", "mask.std_g", "must be > 0"},
      {"[mask]\nthreshold = 0\n", "mask.threshold", "must be > 0"},
      {"[mask]\nthreshold = 1\n", "mask.threshold", "must be < 1"},
  };
  for (const auto& c : cases) ExpectOneProblem(c.toml, 2, c.key, c.text);
}

TEST(Config, ModbusTurntableValuesAreChecked) {
  struct Case {
    const char* toml;
    const char* key;
    const char* text;
  };
  const Case cases[] = {
      {"[turntable.modbus]\nparity = \"mark\"\n", "turntable.modbus.parity",
       "must be one of none | even | odd, got \"mark\""},
      {"[turntable.modbus]\ndata_bits = 9\n", "turntable.modbus.data_bits", "5..8, got 9"},
      {"[turntable.modbus]\nstop_bits = 3\n", "turntable.modbus.stop_bits", "1..2, got 3"},
      {"[turntable.modbus]\nbaud = 12345\n", "turntable.modbus.baud",
       "12345 is not a serial line speed; use one of 9600, 19200"},
      {"[turntable.modbus]\nresponse_timeout = \"0s\"\n", "turntable.modbus.response_timeout",
       "must be > 0s"},
      {"[turntable.modbus]\nresponse_timeout = 200\n", "turntable.modbus.response_timeout",
       "expected a duration string with a unit"},
      {"[turntable.modbus]\nretries = 11\n", "turntable.modbus.retries", "0..10, got 11"},
      {"[turntable.modbus]\ngear_ratio = 0\n", "turntable.modbus.gear_ratio", "must be > 0"},
      {"[turntable.modbus]\nmicrosteps = 0\n", "turntable.modbus.microsteps", "1..100000"},
      {"[turntable.modbus]\nbacklash_approach = \"up\"\n", "turntable.modbus.backlash_approach",
       "positive | negative"},
      {"[turntable.modbus]\nbacklash_comp_deg = -1\n", "turntable.modbus.backlash_comp_deg",
       "0..10"},
      {"[turntable.modbus]\nprofile = \"\"\n", "turntable.modbus.profile", "must not be empty"},
      {"[turntable.modbus]\nunit_id = 256\n", "turntable.modbus.unit_id", "0..255"},
      {"[turntable.modbus]\nprot = 502\n", "turntable.modbus.prot",
       "unknown key; did you mean turntable.modbus.port?"},
  };
  for (const auto& c : cases) ExpectOneProblem(c.toml, 2, c.key, c.text);
  // The link the backend needs must be given.
  ExpectOneProblem("[turntable]\nbackend = \"modbus-tcp\"\n", 0, "turntable.modbus.host",
                   "needs the controller's address, e.g. host = \"192.168.1.50\"");
  ExpectOneProblem("[turntable]\nbackend = \"modbus-rtu\"\n", 0, "turntable.modbus.device",
                   "needs the serial device, e.g. device = \"/dev/ttyUSB0\"");
  ExpectOneProblem(
      "[turntable]\nbackend = \"modbus-rtu\"\n[turntable.modbus]\ndevice = \"/dev/ttyUSB0\"\n"
      "unit_id = 0\n",
      5, "turntable.modbus.unit_id", "a Modbus RTU unit id is 1..247 (0 is broadcast)");
  ExpectOneProblem("[turntable.modbus]\nmotor_steps_per_rev = 1000000\nmicrosteps = 256\n", 3,
                   "turntable.modbus.microsteps", "fewer than 1000 turns in an int32 position");
  Loaded ok = Load(
      "[turntable]\nbackend = \"modbus-rtu\"\n[turntable.modbus]\ndevice = \"/dev/ttyUSB0\"\n"
      "baud = 38400\nparity = \"even\"\nrs485 = true\nresponse_timeout = \"150ms\"\n");
  ASSERT_TRUE(ok.result.ok()) << Dump(ok.problems);
  EXPECT_EQ(ok.result->turntable.modbus.baud, 38400);
  EXPECT_EQ(ok.result->turntable.modbus.response_timeout, 150 * kNsPerMs);
  EXPECT_DOUBLE_EQ(ok.result->turntable.modbus.steps_per_rev(), 3200.0);
}

TEST(Config, UsbTurntableBacklashValuesAreChecked) {
  ExpectOneProblem("[turntable.usb]\nbacklash_approach = \"up\"\n", 2,
                   "turntable.usb.backlash_approach",
                   "must be one of positive | negative, got \"up\"");
  ExpectOneProblem("[turntable.usb]\nbacklash_comp_deg = -1\n", 2,
                   "turntable.usb.backlash_comp_deg", "0..10");
  ExpectOneProblem("[turntable.usb]\nbacklash_comp_deg = 10.5\n", 2,
                   "turntable.usb.backlash_comp_deg", "0..10");
  Loaded defaults = Load("");
  ASSERT_TRUE(defaults.result.ok()) << Dump(defaults.problems);
  EXPECT_EQ(defaults.result->turntable.usb.backlash_comp_deg, 0.0);  // off unless asked for
  EXPECT_EQ(defaults.result->turntable.usb.backlash_approach, "positive");
  Loaded ok = Load("[turntable.usb]\nbacklash_comp_deg = 0.5\nbacklash_approach = \"negative\"\n");
  ASSERT_TRUE(ok.result.ok()) << Dump(ok.problems);
  EXPECT_DOUBLE_EQ(ok.result->turntable.usb.backlash_comp_deg, 0.5);
  EXPECT_EQ(ok.result->turntable.usb.backlash_approach, "negative");
}

// The lens's nominal focal (the SfM path's hint without a calibration) needs
// the sensor's width: one without the other is refused, naming the missing one.
TEST(Config, LensFocalAndSensorWidthGoTogether) {
  ExpectOneProblem("[camera]\nlens_focal_mm = 6.0\n", 0, "camera.sensor_width_mm",
                   "camera.lens_focal_mm and camera.sensor_width_mm go together");
  ExpectOneProblem("[camera]\nsensor_width_mm = 6.287\n", 0, "camera.lens_focal_mm",
                   "set both from the datasheets");
  ExpectOneProblem("[camera]\nlens_focal_mm = -6.0\n", 2, "camera.lens_focal_mm", "");
  Loaded l = Load("[camera]\nlens_focal_mm = 6.0\nsensor_width_mm = 6.287\n");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);
  EXPECT_EQ(l.result->camera.lens_focal_mm, 6.0);
  EXPECT_EQ(l.result->camera.sensor_width_mm, 6.287);
}

TEST(Config, OnnxMaskNeedsAModel) {
  ExpectOneProblem(
      "[mask]\nmodel = \"\"\nmethod = \"onnx\"\n", 2, "mask.model",
      "needs the network: name its .onnx file here, or set mask.method = \"classical\"");
  Loaded l = Load("[mask]\nmethod = \"onnx\"\nmodel = \"/opt/u2net.onnx\"\noutput = \"logits\"\n");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);
  EXPECT_EQ(l.result->mask.model, "/opt/u2net.onnx");
  EXPECT_EQ(l.result->mask.output, "logits");
}

TEST(Config, MarkerRules) {
  ExpectOneProblem("[[rig.markers]]\ncolor = \"purple\"\n", 2, "rig.markers[0].color",
                   "red | green | blue | yellow");
  ExpectOneProblem(
      "[[rig.markers]]\ncolor = \"red\"\n[[rig.markers]]\ncolor = \"red\"\nx_mm = 5.0\n", 4,
      "rig.markers[1].color", "at most once");
  ExpectOneProblem("[[rig.markers]]\nx_mm = 1.0\n", 1, "rig.markers[0].color", "missing");
  Loaded l = Load("[rig]\nmarkers = [{color = \"blue\", x_mm = 1.5, y_mm = -2}]\n");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);
  ASSERT_EQ(l.result->rig.markers.size(), 1u);  // a file's list replaces the default one
  EXPECT_EQ(l.result->rig.markers[0], (RigMarker{"blue", 1.5, -2.0}));
}

// ArUco scale markers: a valid file, then each bad value alone.
constexpr const char* kArucoHead =
    "[sim]\n"                        // 1
    "aruco_image = \"aruco.pgm\"\n"  // 2
    "[rig]\n";                       // 3

TEST(Config, ArucoMarkersLoad) {
  EXPECT_TRUE(Config{}.rig.aruco_markers.empty());  // the colour labels stay the default
  Loaded l = Load(std::string(kArucoHead) +
                  "aruco_dictionary = \"DICT_5X5_100\"\n"
                  "aruco_size_mm = 24.5\n"
                  "[[rig.aruco_markers]]\nid = 3\nx_mm = 80.0\ny_mm = 80.0\n"
                  "[[rig.aruco_markers]]\nid = 99\nx_mm = -80\ny_mm = -80\nyaw_deg = 45.0\n");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);
  const RigConfig& rig = l.result->rig;
  EXPECT_EQ(rig.aruco_dictionary, "DICT_5X5_100");
  EXPECT_EQ(rig.aruco_size_mm, 24.5);
  ASSERT_EQ(rig.aruco_markers.size(), 2u);
  EXPECT_EQ(rig.aruco_markers[0], (ArucoMarker{3, 80.0, 80.0, 0.0}));
  EXPECT_EQ(rig.aruco_markers[1], (ArucoMarker{99, -80.0, -80.0, 45.0}));
  EXPECT_EQ(rig.markers.size(), 4u);  // the colour labels are kept beside them
  // Inline array form, too.
  Loaded m = Load(std::string(kArucoHead) + "aruco_markers = [{id = 0, x_mm = 70, y_mm = 70}]\n");
  ASSERT_TRUE(m.result.ok()) << Dump(m.problems);
  EXPECT_EQ(m.result->rig.aruco_markers.at(0), (ArucoMarker{0, 70.0, 70.0, 0.0}));
}

TEST(Config, ArucoMarkerRules) {
  const std::string h = kArucoHead;
  const std::string one = "[[rig.aruco_markers]]\nid = 3\nx_mm = 80.0\ny_mm = 80.0\n";  // lines 4-7
  ExpectOneProblem(h + "aruco_dictionary = \"DICT_9X9_50\"\n" + one, 4, "rig.aruco_dictionary",
                   "must be one of DICT_4X4_50");
  ExpectOneProblem(h + "aruco_size_mm = 0\n" + one, 4, "rig.aruco_size_mm", "must be > 0");
  ExpectOneProblem(h + "aruco_size_mm = -5\n" + one, 4, "rig.aruco_size_mm", "must be > 0");
  // Duplicate id: reported on the second marker's id, naming the first.
  ExpectOneProblem(h + one + "[[rig.aruco_markers]]\nid = 3\nx_mm = -80.0\ny_mm = -80.0\n", 9,
                   "rig.aruco_markers[1].id", "id 3 is also used by rig.aruco_markers[0]");
  // An id the dictionary does not have.
  ExpectOneProblem(h + "[[rig.aruco_markers]]\nid = 50\nx_mm = 80.0\ny_mm = 80.0\n", 5,
                   "rig.aruco_markers[0].id", "not in DICT_4X4_50 (ids 0..49)");
  ExpectOneProblem(h + "aruco_dictionary = \"DICT_4X4_1000\"\n" +
                       "[[rig.aruco_markers]]\nid = 1000\nx_mm = 80.0\ny_mm = 80.0\n",
                   6, "rig.aruco_markers[0].id", "ids 0..999");
  ExpectOneProblem(h + "[[rig.aruco_markers]]\nid = -4\nx_mm = 80.0\ny_mm = 80.0\n", 5,
                   "rig.aruco_markers[0].id", "must be in 0..1000000, got -4");
  ExpectOneProblem(h + "[[rig.aruco_markers]]\nx_mm = 80.0\ny_mm = 80.0\n", 4,
                   "rig.aruco_markers[0].id", "missing");
  // Off the disc (radius 152.5): the centre is on it, the paper is not.
  ExpectOneProblem(h + "[[rig.aruco_markers]]\nid = 3\nx_mm = 135.0\ny_mm = 10.0\n", 6,
                   "rig.aruco_markers[0].x_mm", "beyond the disc edge (152.5 mm)");
  // A marker that fits square to the rim does not once turned 45 degrees.
  const std::string rim =
      h + "markers = []\n[[rig.aruco_markers]]\nid = 3\nx_mm = 0.0\ny_mm = 125.0\n";
  EXPECT_TRUE(Load(rim).result.ok()) << Dump(Load(rim).problems);
  ExpectOneProblem(rim + "yaw_deg = 45\n", 7, "rig.aruco_markers[0].x_mm",
                   "reaches 156.8 mm from the axis");
  ExpectOneProblem(h + "[[rig.aruco_markers]]\nid = 3\nx_mm = 900.0\ny_mm = 10.0\n", 6,
                   "rig.aruco_markers[0].x_mm", "move it towards the axis");
  // Papers overlapping each other or a colour label.
  ExpectOneProblem(h + one + "[[rig.aruco_markers]]\nid = 4\nx_mm = 100.0\ny_mm = 60.0\n", 10,
                   "rig.aruco_markers[1].x_mm", "overlaps that of rig.aruco_markers[0]");
  ExpectOneProblem(h + "[[rig.aruco_markers]]\nid = 4\nx_mm = 110.0\ny_mm = 0.0\n", 6,
                   "rig.aruco_markers[0].x_mm", "covers the red colour label");
  // Unknown key in a marker.
  ExpectOneProblem(h + "[[rig.aruco_markers]]\nidd = 4\nid = 4\nx_mm = 80.0\ny_mm = 80.0\n", 5,
                   "rig.aruco_markers[0].idd", "did you mean id?");
  ExpectOneProblem(h + "aruco_markers = 7\n", 4, "rig.aruco_markers",
                   "expected an array of tables");
  // Without sim.aruco_image the config is still valid (`aggscan calibrate
  // aruco` writes the image from it); the sim world refuses to start then.
  EXPECT_TRUE(Load(one).result.ok()) << Dump(Load(one).problems);
}

TEST(Config, SeveralProblemsAllReported) {
  const std::string text =
      "[daemon]\n"                   // 1
      "listen_port = 99999\n"        // 2  out of range
      "log_levl = \"info\"\n"        // 3  unknown, did you mean
      "[capture]\n"                  // 4
      "profile = \"custom\"\n"       // 5
      "views_per_side = \"many\"\n"  // 6  wrong type
      "interval = \"soon\"\n"        // 7  malformed duration
      "[camera]\n"                   // 8
      "jpeg_quality = 0\n"           // 9  out of range
      "backend = \"usb\"\n"          // 10 unknown backend
      "[[rig.markers]]\n"            // 11
      "color = \"pink\"\n";          // 12 bad colour
  Loaded l = Load(text);
  ASSERT_FALSE(l.result.ok());
  std::map<std::string, int> got;
  for (const auto& p : l.problems) got[p.key] = p.line;
  std::map<std::string, int> want = {{"daemon.listen_port", 2},     {"daemon.log_levl", 3},
                                     {"capture.views_per_side", 6}, {"capture.interval", 7},
                                     {"camera.jpeg_quality", 9},    {"camera.backend", 10},
                                     {"rig.markers[0].color", 12}};
  EXPECT_EQ(got, want) << Dump(l.problems);
  EXPECT_EQ(l.problems.size(), want.size());
  for (size_t i = 1; i < l.problems.size(); ++i) {  // in file order
    EXPECT_LT(l.problems[i - 1].line, l.problems[i].line) << Dump(l.problems);
  }
  EXPECT_THAT(l.result.error().message, HasSubstr("7 config problems"));
  EXPECT_THAT(l.result.error().detail,
              HasSubstr("t.toml:10: camera.backend: unknown camera backend"));
}

TEST(Config, ProblemsAppendToCallersListAndNullIsAllowed) {
  std::vector<ConfigProblem> problems = {ConfigProblem{"earlier", 1, "x", "y"}};
  Result<Config> ok = LoadConfigString("", "t.toml", &problems);
  EXPECT_TRUE(ok.ok());  // only this call's problems count
  EXPECT_EQ(problems.size(), 1u);
  Result<Config> bad = LoadConfigString("[camera]\nwidth = 1\n", "t.toml", nullptr);
  ASSERT_FALSE(bad.ok());
  EXPECT_THAT(bad.error().message, HasSubstr("1 config problem,"));
}

TEST(Config, MissingFile) {
  std::vector<ConfigProblem> problems;
  Result<Config> r = LoadConfigFile("/nonexistent/aggscan.toml", &problems);
  ASSERT_FALSE(r.ok());
  ASSERT_EQ(problems.size(), 1u);
  EXPECT_EQ(problems[0].file, "/nonexistent/aggscan.toml");
  EXPECT_THAT(problems[0].message, HasSubstr("cannot read"));
}

TEST(Config, ProblemToString) {
  EXPECT_EQ((ConfigProblem{"a.toml", 12, "capture.interval", "must be > 0s"}).ToString(),
            "a.toml:12: capture.interval: must be > 0s");
  EXPECT_EQ((ConfigProblem{"a.toml", 0, "capture.interval", "m"}).ToString(),
            "a.toml: capture.interval: m");
  EXPECT_EQ((ConfigProblem{"a.toml", 3, "", "TOML syntax error: x"}).ToString(),
            "a.toml:3: TOML syntax error: x");
}

TEST(Config, CrossFieldRules) {
  // A 30 deg step at 60 deg/s and 180 deg/s^2 takes 833 ms, plus 300 ms settle.
  ExpectOneProblem("[capture]\nprofile = \"custom\"\ninterval = \"1s\"\n", 3, "capture.interval",
                   "shorter than one step");
  ExpectOneProblem("[capture]\nmove_timeout = \"500ms\"\n", 2, "capture.move_timeout",
                   "shorter than one step");
  ExpectOneProblem("[capture]\nstall_timeout = \"20ms\"\n", 2, "capture.stall_timeout",
                   "poll_interval");
  ExpectOneProblem("[sim]\ncamera_distance_mm = 100\n", 2, "sim.camera_distance_mm",
                   "outside the turntable");
  ExpectOneProblem("[sim]\nrock_size_mm = 5\n", 2, "sim.rock_size_mm", "at least 10");
  // A running worker must not be called silent between two of its reports.
  ExpectOneProblem("[worker]\nheartbeat_interval = \"10s\"\nsilent_after = \"15s\"\n", 3,
                   "worker.silent_after", "twice worker.heartbeat_interval");
  EXPECT_TRUE(Load("[worker]\nheartbeat_interval = \"10s\"\nsilent_after = \"0s\"\n").result.ok());
  // A faster table makes the short interval fine.
  Loaded l = Load(
      "[capture]\nprofile = \"custom\"\ninterval = \"1s\"\n[turntable]\nmax_speed_deg_s = 120\n"
      "accel_deg_s2 = 720\n");
  EXPECT_TRUE(l.result.ok()) << Dump(l.problems);

  // ValidateConfig on a struct (no lines).
  Config c;
  c.capture.views_per_side = 20;  // paper profile, not applied
  c.camera.width = 8;
  std::vector<ConfigProblem> problems;
  ValidateConfig(c, "struct", &problems);
  ASSERT_EQ(problems.size(), 2u) << Dump(problems);
  EXPECT_EQ(problems[0].key, "camera.width");
  EXPECT_EQ(problems[0].line, 0);
  EXPECT_EQ(problems[1].key, "capture.profile");
}

TEST(Config, PaperProfileFixesItsValues) {
  Loaded l = Load(
      "[capture]\nprofile = \"paper\"\nsides = 2\nviews_per_side = 30\nstep_deg = 30.0\n"
      "interval = \"2000ms\"\n");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);  // the same values may be written
  EXPECT_EQ(l.result->capture, CaptureConfig{});

  ExpectOneProblem(
      "[capture]\nviews_per_side = 20\n", 2, "capture.views_per_side",
      "capture.profile \"paper\" fixes this to 30; set capture.profile = \"custom\" to change it");
  ExpectOneProblem("[capture]\nprofile = \"paper\"\nstep_deg = 12\n", 3, "capture.step_deg",
                   "set capture.profile");
  ExpectOneProblem("[capture]\n\ninterval = \"3s\"\n", 3, "capture.interval",
                   "fixes this to \"2s\"");
  ExpectOneProblem("[capture]\nsides = 1\n", 2, "capture.sides", "fixes this to 2");
  // Values the profile does not fix stay free.
  Loaded s = Load("[capture]\nsettle = \"500ms\"\n");
  ASSERT_TRUE(s.result.ok()) << Dump(s.problems);
  EXPECT_EQ(s.result->capture.settle, 500 * kNsPerMs);
}

TEST(Config, FullTurnProfileDerivesTheStep) {
  Loaded d = Load("[capture]\nprofile = \"full-turn\"\n");
  ASSERT_TRUE(d.result.ok()) << Dump(d.problems);
  EXPECT_EQ(d.result->capture.views_per_side, 30);
  EXPECT_DOUBLE_EQ(d.result->capture.step_deg, 12.0);

  Loaded l = Load(
      "[capture]\nprofile = \"full-turn\"\nviews_per_side = 36\nsides = 1\ninterval = \"3s\"\n");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);
  EXPECT_DOUBLE_EQ(l.result->capture.step_deg, 10.0);
  EXPECT_EQ(l.result->capture.sides, 1);
  EXPECT_EQ(l.result->capture.interval, 3 * kNsPerSec);

  Loaded same = Load("[capture]\nprofile = \"full-turn\"\nviews_per_side = 36\nstep_deg = 10\n");
  EXPECT_TRUE(same.result.ok()) << Dump(same.problems);
  ExpectOneProblem("[capture]\nprofile = \"full-turn\"\nviews_per_side = 36\nstep_deg = 12\n", 4,
                   "capture.step_deg", "360/views_per_side = 10.0");
}

TEST(Config, CustomProfileKeepsValues) {
  Loaded l = Load(
      "[capture]\nprofile = \"custom\"\nsides = 1\nviews_per_side = 8\nstep_deg = 45\n"
      "interval = \"3s\"\n");
  ASSERT_TRUE(l.result.ok()) << Dump(l.problems);
  EXPECT_EQ(l.result->capture.sides, 1);
  EXPECT_EQ(l.result->capture.views_per_side, 8);
  EXPECT_EQ(l.result->capture.step_deg, 45.0);
  EXPECT_EQ(l.result->capture.interval, 3 * kNsPerSec);
}

TEST(Config, ApplyProfile) {
  Config c;
  c.capture.profile = "paper";
  c.capture.views_per_side = 5;
  c.capture.interval = kNsPerSec;
  ApplyProfile(&c);
  EXPECT_EQ(c.capture, CaptureConfig{});
  c.capture.profile = "full-turn";
  c.capture.views_per_side = 24;
  ApplyProfile(&c);
  EXPECT_DOUBLE_EQ(c.capture.step_deg, 15.0);
  c.capture.profile = "custom";
  c.capture.step_deg = 7.0;
  ApplyProfile(&c);
  EXPECT_EQ(c.capture.step_deg, 7.0);
}

TEST(Duration, Parse) {
  struct Case {
    const char* text;
    TimeNs ns;
  };
  const Case cases[] = {
      {"500ms", 500 * kNsPerMs},
      {"2s", 2 * kNsPerSec},
      {"1.5min", 90 * kNsPerSec},
      {"250us", 250'000},
      {"250\xC2\xB5s", 250'000},
      {"7ns", 7},
      {"1h", 3600 * kNsPerSec},
      {"0s", 0},
      {"0.3s", 300 * kNsPerMs},
      {"-2s", -2 * kNsPerSec},
      {"2 s", 2 * kNsPerSec},
      {"1.0000000001s", 1'000'000'000},
      {"0.5ns", 1},
      {"1.234us", 1234},
      {"9223372036ns", 9'223'372'036},
  };
  for (const auto& c : cases) {
    TimeNs got = -42;
    EXPECT_TRUE(ParseDuration(c.text, &got)) << c.text;
    EXPECT_EQ(got, c.ns) << c.text;
  }
  for (const char* bad : {"", "2", "s", "2x", "1.s", ".5s", "2ss", "2 ", "-", "1e3s", "2sec",
                          "3 days", "99999999999999999999s", "9999999999h"}) {
    TimeNs got = -42;
    EXPECT_FALSE(ParseDuration(bad, &got)) << bad;
    EXPECT_EQ(got, -42) << bad;
  }
}

TEST(Duration, FormatIsShortAndExact) {
  EXPECT_EQ(FormatDuration(0), "0s");
  EXPECT_EQ(FormatDuration(2 * kNsPerSec), "2s");
  EXPECT_EQ(FormatDuration(300 * kNsPerMs), "300ms");
  EXPECT_EQ(FormatDuration(1500 * kNsPerMs), "1.5s");
  EXPECT_EQ(FormatDuration(90 * kNsPerSec), "90s");
  EXPECT_EQ(FormatDuration(120 * kNsPerSec), "2min");
  EXPECT_EQ(FormatDuration(7200 * kNsPerSec), "2h");
  EXPECT_EQ(FormatDuration(250'000), "250us");
  EXPECT_EQ(FormatDuration(1234), "1.234us");
  EXPECT_EQ(FormatDuration(12), "12ns");
  EXPECT_EQ(FormatDuration(-20 * kNsPerMs), "-20ms");
  for (TimeNs ns :
       {TimeNs{1}, TimeNs{999}, TimeNs{1001}, TimeNs{123'456'789}, TimeNs{1'000'000'001},
        TimeNs{59 * kNsPerSec + 1}, 3 * kNsPerSec / 7, -kNsPerSec / 3,
        std::numeric_limits<TimeNs>::max(), std::numeric_limits<TimeNs>::min() + 1}) {
    TimeNs back = 0;
    ASSERT_TRUE(ParseDuration(FormatDuration(ns), &back)) << FormatDuration(ns);
    EXPECT_EQ(back, ns) << FormatDuration(ns);
  }
}

void ExpectRoundTrip(const Config& c) {
  std::string text = ConfigToToml(c);
  std::vector<ConfigProblem> problems;
  Result<Config> back = LoadConfigString(text, "dump.toml", &problems);
  ASSERT_TRUE(back.ok()) << Dump(problems) << text;
  EXPECT_EQ(*back, c) << text;
  EXPECT_EQ(ConfigToToml(*back), text);
}

TEST(ConfigToToml, RoundTripDefaults) { ExpectRoundTrip(Config{}); }

TEST(ConfigToToml, RoundTripShippedConfigs) {
  for (const char* name : {"sim.toml", "aggscand.toml"}) {
    Result<Config> c = LoadConfigFile(std::string(AGGSCAN_SOURCE_DIR) + "/config/" + name, nullptr);
    ASSERT_TRUE(c.ok()) << name;
    ExpectRoundTrip(*c);
  }
}

TEST(ConfigToToml, RoundTripEveryFieldChanged) {
  Config c;
  c.daemon.state_dir = "/srv/agg \"scan\"\\ dir\twith\ncontrol \x01 and ünïcode";
  c.daemon.listen_address = "0.0.0.0";
  c.daemon.listen_port = 0;
  c.daemon.credentials_file = "/etc/aggscan/accounts of \"the rig\"";
  c.daemon.tls_certificate = "/etc/aggscan/tls/cert.pem";
  c.daemon.tls_key = "/etc/aggscan/tls/key.pem";
  c.daemon.preview_interval = 333 * kNsPerMs + 7;
  c.daemon.preview_max_side = 1280;
  c.daemon.web_root = "/opt/aggscan console/web";
  c.daemon.log_level = "debug";
  c.daemon.time_scale = 1000.0;
  c.capture.profile = "full-turn";
  c.capture.sides = 1;
  c.capture.views_per_side = 7;
  c.capture.step_deg = 360.0 / 7;  // not exact in decimal
  c.capture.interval = 60 * kNsPerSec + 1;
  c.capture.settle = 0;
  c.capture.home_timeout = 90 * kNsPerSec;
  c.capture.move_timeout = 3 * kNsPerSec / 7;
  c.capture.frame_timeout = 1;
  c.capture.poll_interval = 1234;
  c.capture.stall_timeout = 600 * kNsPerSec;
  c.capture.comm_retries = 10;
  c.camera.id = "cam\"1\"";
  c.camera.device = "/dev/aggscan/camera";
  c.camera.width = 16384;
  c.camera.height = 16;
  c.camera.jpeg_quality = 1;
  c.camera.exposure = {false, 0.1, 63.999999999, 1e-7, 15.5};
  c.camera.v4l2 = {"nv12", 32, 123 * kNsPerMs, 1000000, 0, false};
  c.turntable.max_speed_deg_s = 720.0;
  c.turntable.accel_deg_s2 = 35999.5;
  c.turntable.repeatability_deg = 0.0;
  c.turntable.backlash_deg = 1.0 / 3;
  c.turntable.settle_amplitude_deg = 9.75;
  c.turntable.settle_time_constant = 1;
  c.turntable.settle_frequency_hz = 0.001;
  c.turntable.home_duration = 0;
  c.turntable.faults.stall_at_deg = -95.25;
  c.turntable.faults.timeout_every_n_moves = 3;
  c.turntable.faults.disconnect_after = 20 * kNsPerSec;
  c.turntable.modbus.profile = "/etc/aggscan/turntables/my \"table\".toml";
  c.turntable.modbus.unit_id = 247;
  c.turntable.modbus.host = "10.0.0.5";
  c.turntable.modbus.port = 5020;
  c.turntable.modbus.device = "/dev/aggscan/turntable";
  c.turntable.modbus.baud = 115200;
  c.turntable.modbus.parity = "even";
  c.turntable.modbus.data_bits = 7;
  c.turntable.modbus.stop_bits = 2;
  c.turntable.modbus.rs485 = true;
  c.turntable.modbus.response_timeout = 1500 * kNsPerMs;
  c.turntable.modbus.retries = 0;
  c.turntable.modbus.microsteps = 32;
  c.turntable.modbus.gear_ratio = 4.5;
  c.turntable.modbus.shortest_path = true;
  c.turntable.modbus.backlash_comp_deg = 0.25;
  c.turntable.modbus.backlash_approach = "negative";
  c.turntable.modbus.in_position_window_deg = 0.125;
  c.turntable.usb.backlash_comp_deg = 0.75;
  c.turntable.usb.backlash_approach = "negative";
  c.button.debounce = kNsPerSec;
  c.sim.seed = 9'223'372'036'854'775'807ULL;
  c.sim.rock_mesh = "rocks/r1.ply";
  c.sim.rock_unit = "cm";
  c.sim.rock_size_mm = 123.456;
  c.sim.camera_elevation_deg = 10.0;
  c.sim.camera_distance_mm = 10000.0;
  c.sim.hfov_deg = 150.0;
  c.sim.k1 = -1.0;
  c.sim.k2 = 1e-300;
  c.sim.noise_sigma = 0.0;
  c.sim.write_truth = true;
  c.rig.turntable_diameter_mm = 400.0;
  c.rig.marker_size_mm = 25.4;
  c.rig.markers = {{"yellow", -0.0, 4999.999}, {"green", 1e-3, -5000.0}};
  c.rig.aruco_dictionary = "DICT_6X6_250";
  c.rig.aruco_size_mm = 25.5;
  c.rig.aruco_markers = {{249, 100.0, -50.0, -30.5}, {0, -120.0, 60.0, 359.0}};
  c.sim.aruco_image = "markers/aruco \"6x6\".pgm";
  c.worker.poll_interval = 60 * kNsPerSec;
  c.worker.nice = 0;
  c.worker.heartbeat_interval = 250 * kNsPerMs;
  c.worker.silent_after = 0;
  c.mask = {
      "onnx", "models/u2net \"rig\".onnx", 288, 4096, -0.5, 0.0, 1e-9, 0.1, 1.0 / 3, 10.0, "logits",
      0.999};
  std::vector<ConfigProblem> problems;
  ValidateConfig(c, "struct", &problems);
  ASSERT_TRUE(problems.empty()) << Dump(problems);
  ExpectRoundTrip(c);

  c.rig.markers.clear();  // an empty list must survive too
  ExpectRoundTrip(c);
  c.rig.aruco_markers.clear();
  ExpectRoundTrip(c);
  c.rig.markers = {{"red", 1.0, 2.0}};  // ArUco markers after the labels' tables
  c.rig.aruco_markers = {{7, 50.0, 50.0, 0.0}};
  ExpectRoundTrip(c);
}

TEST(ConfigToToml, CommentsEveryFieldAndShowsUnsetOptionals) {
  std::string text = ConfigToToml(Config{});
  EXPECT_THAT(text, HasSubstr("# stall_at_deg =   (not set)"));
  EXPECT_THAT(text, HasSubstr("# disconnect_after =   (not set)"));
  EXPECT_THAT(text, HasSubstr("interval = \"2s\""));
  EXPECT_THAT(text, HasSubstr("[camera.exposure]"));
  EXPECT_THAT(text, HasSubstr("[[rig.markers]]"));
  // Every assignment line follows a comment line.
  std::vector<std::string> lines;
  size_t start = 0, end;
  while ((end = text.find('\n', start)) != std::string::npos) {
    lines.push_back(text.substr(start, end - start));
    start = end + 1;
  }
  for (size_t i = 1; i < lines.size(); ++i) {
    if (lines[i].find(" = ") != std::string::npos && lines[i][0] != '#') {
      EXPECT_EQ(lines[i - 1].rfind("# ", 0), 0u) << "no comment above: " << lines[i];
    }
  }
}

TEST(Config, ButtonAndLightDevicesMustBeNamedAndLinksShareable) {
  ExpectOneProblem("[button]\nbackend = \"evdev\"\n", 0, "button.evdev.device",
                   "needs the input device");
  // The turntable's link is shared only over TCP (a second connection).
  ExpectOneProblem("[button]\nbackend = \"modbus\"\n", 0, "button.modbus.link",
                   "only when turntable.backend = \"modbus-tcp\"");
  ExpectOneProblem("[button]\nbackend = \"modbus\"\n[button.modbus]\nlink = \"tcp\"\n", 0,
                   "button.modbus.host", "needs the controller's address");
  ExpectOneProblem("[light]\nbackend = \"modbus\"\n[light.modbus]\nlink = \"button\"\n", 4,
                   "light.modbus.link", "needs button.backend = \"modbus\"");
  ExpectOneProblem("[button]\nbackend = \"gpio\"\n[button.gpio]\nbias = \"strong\"\n", 4,
                   "button.gpio.bias", "pull-up");
  Loaded ok = Load(
      "[button]\nbackend = \"modbus\"\n[button.modbus]\nlink = \"rtu\"\ndevice = \"/dev/ttyUSB1\"\n"
      "[light]\nbackend = \"modbus\"\n[light.modbus]\nlink = \"button\"\ncoil = 3\n");
  EXPECT_TRUE(ok.result.ok()) << Dump(ok.problems);
}

TEST(Config, KnownBackends) {
  EXPECT_EQ(KnownBackends("camera"), (std::vector<std::string>{"sim", "v4l2", "libcamera"}));
  EXPECT_EQ(KnownBackends("turntable"),
            (std::vector<std::string>{"sim", "modbus-tcp", "modbus-rtu", "usb-tic", "manual"}));
  EXPECT_EQ(KnownBackends("button"), (std::vector<std::string>{"sim", "gpio", "evdev", "modbus"}));
  EXPECT_TRUE(KnownBackends("toaster").empty());
}

}  // namespace
}  // namespace aggscan
