// Sim camera backend: driver thread, state machine, frame metadata, truth.
#include <gtest/gtest.h>

#include <condition_variable>
#include <mutex>
#include <optional>
#include <thread>

#include "drivers/sim/jpeg.h"
#include "drivers/sim/sim_camera.h"

namespace aggscan::sim {
namespace {

std::shared_ptr<SimWorld> TestWorld() {
  static std::shared_ptr<SimWorld> w = [] {
    Config c;
    c.sim.seed = 2;
    c.sim.rock_size_mm = 100.0;
    c.camera.width = 320;
    c.camera.height = 240;
    return std::make_shared<SimWorld>(c, SimWorldOptions{.rock_faces = 4000});
  }();
  return w;
}

CameraSettings SmallSettings() {
  CameraSettings s;
  s.width = 320;
  s.height = 240;
  s.exposure_us = 6000;
  s.gain = 1.5;
  s.wb_red = 1.1;
  s.wb_blue = 0.9;
  return s;
}

// Collects one callback result.
struct Waiter {
  std::mutex mu;
  std::condition_variable cv;
  std::optional<Result<FramePtr>> result;
  std::thread::id thread;
  FrameCallback Callback() {
    return [this](Result<FramePtr> r) {
      std::lock_guard<std::mutex> l(mu);
      result.emplace(std::move(r));
      thread = std::this_thread::get_id();
      cv.notify_all();
    };
  }
  Result<FramePtr> Wait() {
    std::unique_lock<std::mutex> l(mu);
    EXPECT_TRUE(cv.wait_for(l, std::chrono::seconds(60), [this] { return result.has_value(); }));
    if (!result) return MakeError(ErrorClass::kTimeout, "no frame");
    Result<FramePtr> r = std::move(*result);
    result.reset();
    return r;
  }
};

TEST(SimCamera, StateMachineErrors) {
  VirtualClock clock;
  SimCamera cam(TestWorld(), clock, CameraConfig{});
  Waiter w;
  Status s = cam.RequestStill({}, w.Callback());
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidState);
  ASSERT_TRUE(cam.Configure(SmallSettings()).error().cls == ErrorClass::kInvalidState);
  ASSERT_TRUE(cam.Open().ok());
  EXPECT_EQ(cam.Open().error().cls, ErrorClass::kInvalidState);
  s = cam.RequestStill({}, w.Callback());  // opened but not configured
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidState);
  cam.Close();
  EXPECT_EQ(cam.state(), Camera::State::kClosed);
}

TEST(SimCamera, DeliversFramesOnItsOwnThread) {
  VirtualClock clock(5 * kNsPerSec);
  double angle = 0;
  SimCamera cam(TestWorld(), clock, CameraConfig{}, [&](TimeNs) { return angle; });
  EXPECT_EQ(cam.Info().backend, "sim");
  std::vector<TruthView> truths;
  cam.SetTruthSink([&](const StillRequest&, const TruthView& t) { truths.push_back(t); });
  ASSERT_TRUE(cam.Open().ok());
  ASSERT_TRUE(cam.Configure(SmallSettings()).ok());
  Waiter w;
  std::vector<FramePtr> frames;
  for (int view = 0; view < 3; ++view) {
    angle = view * 30.0;
    StillRequest req;
    req.request_id = 100 + view;
    req.side = 1;
    req.view = view;
    ASSERT_TRUE(cam.RequestStill(req, w.Callback()).ok());
    Result<FramePtr> r = w.Wait();
    ASSERT_TRUE(r.ok()) << r.error().ToString();
    EXPECT_NE(w.thread, std::this_thread::get_id());
    frames.push_back(*r);
    EXPECT_EQ(cam.state(), Camera::State::kReady);
  }
  for (int i = 0; i < 3; ++i) {
    const Frame& f = *frames[i];
    EXPECT_EQ(f.request_id, 100u + i);
    EXPECT_EQ(f.sequence, static_cast<uint64_t>(i));
    EXPECT_EQ(f.width, 320);
    EXPECT_EQ(f.height, 240);
    EXPECT_EQ(f.encoding, "jpeg");
    EXPECT_EQ(f.exposure_start, 5 * kNsPerSec);
    EXPECT_EQ(f.utc_ns, clock.UtcNs());
    EXPECT_DOUBLE_EQ(f.exposure_us, 6000);
    EXPECT_DOUBLE_EQ(f.gain, 1.5);
    EXPECT_DOUBLE_EQ(f.wb_red, 1.1);
    EXPECT_DOUBLE_EQ(f.wb_blue, 0.9);
    Result<RgbImage> img = DecodeJpeg(f.data);
    ASSERT_TRUE(img.ok());
    EXPECT_EQ(img->width, 320);
  }
  ASSERT_EQ(truths.size(), 3u);
  for (int i = 0; i < 3; ++i) {
    EXPECT_EQ(truths[i].view, i);
    EXPECT_DOUBLE_EQ(truths[i].platter_deg, i * 30.0);
    ASSERT_EQ(truths[i].mask.size(), 320u * 240);
    long area = 0;
    for (uint8_t m : truths[i].mask) area += m ? 1 : 0;
    EXPECT_GT(area, 500);
    const Rigid expected = TestWorld()->RockToCamera(1, i * 30.0);
    EXPECT_DOUBLE_EQ(truths[i].rock_to_camera_4x4[3], expected.t.x);
    EXPECT_EQ(truths[i].intrinsics.width, 320);
  }
  cam.Close();
  EXPECT_EQ(cam.frames_rendered(), 3u);
}

TEST(SimCamera, SameSeedSameFrames) {
  VirtualClock clock;
  auto shoot = [&](int side, int view) {
    SimCamera cam(TestWorld(), clock, CameraConfig{});
    EXPECT_TRUE(cam.Open().ok());
    EXPECT_TRUE(cam.Configure(SmallSettings()).ok());
    Waiter w;
    StillRequest req;
    req.side = side;
    req.view = view;
    EXPECT_TRUE(cam.RequestStill(req, w.Callback()).ok());
    Result<FramePtr> r = w.Wait();
    EXPECT_TRUE(r.ok());
    return r.ok() ? (*r)->data : std::vector<unsigned char>{};
  };
  EXPECT_EQ(shoot(1, 4), shoot(1, 4));
  EXPECT_NE(shoot(1, 4), shoot(2, 4));  // other side: flipped rock
}

TEST(SimCamera, CloseWaitsForInFlightStill) {
  VirtualClock clock;
  SimCamera cam(TestWorld(), clock, CameraConfig{});
  ASSERT_TRUE(cam.Open().ok());
  ASSERT_TRUE(cam.Configure(SmallSettings()).ok());
  Waiter w;
  ASSERT_TRUE(cam.RequestStill({}, w.Callback()).ok());
  cam.Close();  // joins the worker, which finishes the still first
  Result<FramePtr> r = w.Wait();
  EXPECT_TRUE(r.ok());
  // Reopen works.
  ASSERT_TRUE(cam.Open().ok());
  ASSERT_TRUE(cam.Configure(SmallSettings()).ok());
  ASSERT_TRUE(cam.RequestStill({}, w.Callback()).ok());
  EXPECT_TRUE(w.Wait().ok());
}

}  // namespace
}  // namespace aggscan::sim
