// The V4L2 camera backend against the kernel's vivid test driver. Meant to
// run inside the throwaway VM of tests/vm/run-in-vm.sh (vivid loaded with
// n_devs=1 node_types=0x1); exits 77 (skipped) where no vivid capture node
// exists. The test pokes vivid's own controls (dropped buffers, error
// injection, disconnect) through a second file descriptor, as another
// program would. The disconnect test unregisters the device, so it runs last.
#include <fcntl.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <linux/videodev2.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <string>
#include <thread>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/factory.h"
#include "drivers/sim/jpeg.h"
#include "drivers/v4l2/v4l2_camera.h"
#include "tests/drivers/camera_test_util.h"

namespace aggscan::v4l2 {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

std::string g_vivid;  // the vivid capture node found at start-up

// A second handle on the device, for vivid's test controls.
class Side {
 public:
  Side() : fd_(::open(g_vivid.c_str(), O_RDWR | O_CLOEXEC)) {}
  ~Side() {
    if (fd_ >= 0) ::close(fd_);
  }
  uint32_t Find(const std::string& name) const {
    v4l2_queryctrl q{};
    q.id = V4L2_CTRL_FLAG_NEXT_CTRL;
    while (::ioctl(fd_, VIDIOC_QUERYCTRL, &q) == 0) {
      if (name == reinterpret_cast<const char*>(q.name)) return q.id;
      q.id |= V4L2_CTRL_FLAG_NEXT_CTRL;
    }
    ADD_FAILURE() << "vivid has no control \"" << name << "\"";
    return 0;
  }
  bool Set(uint32_t id, int value) const {
    v4l2_control c{id, value};
    return ::ioctl(fd_, VIDIOC_S_CTRL, &c) == 0;
  }
  bool Set(const std::string& name, int value) const { return Set(Find(name), value); }
  int Get(uint32_t id) const {
    v4l2_control c{id, 0};
    EXPECT_EQ(::ioctl(fd_, VIDIOC_G_CTRL, &c), 0) << std::strerror(errno);
    return c.value;
  }

 private:
  int fd_;
};

CameraConfig BaseConfig() {
  CameraConfig c;
  c.backend = "v4l2";
  c.id = "vivid0";
  c.device = g_vivid;
  c.width = 640;
  c.height = 480;
  c.v4l2.strict_controls = false;  // vivid has gain but no exposure or white balance controls
  c.v4l2.frame_timeout = 5 * kNsPerSec;
  return c;
}

CameraSettings Settings(const CameraConfig& c, double gain = 1.5) {
  CameraSettings s;
  s.width = c.width;
  s.height = c.height;
  s.manual_exposure = true;
  s.exposure_us = 6000;
  s.gain = gain;
  return s;
}

Result<FramePtr> TakeStill(Camera& cam, uint64_t id, std::thread::id* on = nullptr) {
  return testutil::TakeStill(cam, {id, "vivid", 1, static_cast<int>(id)}, on);
}

// Mappings of the video node in this process (buffers still mapped).
int MappedVideoBuffers() {
  std::ifstream maps("/proc/self/maps");
  std::string line;
  int n = 0;
  while (std::getline(maps, line))
    if (line.find(g_vivid) != std::string::npos) ++n;
  return n;
}

using testutil::At;
using testutil::Rgb;

class Vivid : public ::testing::Test {
 protected:
  RealClock clock_;
};

TEST_F(Vivid, OpensByPathAndByUdevName) {
  V4l2Camera cam(clock_, BaseConfig());
  ASSERT_TRUE(cam.Open());
  EXPECT_EQ(cam.device_path(), g_vivid);
  EXPECT_THAT(cam.Info().model, HasSubstr("vivid"));
  EXPECT_EQ(cam.Info().backend, "v4l2");
  cam.Close();
  // The VM has no udev: make the by-id link udev would make, then use its bare name.
  if (std::getenv("AGGSCAN_IN_VM") == nullptr) GTEST_SKIP() << "not touching /dev outside the VM";
  namespace fs = std::filesystem;
  fs::create_directories("/dev/v4l/by-id");
  fs::remove("/dev/v4l/by-id/platform-vivid.0-video-index0");
  fs::create_symlink(g_vivid, "/dev/v4l/by-id/platform-vivid.0-video-index0");
  CameraConfig c = BaseConfig();
  c.device = "platform-vivid.0-video-index0";
  V4l2Camera byname(clock_, c);
  ASSERT_TRUE(byname.Open());
  EXPECT_EQ(byname.device_path(), g_vivid);
  byname.Close();
}

TEST_F(Vivid, StillsAreFreshOnTheDriverThreadWithTheGainReadBack) {
  CameraConfig c = BaseConfig();
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(c)));
  // vivid offers no MJPEG, so "auto" picks YUYV.
  EXPECT_EQ(cam.negotiated().fourcc, static_cast<uint32_t>(V4L2_PIX_FMT_YUYV));
  EXPECT_EQ(MappedVideoBuffers(), c.v4l2.buffers)
      << "one mapping per driver buffer while streaming";
  Side side;
  EXPECT_EQ(side.Get(V4L2_CID_AUTOGAIN), 0) << "auto gain must be off";
  EXPECT_EQ(side.Get(V4L2_CID_GAIN), 150) << "gain 1.5 x the control's default 100";
  std::this_thread::sleep_for(
      std::chrono::milliseconds(400));  // let every buffer fill with stale frames
  uint64_t last_seq = 0;
  for (uint64_t v = 0; v < 3; ++v) {
    const TimeNs asked = clock_.Now();
    std::thread::id on;
    Result<FramePtr> f = TakeStill(cam, v, &on);
    ASSERT_TRUE(f.ok()) << f.error().ToString();
    const Frame& fr = **f;
    EXPECT_NE(on, std::this_thread::get_id());
    EXPECT_EQ(fr.request_id, v);
    EXPECT_GE(fr.exposure_start, asked)
        << "a frame queued before the request must not be the still";
    if (v > 0) {
      EXPECT_GT(fr.sequence, last_seq);
    }
    last_seq = fr.sequence;
    EXPECT_DOUBLE_EQ(fr.gain, 1.5);
    EXPECT_DOUBLE_EQ(fr.exposure_us, 0.0);
    EXPECT_THAT(fr.missing_controls, ElementsAre("exposure", "wb_red", "wb_blue"));
    EXPECT_EQ(cam.state(), Camera::State::kReady);
  }
  EXPECT_GE(cam.stale_frames(), 1u) << "the buffers filled during the pause were skipped";
  cam.Close();
  EXPECT_EQ(MappedVideoBuffers(), 0) << "Close must unmap every buffer";
}

TEST_F(Vivid, StrictControlsRefuseADeviceWithoutExposure) {
  CameraConfig c = BaseConfig();
  c.v4l2.strict_controls = true;
  c.v4l2.focus = 50;  // vivid has no focus either
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  Status s = cam.Configure(Settings(c));
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(s.error().message, HasSubstr("no control for exposure, wb_red, wb_blue, focus"));
  EXPECT_EQ(cam.state(), Camera::State::kOpened);
  EXPECT_EQ(MappedVideoBuffers(), 0);
  // Automatic exposure locks nothing, so a strict camera configures, with
  // vivid's automatic gain switched back on.
  CameraSettings automatic = Settings(c);
  automatic.manual_exposure = false;
  c.v4l2.focus = -1;
  V4l2Camera autocam(clock_, c);
  cam.Close();
  ASSERT_TRUE(autocam.Open());
  Status a = autocam.Configure(automatic);
  ASSERT_TRUE(a.ok()) << a.error().ToString();
  EXPECT_EQ(Side().Get(V4L2_CID_AUTOGAIN), 1);
  Result<FramePtr> f = TakeStill(autocam, 1);
  ASSERT_TRUE(f.ok()) << f.error().ToString();
  EXPECT_TRUE((*f)->missing_controls.empty());
  // What vivid's automatic gain chose, read back in units of its default
  // (100). vivid's automatic gain steps by one a second, hence the tolerance.
  EXPECT_NEAR((*f)->gain, Side().Get(V4L2_CID_GAIN) / 100.0, 0.015);
  EXPECT_LE((*f)->gain, 2.55);
  autocam.Close();
}

TEST_F(Vivid, GainOutsideTheControlRangeIsRefusedAndGainUnitApplies) {
  CameraConfig c = BaseConfig();
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  Status s = cam.Configure(Settings(c, 3.0));  // 300 > vivid's 255
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.error().message, HasSubstr("outside the control's range 0..255"));
  cam.Close();
  c.v4l2.gain_unit = 40;
  V4l2Camera unit(clock_, c);
  ASSERT_TRUE(unit.Open());
  ASSERT_TRUE(unit.Configure(Settings(c, 2.5)));
  EXPECT_EQ(Side().Get(V4L2_CID_GAIN), 100);
  Result<FramePtr> f = TakeStill(unit, 1);
  ASSERT_TRUE(f.ok()) << f.error().ToString();
  EXPECT_DOUBLE_EQ((*f)->gain, 2.5);
  unit.Close();
}

// Every format: the 75 % colour bars (white, yellow, cyan, green, magenta,
// red, blue, black) must come out in the right colours, so the conversion
// of each layout is checked, not just the size.
TEST_F(Vivid, SeveralPixelFormatsGiveTheSameColourBars) {
  for (const char* fmt : {"yuyv", "uyvy", "nv12", "rgb24", "bgr24", "grey"}) {
    SCOPED_TRACE(fmt);
    CameraConfig c = BaseConfig();
    c.v4l2.pixel_format = fmt;
    V4l2Camera cam(clock_, c);
    ASSERT_TRUE(cam.Open());
    ASSERT_TRUE(cam.Configure(Settings(c)));
    EXPECT_EQ(cam.negotiated().fourcc, *FormatFromName(fmt));
    Result<FramePtr> f = TakeStill(cam, 7);
    ASSERT_TRUE(f.ok()) << f.error().ToString();
    Result<sim::RgbImage> img = sim::DecodeJpeg((*f)->data);
    ASSERT_TRUE(img.ok());
    ASSERT_EQ(img->width, 640);
    ASSERT_EQ(img->height, 480);
    const int y = 300;  // below vivid's text overlay
    auto bar = [&](int i) { return At(*img, img->width * (2 * i + 1) / 16, y); };
    if (std::string(fmt) == "grey") {
      EXPECT_GT(bar(0).r, 150);
      EXPECT_LT(bar(7).r, 40);
      EXPECT_GT(bar(1).r, bar(6).r + 60) << "yellow is much brighter than blue";
    } else {
      const Rgb white = bar(0), yellow = bar(1), red = bar(5), blue = bar(6), black = bar(7);
      EXPECT_GT(white.r, 150);
      EXPECT_GT(white.g, 150);
      EXPECT_GT(white.b, 150);
      EXPECT_GT(yellow.r, 150);
      EXPECT_GT(yellow.g, 150);
      EXPECT_LT(yellow.b, 60);
      EXPECT_GT(red.r, 150);
      EXPECT_LT(red.g, 60);
      EXPECT_LT(red.b, 60);
      EXPECT_LT(blue.r, 60);
      EXPECT_LT(blue.g, 60);
      EXPECT_GT(blue.b, 150);
      EXPECT_LT(black.r + black.g + black.b, 60);
    }
    cam.Close();
  }
}

TEST_F(Vivid, NoFrameInTimeIsATimeoutAndTheCameraRecovers) {
  CameraConfig c = BaseConfig();
  c.v4l2.frame_timeout = 600 * kNsPerMs;
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(c)));
  Side side;
  ASSERT_TRUE(side.Set("Percentage of Dropped Buffers", 100));
  const auto t0 = std::chrono::steady_clock::now();
  Result<FramePtr> f = TakeStill(cam, 1);
  const double waited =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  ASSERT_FALSE(f.ok());
  EXPECT_EQ(f.error().cls, ErrorClass::kTimeout) << f.error().ToString();
  EXPECT_GE(waited, 0.55);
  EXPECT_LT(waited, 3.0);
  EXPECT_EQ(cam.state(), Camera::State::kReady);
  ASSERT_TRUE(side.Set("Percentage of Dropped Buffers", 0));
  Result<FramePtr> again = TakeStill(cam, 2);
  EXPECT_TRUE(again.ok()) << again.error().ToString();
  cam.Close();
}

TEST_F(Vivid, AFrameFlaggedAsErroneousIsNotDelivered) {
  CameraConfig c = BaseConfig();
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(c)));
  Side side;
  ASSERT_TRUE(TakeStill(cam, 1).ok());
  EXPECT_EQ(cam.corrupt_frames(), 0u);
  ASSERT_TRUE(side.Set("Inject V4L2_BUF_FLAG_ERROR", 0));
  Result<FramePtr> f = TakeStill(cam, 2);
  ASSERT_TRUE(f.ok()) << f.error().ToString();
  EXPECT_FALSE((*f)->data.empty());
  EXPECT_EQ(cam.corrupt_frames(), 1u) << "the flagged frame was skipped, the next one delivered";
  cam.Close();
}

// vivid's fatal streaming error puts the queue in its error state (what a
// driver does when the hardware stops mid-stream): the still fails as a
// device fault, and configuring again restarts the stream.
TEST_F(Vivid, AFatalStreamingErrorIsADeviceFaultUntilReconfigured) {
  CameraConfig c = BaseConfig();
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(c)));
  ASSERT_TRUE(Side().Set("Inject Fatal Streaming Error", 0));
  Result<FramePtr> f = TakeStill(cam, 1);
  ASSERT_FALSE(f.ok());
  EXPECT_EQ(f.error().cls, ErrorClass::kDeviceFault) << f.error().ToString();
  ASSERT_TRUE(cam.Configure(Settings(c)));
  Result<FramePtr> again = TakeStill(cam, 2);
  EXPECT_TRUE(again.ok()) << again.error().ToString();
  cam.Close();
  EXPECT_EQ(MappedVideoBuffers(), 0);
}

TEST_F(Vivid, AStreamOnFailureIsReportedAndBuffersReleased) {
  CameraConfig c = BaseConfig();
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(Side().Set("Inject VIDIOC_STREAMON Error", 0));
  Status s = cam.Configure(Settings(c));
  ASSERT_FALSE(s.ok());
  EXPECT_THAT(s.error().message, HasSubstr("VIDIOC_STREAMON"));
  EXPECT_EQ(cam.state(), Camera::State::kOpened);
  EXPECT_EQ(MappedVideoBuffers(), 0) << "a failed start must unmap what it mapped";
  ASSERT_TRUE(cam.Configure(Settings(c))) << "the next attempt works";
  EXPECT_TRUE(TakeStill(cam, 1).ok());
  cam.Close();
}

TEST_F(Vivid, CloseWithAStillInFlightDeliversExactlyOnce) {
  CameraConfig c = BaseConfig();
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(c)));
  Side side;
  ASSERT_TRUE(side.Set("Percentage of Dropped Buffers", 100));  // keep the still pending
  std::atomic<int> calls{0};
  ErrorClass cls = ErrorClass::kInternal;
  ASSERT_TRUE(cam.RequestStill({1, "c", 1, 0}, [&](Result<FramePtr> r) {
    if (!r) cls = r.error().cls;
    ++calls;
  }));
  EXPECT_EQ(cam.RequestStill({2, "c", 1, 1}, [](Result<FramePtr>) {}).error().cls,
            ErrorClass::kInvalidState);
  cam.Close();
  EXPECT_EQ(calls.load(), 1);
  EXPECT_EQ(cls, ErrorClass::kInvalidState);
  EXPECT_EQ(MappedVideoBuffers(), 0);
  ASSERT_TRUE(side.Set("Percentage of Dropped Buffers", 0));
}

// The largest frame size the device lists for YUYV (vivid's webcam input:
// 3840x2160), as the rig's full-resolution still.
TEST_F(Vivid, FullResolutionStill) {
  const auto [w, h] = testutil::LargestFrameSize(g_vivid, V4L2_PIX_FMT_YUYV);
  ASSERT_GT(w, 640);
  CameraConfig c = BaseConfig();
  c.width = w;
  c.height = h;
  c.v4l2.frame_timeout = 30 * kNsPerSec;  // vivid draws large frames slowly under TCG
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  Status s = cam.Configure(Settings(c));
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  Result<FramePtr> f = TakeStill(cam, 1);
  ASSERT_TRUE(f.ok()) << f.error().ToString();
  Result<sim::RgbImage> img = sim::DecodeJpeg((*f)->data);
  ASSERT_TRUE(img.ok());
  EXPECT_EQ(img->width, w);
  EXPECT_EQ(img->height, h);
  std::fprintf(stderr, "full-resolution still: %dx%d, %zu JPEG bytes\n", w, h, (*f)->data.size());
  cam.Close();
}

// vivid's webcam input lists discrete sizes, so 641 wide cannot be had: the
// backend refuses rather than shoot at a size the config did not ask for.
TEST_F(Vivid, ASizeTheDeviceCannotGiveIsRefused) {
  CameraConfig c = BaseConfig();
  c.width = 641;
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  testutil::ExpectConfigureRefused(cam, Settings(c),
                                   "cannot deliver YUYV 641x480; it offers YUYV 640x480");
  cam.Close();
}

// Last: vivid's "Disconnect" makes the node refuse everything with ENODEV,
// like a USB unplug; vivid "replugs" once every file handle is closed.
TEST_F(Vivid, ZzUnplugIsDisconnectedThenMissingThenRecovers) {
  CameraConfig c = BaseConfig();
  V4l2Camera cam(clock_, c);
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(c)));
  ASSERT_TRUE(TakeStill(cam, 1).ok());
  {
    Side side;  // holds the device: vivid stays unplugged while it is open
    ASSERT_TRUE(side.Set("Percentage of Dropped Buffers", 100));
    std::promise<Result<FramePtr>> p;
    auto fut = p.get_future();
    ASSERT_TRUE(
        cam.RequestStill({2, "c", 1, 1}, [&](Result<FramePtr> r) { p.set_value(std::move(r)); }));
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    ASSERT_TRUE(side.Set("Disconnect", 0));
    ASSERT_EQ(fut.wait_for(std::chrono::seconds(10)), std::future_status::ready);
    Result<FramePtr> r = fut.get();
    ASSERT_FALSE(r.ok());
    EXPECT_EQ(r.error().cls, ErrorClass::kDisconnected) << r.error().ToString();
    cam.Close();
    EXPECT_EQ(MappedVideoBuffers(), 0);
    Status again = cam.Open();
    ASSERT_FALSE(again.ok());
    EXPECT_EQ(again.error().cls, ErrorClass::kDeviceMissing) << again.error().ToString();
  }
  // Every handle closed: vivid is back, and so is the camera.
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(c)));
  Side().Set("Percentage of Dropped Buffers", 0);
  Result<FramePtr> f = TakeStill(cam, 3);
  EXPECT_TRUE(f.ok()) << f.error().ToString();
  cam.Close();
}

}  // namespace
}  // namespace aggscan::v4l2
int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  aggscan::v4l2::g_vivid = aggscan::testutil::FindCaptureNode("vivid");
  if (aggscan::v4l2::g_vivid.empty()) {
    std::fprintf(
        stderr,
        "v4l2_vivid_test: SKIP: no vivid capture node (modprobe vivid n_devs=1 node_types=0x1; "
        "tests/vm/run-in-vm.sh does this in a VM)\n");
    return 77;
  }
  std::fprintf(stderr, "v4l2_vivid_test: vivid at %s\n", aggscan::v4l2::g_vivid.c_str());
  return RUN_ALL_TESTS();
}
