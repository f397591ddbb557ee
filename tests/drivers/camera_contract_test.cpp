// Camera contract: what the capture service relies on from every camera
// backend, each built through the factory as the daemon builds it. The sim
// camera runs everywhere (on a virtual clock). The V4L2 backend runs against
// the kernel's vivid driver and the libcamera backend against vimc through
// libcamera's vimc pipeline handler, both inside the VM lane
// (tests/drivers/camera_vm.sh sets AGGSCAN_V4L2_CONTRACT_DRIVER /
// AGGSCAN_LIBCAMERA_CONTRACT_CAMERA there); elsewhere those are skipped.
//
// A real peer may lack a control a locked setting needs (vivid has no
// exposure or white balance control, vimc none at all). The contract for
// that: a strict camera refuses Configure naming every such setting; a
// lenient one shoots and every frame names them in missing_controls, where
// their values read 0 (exposure, gain) or 1 (white balance), never the value
// asked for. Every setting not named is the locked value, on every view.
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <linux/videodev2.h>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <future>
#include <memory>
#include <ostream>
#include <stdexcept>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/factory.h"
#include "drivers/sim/jpeg.h"
#include "tests/drivers/camera_test_util.h"
#ifdef AGGSCAN_HAVE_LIBCAMERA
#include "drivers/libcamera/libcamera_camera.h"
#endif

namespace aggscan {
namespace {

using ::testing::HasSubstr;

// What a backend's harness sets up: the config (its camera section; every
// other device is the sim), the sizes its device gives exactly, and why it
// cannot run here (empty: it can).
struct CameraSetup {
  Config config;
  int width = 640, height = 480;              // an ordinary still
  int full_width = 4032, full_height = 3024;  // the largest still the device gives
  int small_width = 320, small_height = 240;  // another size it gives
  // A size in range the device cannot give exactly; 0 x 0: it gives every size.
  int odd_width = 0, odd_height = 0;
  bool virtual_clock = false;
  std::shared_ptr<void> keep_alive;  // held for the test (libcamera's manager)
  std::string skip;
};

struct BackendParam {
  const char* name;
  CameraSetup (*setup)();
};

CameraSetup SetupSim() {
  CameraSetup s;
  s.config.camera.backend = "sim";  // any size; full: the rig's 12 MP mode
  s.virtual_clock = true;
  return s;
}

// vivid, found by its driver name (AGGSCAN_V4L2_CONTRACT_DRIVER=vivid).
CameraSetup SetupV4l2() {
  CameraSetup s;
  const char* driver = std::getenv("AGGSCAN_V4L2_CONTRACT_DRIVER");
  if (!driver) {
    s.skip = "v4l2: no device here (VM lane only: tests/drivers/camera_vm.sh)";
    return s;
  }
  const std::string node = testutil::FindCaptureNode(driver);
  if (node.empty()) {
    ADD_FAILURE() << "AGGSCAN_V4L2_CONTRACT_DRIVER=" << driver
                  << " but no capture node of that driver";
    s.skip = "no device";
    return s;
  }
  CameraConfig& c = s.config.camera;
  c.backend = "v4l2";
  c.device = node;
  c.id = driver;
  c.v4l2.strict_controls = false;
  // Bounds, not speed checks: vivid draws 4K frames slowly under QEMU/TCG.
  c.v4l2.frame_timeout = 60 * kNsPerSec;
  std::tie(s.full_width, s.full_height) = testutil::LargestFrameSize(node, V4L2_PIX_FMT_YUYV);
  // vivid's webcam input lists discrete sizes: 320x180 is one, 641 wide is not.
  s.small_height = 180;
  s.odd_width = 641;
  s.odd_height = 480;
  return s;
}

// The libcamera camera whose id contains AGGSCAN_LIBCAMERA_CONTRACT_CAMERA
// (vimc), listed by libcamera's own CameraManager.
CameraSetup SetupLibcamera() {
  CameraSetup s;
  const char* want = std::getenv("AGGSCAN_LIBCAMERA_CONTRACT_CAMERA");
  if (!want) {
    s.skip = "libcamera: no camera here (VM lane only: tests/drivers/camera_vm.sh)";
    return s;
  }
#ifdef AGGSCAN_HAVE_LIBCAMERA
  auto manager = lc::SharedCameraManager();
  if (!manager) {
    ADD_FAILURE() << manager.error().ToString();
    s.skip = "no camera manager";
    return s;
  }
  CameraConfig& c = s.config.camera;
  for (const auto& cam : (*manager)->cameras())
    if (cam->id().find(want) != std::string::npos) c.libcamera.camera_id = cam->id();
  if (c.libcamera.camera_id.empty()) {
    ADD_FAILURE() << "AGGSCAN_LIBCAMERA_CONTRACT_CAMERA=" << want
                  << " but libcamera lists no such camera";
    s.skip = "no camera";
    return s;
  }
  s.keep_alive = *manager;  // one manager for the whole test, as the daemon holds it
  c.backend = "libcamera";
  c.id = want;
  c.libcamera.strict_controls = false;
  c.libcamera.frame_timeout = 60 * kNsPerSec;  // seconds a 4K frame under QEMU/TCG
  // vimc's pipeline gives multiples of 6 (its scaler), up to 4096x2160.
  s.width = 636;
  s.full_width = 4092;
  s.full_height = 2160;
  s.small_width = 480;
  s.small_height = 360;
  s.odd_width = 640;
  s.odd_height = 480;
#else
  s.skip = "libcamera: this build has no libcamera support";
#endif
  return s;
}

// Readable names where gtest prints the parameter.
void PrintTo(const BackendParam& b, std::ostream* os) { *os << b.name; }

const BackendParam kBackends[] = {
    {"sim", SetupSim}, {"v4l2", SetupV4l2}, {"libcamera", SetupLibcamera}};

// The locked settings every test asks for (white balance off neutral, so a
// backend that ignores it is seen).
CameraSettings Settings(int w, int h) {
  CameraSettings s;
  s.width = w;
  s.height = h;
  s.manual_exposure = true;
  s.exposure_us = 6000;
  s.gain = 1.5;
  s.wb_red = 1.25;
  s.wb_blue = 0.75;
  return s;
}

// Takes one still and waits for it (bounded: a hang guard, longer than any
// backend's frame timeout).
Result<FramePtr> TakeStill(Camera& cam, int view, std::thread::id* delivered_on = nullptr) {
  return testutil::TakeStill(cam, {static_cast<uint64_t>(100 + view), "contract", 1, view},
                             delivered_on, std::chrono::seconds(120));
}

// Takes a still and checks it is a JPEG of w x h, framed as that; null when
// there is none (the failure is recorded).
FramePtr ExpectStill(Camera& cam, int view, int w, int h, std::thread::id* delivered_on = nullptr) {
  Result<FramePtr> f = TakeStill(cam, view, delivered_on);
  if (!f.ok()) {
    ADD_FAILURE() << "still " << view << ": " << f.error().ToString();
    return nullptr;
  }
  const Frame& fr = **f;
  EXPECT_EQ(fr.request_id, static_cast<uint64_t>(100 + view));
  EXPECT_EQ(fr.encoding, "jpeg");
  EXPECT_EQ(fr.width, w);
  EXPECT_EQ(fr.height, h);
  auto img = sim::DecodeJpeg(fr.data);
  EXPECT_TRUE(img.ok()) << img.error().ToString();
  if (img.ok()) {
    EXPECT_EQ(img->width, w);
    EXPECT_EQ(img->height, h);
  }
  return *f;
}

bool Named(const Frame& f, const std::string& setting) {
  return std::find(f.missing_controls.begin(), f.missing_controls.end(), setting) !=
         f.missing_controls.end();
}

// Every locked setting is either the locked value or named as missing, with
// the neutral reading the contract gives it.
void ExpectLockedOrNamed(const Frame& f, const CameraSettings& s) {
  for (const std::string& m : f.missing_controls)
    EXPECT_THAT((std::vector<std::string>{"exposure", "gain", "wb_red", "wb_blue", "focus"}),
                ::testing::Contains(m))
        << "unknown setting named missing";
  struct Check {
    const char* name;
    double got, locked, unknown;
  };
  for (const Check& c :
       {Check{"exposure", f.exposure_us, s.exposure_us, 0.0}, Check{"gain", f.gain, s.gain, 0.0},
        Check{"wb_red", f.wb_red, s.wb_red, 1.0}, Check{"wb_blue", f.wb_blue, s.wb_blue, 1.0}}) {
    if (Named(f, c.name)) {
      EXPECT_DOUBLE_EQ(c.got, c.unknown) << c.name << " has no control: it must not read as locked";
    } else {
      EXPECT_DOUBLE_EQ(c.got, c.locked) << c.name << " is locked and read back";
    }
  }
}

class CameraContract : public ::testing::TestWithParam<BackendParam> {
 protected:
  void SetUp() override {
    setup_ = GetParam().setup();
    if (!setup_.skip.empty()) GTEST_SKIP() << setup_.skip;
  }

  // The camera of a rig built from the harness's config, `change` applied.
  Camera& Make(const std::function<void(CameraConfig&)>& change = {}) {
    Config c = setup_.config;
    c.turntable.backend = c.button.backend = "sim";
    c.camera.width = setup_.width;
    c.camera.height = setup_.height;
    if (change) change(c.camera);
    rig_ = {};  // a camera made before goes before its clock
    if (setup_.virtual_clock) {
      clock_ = std::make_unique<VirtualClock>();
    } else {
      clock_ = std::make_unique<RealClock>();
    }
    auto rig = CreateRig(c, *clock_);
    if (!rig.ok()) throw std::runtime_error(rig.error().ToString());
    rig_ = std::move(*rig);
    return *rig_.camera;
  }

  CameraSettings Ordinary() const { return Settings(setup_.width, setup_.height); }

  void TearDown() override {
    if (rig_.camera) rig_.camera->Close();
    rig_ = {};
    clock_.reset();
  }

  CameraSetup setup_;
  std::unique_ptr<Clock> clock_;
  RigDevices rig_;
};

TEST_P(CameraContract, CallsInTheWrongStateAreRejected) {
  Camera& cam = Make();
  EXPECT_EQ(cam.state(), Camera::State::kClosed);
  EXPECT_EQ(cam.Configure(Ordinary()).error().cls, ErrorClass::kInvalidState);
  EXPECT_EQ(cam.RequestStill({}, [](Result<FramePtr>) {}).error().cls, ErrorClass::kInvalidState);
  Status open = cam.Open();
  ASSERT_TRUE(open.ok()) << open.error().ToString();
  EXPECT_EQ(cam.Open().error().cls, ErrorClass::kInvalidState);
  EXPECT_EQ(cam.RequestStill({}, [](Result<FramePtr>) {}).error().cls, ErrorClass::kInvalidState)
      << "a still before Configure must be refused";
  cam.Close();
  EXPECT_EQ(cam.state(), Camera::State::kClosed);
}

TEST_P(CameraContract, BadSettingsAreRejectedWithAReason) {
  Camera& cam = Make();
  ASSERT_TRUE(cam.Open());
  for (CameraSettings bad : {Settings(8, setup_.height), Settings(setup_.width, 20000)}) {
    Status s = cam.Configure(bad);
    ASSERT_FALSE(s.ok());
    EXPECT_EQ(s.error().cls, ErrorClass::kInvalidArgument);
    EXPECT_NE(s.error().message.find("resolution"), std::string::npos);
  }
  CameraSettings q = Ordinary();
  q.jpeg_quality = 0;
  EXPECT_EQ(cam.Configure(q).error().cls, ErrorClass::kInvalidArgument);
  CameraSettings e = Ordinary();
  e.exposure_us = 0;
  EXPECT_EQ(cam.Configure(e).error().cls, ErrorClass::kInvalidArgument);
  EXPECT_EQ(cam.state(), Camera::State::kOpened) << "refused settings leave the camera as it was";
  cam.Close();
}

TEST_P(CameraContract, StillsArriveOnTheDriverThreadWithLockedExposure) {
  Camera& cam = Make();
  ASSERT_TRUE(cam.Open());
  const CameraSettings settings = Ordinary();
  Status cs = cam.Configure(settings);
  ASSERT_TRUE(cs.ok()) << cs.error().ToString();
  EXPECT_EQ(cam.state(), Camera::State::kReady);
  uint64_t last_seq = 0;
  TimeNs last_t = -1;
  std::vector<std::string> first_missing;
  for (int v = 0; v < 3; ++v) {
    const std::thread::id caller = std::this_thread::get_id();
    std::thread::id on = caller;
    FramePtr f = ExpectStill(cam, v, settings.width, settings.height, &on);
    ASSERT_TRUE(f);
    const Frame& fr = *f;
    EXPECT_NE(on, caller) << "frames must be delivered on the driver's own thread";
    // Exposure, gain and white balance are the locked values on every view,
    // or named as settings the device has no control for.
    ExpectLockedOrNamed(fr, settings);
    if (v == 0) first_missing = fr.missing_controls;
    EXPECT_EQ(fr.missing_controls, first_missing) << "every view shares the same settings";
    if (v > 0) {
      EXPECT_GT(fr.sequence, last_seq);
      EXPECT_GE(fr.exposure_start, last_t);
    }
    last_seq = fr.sequence;
    last_t = fr.exposure_start;
    EXPECT_GT(fr.utc_ns, 0);
    EXPECT_EQ(cam.state(), Camera::State::kReady);
  }
  cam.Close();
}

// A camera told to be strict either locks every setting or refuses to
// configure, naming exactly the settings a lenient one reports as missing.
TEST_P(CameraContract, StrictControlsLockEverythingOrNameWhatTheyCannot) {
  Camera& lenient = Make();
  ASSERT_TRUE(lenient.Open());
  ASSERT_TRUE(lenient.Configure(Ordinary()));
  Result<FramePtr> f = TakeStill(lenient, 0);
  ASSERT_TRUE(f.ok()) << f.error().ToString();
  const std::vector<std::string> missing = (*f)->missing_controls;
  lenient.Close();

  Camera& strict =
      Make([](CameraConfig& c) { c.v4l2.strict_controls = c.libcamera.strict_controls = true; });
  ASSERT_TRUE(strict.Open());
  Status s = strict.Configure(Ordinary());
  if (missing.empty()) {
    ASSERT_TRUE(s.ok()) << s.error().ToString();
    Result<FramePtr> g = TakeStill(strict, 1);
    ASSERT_TRUE(g.ok()) << g.error().ToString();
    EXPECT_TRUE((*g)->missing_controls.empty());
    ExpectLockedOrNamed(**g, Ordinary());
  } else {
    std::string list;
    for (const auto& m : missing) list += (list.empty() ? "" : ", ") + m;
    std::fprintf(stderr, "%s: no control for %s\n", GetParam().name, list.c_str());
    ASSERT_FALSE(s.ok()) << "a strict camera must refuse settings it cannot lock: " << list;
    EXPECT_EQ(s.error().cls, ErrorClass::kInvalidConfig);
    EXPECT_THAT(s.error().message, HasSubstr("no control for " + list));
    EXPECT_THAT(s.error().message, HasSubstr("strict_controls")) << "the message says what to do";
    EXPECT_EQ(strict.state(), Camera::State::kOpened);
  }
  strict.Close();
}

TEST_P(CameraContract, OneStillAtATime) {
  Camera& cam = Make();
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Ordinary()));
  std::promise<void> first_done;
  ASSERT_TRUE(cam.RequestStill({1, "c", 1, 0}, [&](Result<FramePtr>) { first_done.set_value(); }));
  // A second request while the first is in flight is refused, not queued.
  Status second = cam.RequestStill({2, "c", 1, 1}, [](Result<FramePtr>) {});
  EXPECT_EQ(second.error().cls, ErrorClass::kInvalidState);
  first_done.get_future().wait();
  cam.Close();  // waits for nothing: the still is done
  EXPECT_EQ(cam.state(), Camera::State::kClosed);
}

TEST_P(CameraContract, CloseWithAStillInFlightDeliversItOrAnError) {
  Camera& cam = Make();
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Ordinary()));
  std::atomic<int> calls{0};
  ASSERT_TRUE(cam.RequestStill({1, "c", 1, 0}, [&](Result<FramePtr>) { ++calls; }));
  cam.Close();
  EXPECT_EQ(calls.load(), 1) << "the callback runs exactly once, before Close returns";
  EXPECT_EQ(cam.state(), Camera::State::kClosed);
}

// The daemon configures the camera again for each capture: the next still
// has the new size.
TEST_P(CameraContract, ConfigureAgainTakesTheNewSize) {
  Camera& cam = Make();
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Ordinary()));
  ASSERT_TRUE(ExpectStill(cam, 0, setup_.width, setup_.height));
  Status s = cam.Configure(Settings(setup_.small_width, setup_.small_height));
  ASSERT_TRUE(s.ok()) << s.error().ToString();
  EXPECT_EQ(cam.state(), Camera::State::kReady);
  EXPECT_TRUE(ExpectStill(cam, 1, setup_.small_width, setup_.small_height));
  cam.Close();
}

// A size the device cannot give exactly is refused as a config error naming
// it, and leaves a ready camera opened: not ready with settings it no longer
// has. A good Configure makes it ready again. A device that gives every size
// in range (the sim) shoots the odd size instead.
TEST_P(CameraContract, ASizeTheDeviceCannotGiveIsRefusedAndLeavesItOpened) {
  Camera& cam = Make();
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Ordinary()));
  ASSERT_TRUE(ExpectStill(cam, 0, setup_.width, setup_.height));
  const bool every_size = setup_.odd_width == 0;
  const CameraSettings odd =
      every_size ? Settings(641, 481) : Settings(setup_.odd_width, setup_.odd_height);
  Status s = cam.Configure(odd);
  if (every_size) {
    ASSERT_TRUE(s.ok()) << s.error().ToString();
    EXPECT_TRUE(ExpectStill(cam, 1, odd.width, odd.height));
  } else {
    ASSERT_FALSE(s.ok()) << "the device cannot give " << odd.width << "x" << odd.height;
    EXPECT_EQ(s.error().cls, ErrorClass::kInvalidConfig) << s.error().ToString();
    EXPECT_THAT(s.error().message,
                HasSubstr(std::to_string(odd.width) + "x" + std::to_string(odd.height)));
    EXPECT_EQ(cam.state(), Camera::State::kOpened);
    EXPECT_EQ(cam.RequestStill({1, "c", 1, 1}, [](Result<FramePtr>) {}).error().cls,
              ErrorClass::kInvalidState)
        << "no still with settings the camera no longer has";
    Status again = cam.Configure(Ordinary());
    ASSERT_TRUE(again.ok()) << again.error().ToString();
    EXPECT_TRUE(ExpectStill(cam, 2, setup_.width, setup_.height));
  }
  cam.Close();
}

// A closed camera opens again and shoots (the daemon's recovery path).
TEST_P(CameraContract, ReopensAfterClose) {
  Camera& cam = Make();
  for (int round = 0; round < 2; ++round) {
    Status open = cam.Open();
    ASSERT_TRUE(open.ok()) << "round " << round << ": " << open.error().ToString();
    ASSERT_TRUE(cam.Configure(Ordinary()));
    EXPECT_TRUE(ExpectStill(cam, round, setup_.width, setup_.height)) << "round " << round;
    cam.Close();
  }
}

// The largest still the device gives (the sim: the rig's 12 MP mode, 4032 x 3024).
TEST_P(CameraContract, FullResolutionStill) {
  ASSERT_GT(setup_.full_width, setup_.width);
  ASSERT_GT(setup_.full_height, 0);
  Camera& cam = Make([&](CameraConfig& c) {
    c.width = setup_.full_width;
    c.height = setup_.full_height;
  });
  ASSERT_TRUE(cam.Open());
  Status cs = cam.Configure(Settings(setup_.full_width, setup_.full_height));
  ASSERT_TRUE(cs.ok()) << cs.error().ToString();
  EXPECT_TRUE(ExpectStill(cam, 0, setup_.full_width, setup_.full_height));
  cam.Close();
}

INSTANTIATE_TEST_SUITE_P(Backends, CameraContract, ::testing::ValuesIn(kBackends),
                         [](const ::testing::TestParamInfo<BackendParam>& i) {
                           return std::string(i.param.name);
                         });

// The base class's part of the rule above, on every machine: a backend that
// refuses a Configure (after stopping its stream, as V4L2 and libcamera do)
// leaves the camera Opened; settings refused before the device is asked
// leave it as it was.
class RefusingCamera final : public Camera {
 public:
  bool refuse = false;
  CameraInfo Info() const override { return {"refusing", "test", "refuses when told"}; }

 protected:
  Status DoOpen() override { return OkStatus(); }
  Status DoConfigure(const CameraSettings& s) override {
    if (refuse)
      return MakeError(ErrorClass::kInvalidConfig, "cannot deliver " + std::to_string(s.width));
    return OkStatus();
  }
  Status DoRequestStill(const StillRequest&, FrameCallback done) override {
    done(MakeError(ErrorClass::kDeviceFault, "no pictures here"));
    return OkStatus();
  }
  void DoClose() override {}
};

TEST(CameraBase, ARefusedConfigureLeavesAReadyCameraOpened) {
  RefusingCamera cam;
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(640, 480)));
  ASSERT_EQ(cam.state(), Camera::State::kReady);
  EXPECT_EQ(cam.Configure(Settings(8, 480)).error().cls, ErrorClass::kInvalidArgument);
  EXPECT_EQ(cam.state(), Camera::State::kReady) << "refused before the device was asked";
  cam.refuse = true;
  EXPECT_EQ(cam.Configure(Settings(641, 480)).error().cls, ErrorClass::kInvalidConfig);
  EXPECT_EQ(cam.state(), Camera::State::kOpened);
  EXPECT_EQ(cam.RequestStill({}, [](Result<FramePtr>) {}).error().cls, ErrorClass::kInvalidState);
  cam.refuse = false;
  ASSERT_TRUE(cam.Configure(Settings(640, 480)));
  EXPECT_EQ(cam.state(), Camera::State::kReady);
  EXPECT_EQ(cam.settings().width, 640);
  cam.Close();
}

}  // namespace
}  // namespace aggscan
