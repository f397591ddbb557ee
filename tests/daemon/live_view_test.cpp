// The live view on the real capture loop and the sim rig: stills are shot
// only while a screen watches and no side runs, a view whose trigger comes
// while a live-view still is in flight is shot as soon as that still is in
// (never refused as "camera busy"), and the views of a side reach the screen.
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "config/config.h"
#include "daemon/capture_service.h"
#include "daemon/event_loop.h"
#include "daemon/preview_hub.h"
#include "drivers/factory.h"
#include "store/sample_store.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using nlohmann::json;
using Steady = std::chrono::steady_clock;

// The sim camera, with every still answered `delay_ms` later (a camera that
// is slow to read out at full size).
class SlowCamera final : public Camera {
 public:
  explicit SlowCamera(std::unique_ptr<Camera> inner) : inner_(std::move(inner)) {}
  CameraInfo Info() const override { return inner_->Info(); }
  std::atomic<int> delay_ms{0};
  std::atomic<int> requests{0};
  // (side, view) of each still asked for, in order; a live-view still asks
  // for view 0 of the current side.
  std::vector<std::pair<int, int>> Asked() const {
    std::lock_guard lock(mu_);
    return asked_;
  }

 protected:
  Status DoOpen() override { return inner_->Open(); }
  Status DoConfigure(const CameraSettings& s) override { return inner_->Configure(s); }
  Status DoRequestStill(const StillRequest& req, FrameCallback done) override {
    {
      std::lock_guard lock(mu_);
      asked_.emplace_back(req.side, req.view);
    }
    ++requests;
    const int delay = delay_ms.load();
    return inner_->RequestStill(req, [delay, done = std::move(done)](Result<FramePtr> r) {
      std::this_thread::sleep_for(std::chrono::milliseconds(delay));
      done(std::move(r));
    });
  }
  void DoClose() override { inner_->Close(); }

 private:
  std::unique_ptr<Camera> inner_;
  mutable std::mutex mu_;
  std::vector<std::pair<int, int>> asked_;
};

template <typename Pred>
bool WaitUntil(Pred pred, int seconds) {
  const auto until = Steady::now() + std::chrono::seconds(seconds);
  while (Steady::now() < until) {
    if (pred()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return pred();
}

TEST(LiveView, StillsOnlyWhileWatchedAndAViewWaitsForTheStillInFlight) {
  test::TempDir dir;
  Config config;
  config.daemon.state_dir = dir.path() + "/state";
  config.daemon.preview_interval = 100 * kNsPerMs;
  config.daemon.health_probe_interval = 0;
  config.camera.width = 640;
  config.camera.height = 480;
  config.capture.profile = "custom";
  config.capture.sides = 2;
  config.capture.views_per_side = 3;
  config.capture.step_deg = 120;
  config.capture.interval = 1 * kNsPerSec;
  config.turntable.home_duration = 10 * kNsPerMs;
  config.turntable.max_speed_deg_s = 720;
  config.turntable.accel_deg_s2 = 7200;
  SampleStore store(config.daemon.state_dir);
  ASSERT_TRUE(store.Init().ok());
  RealClock clock;
  EventLoop loop(clock);
  Result<RigDevices> rig = CreateRig(config, clock);
  ASSERT_TRUE(rig) << rig.error().ToString();
  auto slow = std::make_unique<SlowCamera>(std::move(rig->camera));
  SlowCamera* camera = slow.get();
  rig->camera = std::move(slow);
  PreviewHub hub(320, 70);
  CaptureService service(loop, config, "", std::move(*rig), store, nullptr);
  service.SetPreviewHub(&hub);
  loop.Post([&] { service.Start(); });
  std::thread thread([&] { loop.Run(); });
  auto metric = [&](const std::string& name) {
    const std::string m = service.Metrics();
    const size_t at = m.find("\n" + name + " ");
    return at == std::string::npos ? -1.0 : std::stod(m.substr(at + name.size() + 2));
  };
  const auto ctx = [] { return CallContext::Within(std::chrono::seconds(5)); };

  ASSERT_TRUE(WaitUntil([&] { return service.GetHealth().value("status", "") == "ok"; }, 20));
  // Nobody watches: no still is shot.
  std::this_thread::sleep_for(std::chrono::milliseconds(400));
  EXPECT_EQ(camera->requests.load(), 0);
  EXPECT_EQ(hub.frames_published(), 0u);

  // A screen watches: frames come, scaled to the hub's size.
  hub.AddViewer();
  ASSERT_TRUE(WaitUntil([&] { return hub.frames_published() >= 3; }, 10));
  EXPECT_EQ(hub.Latest().source, "preview");
  EXPECT_EQ(hub.Latest().width, 320);
  EXPECT_EQ(metric("aggscan_preview_viewers"), 1.0);

  // The next live-view still takes 1.5 s; the side's first trigger (homing
  // 10 ms, settle 300 ms) comes while it is in flight.
  ASSERT_TRUE(service.Arm("rock-1", ctx()).ok());
  camera->delay_ms = 1500;
  const int before = camera->requests.load();
  ASSERT_TRUE(WaitUntil([&] { return camera->requests.load() > before; }, 5));
  camera->delay_ms = 0;
  Result<json> pressed = service.Press("test", ctx());
  ASSERT_TRUE(pressed) << pressed.error().ToString();
  ASSERT_TRUE(
      WaitUntil([&] { return service.GetStatus().value("state", "") == "awaiting_pose"; }, 30))
      << service.GetStatus().dump();
  EXPECT_EQ(metric("aggscan_preview_delayed_views_total"), 1.0);
  EXPECT_EQ(metric("aggscan_views_captured_total"), 3.0);
  EXPECT_EQ(service.GetStatus()["fault"], nullptr);
  // No live-view still was shot during the side: after the one in flight at
  // the trigger come the side's three views, back to back. (Once the side is
  // done the live view resumes, so later requests are not counted.)
  const std::vector<std::pair<int, int>> asked = camera->Asked();
  ASSERT_GE(asked.size(), static_cast<size_t>(before + 1 + 3));
  for (int v = 0; v < 3; ++v)
    EXPECT_EQ(asked[before + 1 + v], std::make_pair(1, v)) << "request " << before + 1 + v;

  // Between sides the live view goes on; with nobody watching it stops.
  const uint64_t published = hub.frames_published();
  ASSERT_TRUE(WaitUntil([&] { return hub.frames_published() >= published + 2; }, 10));
  hub.RemoveViewer();
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  const int quiet = camera->requests.load();
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  EXPECT_EQ(camera->requests.load(), quiet);

  loop.Post([&] { service.Shutdown(); });
  loop.Quit(0);
  thread.join();
}

}  // namespace
}  // namespace aggscan
