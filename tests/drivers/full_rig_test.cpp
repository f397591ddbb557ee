// A full scenario on real drivers: the real aggscand with its camera on the
// V4L2 backend against the kernel's vivid driver, its turntable on a Modbus/TCP
// peer (the libmodbus server of modbus_test_server.h, in this process on
// 127.0.0.1) and its start button on a gpio-sim line. A press through gpio-sim
// captures a complete side; every view is a real vivid image and every
// sidecar carries the angle the peer reported, which the peer makes differ
// from the commanded one by a known rest error.
//
// Meant to run inside the throwaway VM of tests/vm/run-in-vm.sh with vivid and
// gpio-sim loaded; exits 77 (skipped) where either is missing.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <linux/videodev2.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <string>
#include <thread>
#include <vector>

#include "tests/drivers/gpio_sim_chip.h"
#include "tests/drivers/modbus_test_server.h"
#include "tests/scenario/process.h"

namespace aggscan {
namespace {

namespace gpiosim = test::gpiosim;
using json = nlohmann::json;
using test::Eventually;
using test::ReadAll;

gpiosim::Chip g_sim;  // made in main()
std::string g_vivid;  // vivid's capture node, found in main()
int g_width = 0, g_height = 0;

// The capture node whose sysfs name is vivid's ("vivid-000-vid-cap").
std::string FindVivid() {
  namespace fs = std::filesystem;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator("/sys/class/video4linux", ec)) {
    const std::string name = gpiosim::ReadLine(e.path().string() + "/name");
    if (name.starts_with("vivid-") && name.ends_with("-vid-cap"))
      return "/dev/" + e.path().filename().string();
  }
  return {};
}

// The smallest discrete YUYV size the node lists (quick to draw under TCG).
bool SmallestYuyvSize(const std::string& node, int* w, int* h) {
  const int fd = ::open(node.c_str(), O_RDWR | O_CLOEXEC);
  if (fd < 0) return false;
  v4l2_frmsizeenum fs{};
  fs.pixel_format = V4L2_PIX_FMT_YUYV;
  for (fs.index = 0; ::ioctl(fd, VIDIOC_ENUM_FRAMESIZES, &fs) == 0; ++fs.index) {
    if (fs.type != V4L2_FRMSIZE_TYPE_DISCRETE) {
      *w = static_cast<int>(fs.stepwise.min_width);
      *h = static_cast<int>(fs.stepwise.min_height);
      break;
    }
    if (*w == 0 || static_cast<int64_t>(fs.discrete.width) * fs.discrete.height <
                       static_cast<int64_t>(*w) * *h) {
      *w = static_cast<int>(fs.discrete.width);
      *h = static_cast<int>(fs.discrete.height);
    }
  }
  ::close(fd);
  return *w > 0 && *h > 0;
}

constexpr int kViews = 4;
constexpr double kStepsPerDeg = 32000.0 / 360.0;  // 200 steps x 16 microsteps x 10:1 gear
constexpr int64_t kRestError = 12;                // steps past each target the peer's drive stops

// Four views 90 deg apart, 3 s apart on the real clock (a 90 deg move takes
// 0.5 s at 360 deg/s; the rest is slack for TCG); the in-position window
// (0.2 deg = 17.8 steps) takes the peer's rest error.
std::string WriteConfig(const std::string& dir, const testing::ModbusTestServer& peer) {
  const TurntableConfig tt = testing::ModbusConfigFor(peer, /*tcp=*/true);
  const std::string path = dir + "/full-rig.toml";
  std::ofstream f(path);
  f << "[daemon]\nstate_dir = \"" << dir
    << "/state\"\nlisten_port = 0\ntime_scale = 1\nlog_level = \"info\"\n\n"
    << "[capture]\nprofile = \"custom\"\nsides = 1\nviews_per_side = " << kViews
    << "\nstep_deg = 90.0\ninterval = \"3s\"\nsettle = \"50ms\"\nframe_timeout = \"30s\"\n\n"
    << "[camera]\nbackend = \"v4l2\"\nid = \"vivid0\"\ndevice = \"" << g_vivid
    << "\"\nwidth = " << g_width << "\nheight = " << g_height
    << "\n\n"
    // vivid has gain but no exposure or white balance controls.
    << "[camera.v4l2]\nstrict_controls = false\nframe_timeout = \"30s\"\n\n"
    << "[turntable]\nbackend = \"modbus-tcp\"\nmax_speed_deg_s = 360.0\naccel_deg_s2 = 1440.0\n\n"
    << "[turntable.modbus]\nprofile = \"" << tt.modbus.profile
    << "\"\nhost = \"127.0.0.1\"\nport = " << peer.port()
    << "\nmotor_steps_per_rev = 200\nmicrosteps = 16\ngear_ratio = 10.0\n"
    << "in_position_window_deg = 0.2\nresponse_timeout = \"2s\"\n\n"
    << "[button]\nbackend = \"gpio\"\ndebounce = \"50ms\"\n\n"
    << "[button.gpio]\nchip = \"" << g_sim.name << "\"\nline = \"start\"\n";
  return path;
}

TEST(FullRig, GpioPressCapturesASideOfVividImagesAtTheAnglesTheModbusPeerReports) {
  auto peer = testing::ModbusTestServer::StartTcp({});
  peer->SetRestErrorSteps(kRestError);
  ASSERT_TRUE(gpiosim::SetPull(g_sim, 0, false));
  test::TempDir t;
  test::Daemon d(WriteConfig(t.path(), *peer), t.path(), 60);
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());

  // All three devices up: each names the real device behind it.
  json h;
  ASSERT_TRUE(Eventually(
      [&] {
        h = d.Get("/api/v1/health");
        if (!h.is_object()) return false;
        for (const char* dev : {"camera", "turntable", "button"}) {
          if (h["devices"][dev].value("state", "") != "ok") {
            std::this_thread::sleep_for(std::chrono::milliseconds(100));  // spare the guest's CPUs
            return false;
          }
        }
        return true;
      },
      90))
      << h.dump(2) << ReadAll(d.log());
  EXPECT_EQ(h["devices"]["camera"]["backend"], "v4l2");
  EXPECT_NE(h["devices"]["camera"].value("model", "").find("(vivid, "), std::string::npos)
      << h["devices"]["camera"].dump();
  EXPECT_EQ(h["devices"]["turntable"]["backend"], "modbus-tcp");
  EXPECT_EQ(h["devices"]["turntable"]["id"], "127.0.0.1:" + std::to_string(peer->port()) + "/1");
  EXPECT_EQ(h["devices"]["button"]["backend"], "gpio");

  int code = 0;
  json r = d.Post("/api/v1/samples", R"({"id": "rock-full"})", &code);
  ASSERT_EQ(code, 200) << r.dump();
  json st = d.Get("/api/v1/status");
  ASSERT_EQ(st["state"], "armed") << st.dump();

  ASSERT_TRUE(gpiosim::SetPull(g_sim, 0, true));  // the operator presses start
  ASSERT_TRUE(d.WaitFor([](const json& s) { return s.value("state", "") != "armed"; }, 60, &st))
      << st.dump() << ReadAll(d.log());
  ASSERT_TRUE(gpiosim::SetPull(g_sim, 0, false));
  EXPECT_NE(ReadAll(d.log()).find("start button pressed (gpio)"), std::string::npos)
      << ReadAll(d.log());
  ASSERT_TRUE(d.WaitFor(
      [](const json& s) {
        return s.value("state", "") == "idle" && s.value("views_captured", 0) == kViews;
      },
      180, &st))
      << st.dump() << ReadAll(d.log());

  // The peer: homed, then one move per further view, each at rest
  // kRestError steps past its target.
  EXPECT_TRUE(peer->homed());
  std::vector<int64_t> targets, rests;
  for (int i = 1; i < kViews; ++i) {
    targets.push_back(8000 * i);
    rests.push_back(8000 * i + kRestError);
  }
  EXPECT_EQ(peer->move_targets(), targets);
  EXPECT_EQ(peer->rest_positions(), rests);
  EXPECT_EQ(peer->position_steps(), rests.back());

  const std::string side = t.path() + "/state/samples/rock-full/side1";
  for (int i = 0; i < kViews; ++i) {
    SCOPED_TRACE("view " + std::to_string(i));
    char stem[32];
    std::snprintf(stem, sizeof(stem), "/view_%03d", i);
    // A real vivid frame of the negotiated size, not an empty or sim image.
    const cv::Mat img = cv::imread(side + stem + ".jpg", cv::IMREAD_COLOR);
    ASSERT_FALSE(img.empty()) << side + stem + ".jpg is missing or no image";
    EXPECT_EQ(img.cols, g_width);
    EXPECT_EQ(img.rows, g_height);
    cv::Scalar mean, sd;
    cv::meanStdDev(img, mean, sd);
    EXPECT_GT(sd[0] + sd[1] + sd[2], 30) << "a flat image, not vivid's colour bars";
    json car = json::parse(ReadAll(side + stem + ".json"), nullptr, false);
    ASSERT_TRUE(car.is_object()) << side + stem + ".json";
    EXPECT_EQ(car["camera_id"], "vivid0");
    EXPECT_EQ(car["camera_backend"], "v4l2");
    EXPECT_EQ(car["width"], g_width);
    EXPECT_EQ(car["height"], g_height);
    // The angle the peer reported at the shot: view 0 at home (0 steps),
    // the others where the peer's moves came to rest, not the commanded angle.
    const double commanded = 90.0 * i;
    const int64_t peer_steps = i == 0 ? 0 : rests[i - 1];
    EXPECT_DOUBLE_EQ(car["commanded_angle_deg"].get<double>(), commanded);
    EXPECT_NEAR(car["measured_angle_deg"].get<double>(),
                static_cast<double>(peer_steps) / kStepsPerDeg, 1e-9);
    if (i > 0) {
      EXPECT_GT(std::fabs(car["measured_angle_deg"].get<double>() - commanded), 10 / kStepsPerDeg)
          << "the measured angle must be the peer's, not the commanded one";
    }
  }
  EXPECT_EQ(d.Stop(), 0) << ReadAll(d.log());
}

}  // namespace
}  // namespace aggscan

int main(int argc, char** argv) {
  namespace gpiosim = aggscan::test::gpiosim;
  ::testing::InitGoogleTest(&argc, argv);
  if (!gpiosim::Available()) {
    std::fprintf(stderr,
                 "full_rig_test: SKIP: no %s (gpio-sim not loaded or configfs not mounted; "
                 "tests/vm/run-in-vm.sh --modules DIR --modprobe gpio-sim does both in a VM)\n",
                 gpiosim::kConfigfs);
    return 77;
  }
  aggscan::g_vivid = aggscan::FindVivid();
  if (aggscan::g_vivid.empty()) {
    std::fprintf(stderr,
                 "full_rig_test: SKIP: no vivid capture node (run-in-vm.sh --modprobe "
                 "\"vivid n_devs=1 node_types=0x1\" loads it)\n");
    return 77;
  }
  if (!aggscan::SmallestYuyvSize(aggscan::g_vivid, &aggscan::g_width, &aggscan::g_height)) {
    std::fprintf(stderr, "full_rig_test: %s lists no YUYV frame size\n", aggscan::g_vivid.c_str());
    return 1;
  }
  gpiosim::BringUpLoopback();
  const std::string err = gpiosim::MakeChip(&aggscan::g_sim);
  if (!err.empty()) {
    std::fprintf(stderr, "full_rig_test: cannot create the gpio-sim chip: %s\n", err.c_str());
    return 1;
  }
  std::fprintf(stderr, "full_rig_test: vivid %s at %dx%d, gpio-sim chip %s\n",
               aggscan::g_vivid.c_str(), aggscan::g_width, aggscan::g_height,
               aggscan::g_sim.name.c_str());
  return RUN_ALL_TESTS();
}
