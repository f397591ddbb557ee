// Camera contract: what the capture service relies on from every camera
// backend. Instantiated for the sim camera (through the factory, as the daemon
// builds it); the V4L2 and libcamera backends join with one more entry in
// kBackends, running against kernel test drivers where the machine has them.
#include <gtest/gtest.h>

#include <condition_variable>
#include <future>
#include <memory>
#include <thread>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/factory.h"
#include "drivers/sim/jpeg.h"

namespace aggscan {
namespace {

struct CameraHarness {
  std::unique_ptr<Clock> clock;
  RigDevices rig;  // keeps the sim world (and turntable) alive
  Camera* camera = nullptr;
};

struct BackendParam {
  const char* name;
  // Returns an empty harness with a skip reason when the backend cannot run here.
  CameraHarness (*make)(const Config& base, std::string* skip_reason);
};

CameraHarness MakeSim(const Config& base, std::string*) {
  CameraHarness h;
  h.clock = std::make_unique<VirtualClock>();
  Config c = base;
  c.camera.backend = c.turntable.backend = c.button.backend = "sim";
  auto rig = CreateRig(c, *h.clock);
  EXPECT_TRUE(rig.ok()) << rig.error().ToString();
  h.rig = std::move(*rig);
  h.camera = h.rig.camera.get();
  return h;
}

const BackendParam kBackends[] = {{"sim", MakeSim}};

CameraSettings Settings(int w, int h) {
  CameraSettings s;
  s.width = w;
  s.height = h;
  s.manual_exposure = true;
  s.exposure_us = 6000;
  s.gain = 1.5;
  return s;
}

// Takes one still and waits for it (bounded).
Result<FramePtr> TakeStill(Camera& cam, int view, std::thread::id* delivered_on = nullptr) {
  auto prom = std::make_shared<std::promise<Result<FramePtr>>>();
  auto fut = prom->get_future();
  StillRequest req{static_cast<uint64_t>(100 + view), "contract", 1, view};
  Status s = cam.RequestStill(req, [prom, delivered_on](Result<FramePtr> r) {
    if (delivered_on) *delivered_on = std::this_thread::get_id();
    prom->set_value(std::move(r));
  });
  if (!s) return s.error();
  if (fut.wait_for(std::chrono::seconds(30)) != std::future_status::ready) {
    return MakeError(ErrorClass::kTimeout, "no still within 30 s");
  }
  return fut.get();
}

class CameraContract : public ::testing::TestWithParam<BackendParam> {
 protected:
  CameraHarness Make(int w = 640, int h = 480) {
    Config c;
    c.camera.width = w;
    c.camera.height = h;
    std::string skip;
    CameraHarness hs = GetParam().make(c, &skip);
    if (!skip.empty()) {
      skipped_ = true;
    }
    return hs;
  }
  bool skipped_ = false;
};

TEST_P(CameraContract, CallsInTheWrongStateAreRejected) {
  CameraHarness h = Make();
  if (skipped_) GTEST_SKIP();
  Camera& cam = *h.camera;
  EXPECT_EQ(cam.state(), Camera::State::kClosed);
  EXPECT_EQ(cam.Configure(Settings(640, 480)).error().cls, ErrorClass::kInvalidState);
  EXPECT_EQ(cam.RequestStill({}, [](Result<FramePtr>) {}).error().cls, ErrorClass::kInvalidState);
  ASSERT_TRUE(cam.Open());
  EXPECT_EQ(cam.Open().error().cls, ErrorClass::kInvalidState);
  EXPECT_EQ(cam.RequestStill({}, [](Result<FramePtr>) {}).error().cls, ErrorClass::kInvalidState)
      << "a still before Configure must be refused";
  cam.Close();
  EXPECT_EQ(cam.state(), Camera::State::kClosed);
}

TEST_P(CameraContract, BadSettingsAreRejectedWithAReason) {
  CameraHarness h = Make();
  if (skipped_) GTEST_SKIP();
  Camera& cam = *h.camera;
  ASSERT_TRUE(cam.Open());
  for (CameraSettings bad : {Settings(8, 480), Settings(640, 20000)}) {
    Status s = cam.Configure(bad);
    ASSERT_FALSE(s.ok());
    EXPECT_EQ(s.error().cls, ErrorClass::kInvalidArgument);
    EXPECT_NE(s.error().message.find("resolution"), std::string::npos);
  }
  CameraSettings q = Settings(640, 480);
  q.jpeg_quality = 0;
  EXPECT_EQ(cam.Configure(q).error().cls, ErrorClass::kInvalidArgument);
  CameraSettings e = Settings(640, 480);
  e.exposure_us = 0;
  EXPECT_EQ(cam.Configure(e).error().cls, ErrorClass::kInvalidArgument);
  cam.Close();
}

TEST_P(CameraContract, StillsArriveOnTheDriverThreadWithLockedExposure) {
  CameraHarness h = Make();
  if (skipped_) GTEST_SKIP();
  Camera& cam = *h.camera;
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(640, 480)));
  EXPECT_EQ(cam.state(), Camera::State::kReady);
  uint64_t last_seq = 0;
  TimeNs last_t = -1;
  for (int v = 0; v < 3; ++v) {
    std::thread::id on;
    Result<FramePtr> f = TakeStill(cam, v, &on);
    ASSERT_TRUE(f.ok()) << f.error().ToString();
    const Frame& fr = **f;
    EXPECT_NE(on, std::this_thread::get_id()) << "frames must be delivered on the driver's own thread";
    EXPECT_EQ(fr.request_id, static_cast<uint64_t>(100 + v));
    EXPECT_EQ(fr.encoding, "jpeg");
    EXPECT_EQ(fr.width, 640);
    EXPECT_EQ(fr.height, 480);
    // Exposure, gain and white balance are the locked values, on every view.
    EXPECT_DOUBLE_EQ(fr.exposure_us, 6000);
    EXPECT_DOUBLE_EQ(fr.gain, 1.5);
    auto img = sim::DecodeJpeg(fr.data);
    ASSERT_TRUE(img.ok()) << img.error().ToString();
    EXPECT_EQ(img->width, 640);
    EXPECT_EQ(img->height, 480);
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

TEST_P(CameraContract, OneStillAtATime) {
  CameraHarness h = Make();
  if (skipped_) GTEST_SKIP();
  Camera& cam = *h.camera;
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(640, 480)));
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
  CameraHarness h = Make();
  if (skipped_) GTEST_SKIP();
  Camera& cam = *h.camera;
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(640, 480)));
  std::atomic<int> calls{0};
  ASSERT_TRUE(cam.RequestStill({1, "c", 1, 0}, [&](Result<FramePtr>) { ++calls; }));
  cam.Close();
  EXPECT_EQ(calls.load(), 1) << "the callback runs exactly once, before Close returns";
}

TEST_P(CameraContract, FullResolutionStill) {
  // The rig's 12 MP mode: 4032 x 3024.
  CameraHarness h = Make(4032, 3024);
  if (skipped_) GTEST_SKIP();
  Camera& cam = *h.camera;
  ASSERT_TRUE(cam.Open());
  ASSERT_TRUE(cam.Configure(Settings(4032, 3024)));
  Result<FramePtr> f = TakeStill(cam, 0);
  ASSERT_TRUE(f.ok()) << f.error().ToString();
  auto img = sim::DecodeJpeg((*f)->data);
  ASSERT_TRUE(img.ok());
  EXPECT_EQ(img->width, 4032);
  EXPECT_EQ(img->height, 3024);
  cam.Close();
}

INSTANTIATE_TEST_SUITE_P(Backends, CameraContract, ::testing::ValuesIn(kBackends),
                         [](const ::testing::TestParamInfo<BackendParam>& i) { return std::string(i.param.name); });

}  // namespace
}  // namespace aggscan
