// Sim camera backend: renders the sim world as the rig camera would see it.
//
// A real backend, not a mock: stills are rendered on the driver's own worker
// thread (a request queue served in order), JPEG-encoded, and delivered
// through the callback on that thread, like a V4L2 or libcamera driver. The
// platter angle at the moment of exposure comes from `platter_angle_at`
// (supplied by the factory from the sim turntable); the request's side picks
// the rock's rest pose. Frames are deterministic: the sensor noise seed is
// derived from sim.seed, side and view.
#pragma once

#include <array>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "config/config.h"
#include "drivers/camera.h"
#include "drivers/sim/world.h"

namespace aggscan::sim {

class Renderer;

/// Ground truth of one rendered view, for tests and sim.write_truth.
struct TruthView {
  int side = 1;
  int view = 0;
  double platter_deg = 0.0;  // platter angle the frame was rendered at
  int width = 0;
  int height = 0;
  std::vector<uint8_t> mask;  // width*height, 255 = rock (object markers included)
  Rigid rock_to_camera;       // rock frame -> camera frame
  std::array<double, 16> rock_to_camera_4x4{};  // same, row-major homogeneous
  Intrinsics intrinsics;                        // of this frame's resolution
};
/// Called on the driver thread after each frame is rendered, before the frame
/// callback. Must be quick and must not call back into the camera.
using TruthSink = std::function<void(const StillRequest&, const TruthView&)>;

class SimCamera final : public Camera {
 public:
  using AngleFn = std::function<double(TimeNs)>;
  /// `platter_angle_at(t)`: platter angle (deg) at clock time t; default: always 0.
  /// `board_world`: what a request with `board` set shows (the charuco
  /// scene); null: such a request fails, naming sim.board_image.
  SimCamera(std::shared_ptr<const SimWorld> world, Clock& clock, const CameraConfig& config,
            AngleFn platter_angle_at = {}, std::shared_ptr<const SimWorld> board_world = {});
  ~SimCamera() override;

  CameraInfo Info() const override;
  /// Installs (or clears, with an empty function) the ground-truth sink. With
  /// a sink the renderer also produces the rock mask.
  void SetTruthSink(TruthSink sink);
  /// A camera walked round a still rock (capture.mode = "moving_camera"):
  /// where it stands (world -> camera) at clock time t, read mid-exposure.
  /// Empty (the default): the rig's fixed camera.
  using PoseFn = std::function<Rigid(TimeNs)>;
  void SetCameraPath(PoseFn pose_at);
  /// Frames rendered since construction.
  uint64_t frames_rendered() const;

 protected:
  Status DoOpen() override;
  Status DoConfigure(const CameraSettings& settings) override;
  Status DoRequestStill(const StillRequest& req, FrameCallback done) override;
  void DoClose() override;

 private:
  struct Job {
    StillRequest req;
    FrameCallback done;
    bool warmup = false;  // prepare the renderer for the active settings, no frame
  };
  void WorkerLoop();
  void Serve(Job& job);

  std::shared_ptr<const SimWorld> world_;
  std::shared_ptr<const SimWorld> board_world_;
  Clock& clock_;
  CameraConfig config_;
  AngleFn angle_at_;

  mutable std::mutex mu_;  // guards everything below
  std::condition_variable cv_;
  std::deque<Job> queue_;
  bool stop_ = false;
  CameraSettings active_;  // settings from the last Configure()
  TruthSink truth_sink_;
  PoseFn pose_at_;
  uint64_t sequence_ = 0;
  std::thread worker_;

  std::unique_ptr<Renderer> renderer_;        // worker thread only
  std::unique_ptr<Renderer> board_renderer_;  // of board_world_, worker thread only
};

}  // namespace aggscan::sim
