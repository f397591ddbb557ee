// libcamera camera backend: a camera behind one of libcamera's pipeline
// handlers (Raspberry Pi, IPU3, rkisp1, UVC through libcamera, vimc in tests),
// written against Debian 12's libcamera 0.0.3.
//
// Open() starts the process-wide CameraManager (libcamera allows one per
// process; the backends share it), picks camera.libcamera.camera_id or
// .index from its list and acquires the camera. Configure() asks the pipeline
// for one stream of camera.libcamera.role, picks the pixel format, sets the
// resolution (a pipeline that adjusts it is refused, as the V4L2 backend
// does), maps exposure, gain and white balance onto libcamera controls
// (ExposureTime, AnalogueGain, ColourGains with AeEnable/AwbEnable off),
// allocates the buffers with FrameBufferAllocator, mmaps their dmabuf planes
// and starts the camera with those controls. While a still is pending every
// idle Request is queued, each carrying the controls (pipelines need several
// in flight to stream); the still is the first completed frame that is not
// flagged bad, began after the request and whose metadata shows the locked
// values in effect.
//
// Threads: libcamera emits requestCompleted and disconnected on its own
// thread; the handlers only post them (a queue and a flag under a mutex) to
// this backend's worker thread, which converts, encodes and calls `done`.
//
// Errors: camera not listed -> kDeviceMissing naming the cameras found; the
// camera removed while open (unplug, driver unbound: libcamera's disconnected
// signal, or the camera's video node gone once the pipeline cancels a
// request or fails to queue one) -> kDisconnected; no
// completed frame within camera.libcamera.frame_timeout -> kTimeout; frames
// arriving but never with the locked values -> kDeviceFault. After a
// disconnect the camera must be closed and opened again (the recovery path).
#pragma once

#include <libcamera/camera.h>
#include <libcamera/camera_manager.h>
#include <libcamera/framebuffer_allocator.h>
#include <libcamera/pixel_format.h>
#include <libcamera/request.h>
#include <sys/types.h>

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "config/config.h"
#include "drivers/camera.h"
#include "drivers/libcamera/libcamera_util.h"
#include "drivers/still_worker.h"
#include "drivers/v4l2/v4l2_camera.h"

namespace aggscan::lc {

/// What Configure negotiated with the pipeline.
struct LibcameraNegotiated {
  libcamera::PixelFormat format;
  int width = 0;
  int height = 0;
  int stride = 0;
  unsigned buffers = 0;
  std::vector<libcamera::PixelFormat> offered;  // formats the pipeline listed for the role
  std::vector<std::string> controls;            // names of every control the camera has
  std::vector<std::string> missing_controls;    // locked settings without a control
};

class LibcameraCamera final : public Camera {
 public:
  LibcameraCamera(Clock& clock, const CameraConfig& config);
  ~LibcameraCamera() override;

  CameraInfo Info() const override;
  /// libcamera's id of the camera Open() picked ("" before).
  std::string camera_id() const { return id_; }
  /// Result of the last successful Configure().
  LibcameraNegotiated negotiated() const { return neg_; }
  /// Frames re-requested because the pipeline flagged them bad.
  uint64_t corrupt_frames() const { return corrupt_frames_.load(); }
  /// Frames re-requested because their metadata did not yet show the locked values.
  uint64_t unsettled_frames() const { return unsettled_frames_.load(); }
  /// Frames skipped because their exposure began before the still request.
  uint64_t stale_frames() const { return stale_frames_.load(); }

 protected:
  Status DoOpen() override;
  Status DoConfigure(const CameraSettings& settings) override;
  Status DoRequestStill(const StillRequest& req, FrameCallback done) override;
  void DoClose() override;

 private:
  using Job = StillWorker::Job;
  // One allocated buffer, mapped: a pointer per plane into `maps`.
  struct MappedFrame {
    std::vector<v4l2::MappedBuffer> maps;
    std::vector<const uint8_t*> planes;
  };

  // libcamera's thread: post only.
  void OnRequestCompleted(libcamera::Request* request);
  void OnDisconnected();

  Status StartCamera(const ControlPlan& plan);
  void StopCamera();
  Status QueueStill(libcamera::Request* request);
  Result<FramePtr> Capture(const Job& job);
  Result<FramePtr> MakeFrame(const Job& job, libcamera::Request* request, const ReadBack& rb);
  int64_t FrameTimestamp(libcamera::Request* request) const;
  void ReleaseCamera();
  /// True when a device node the camera was found on has vanished since Open.
  bool NodesGone() const;

  Clock& clock_;
  CameraConfig config_;

  // Touched by Open/Configure/Close (the owner's thread, worker idle) and
  // read by the worker while it serves a job.
  std::shared_ptr<libcamera::CameraManager> manager_;
  std::shared_ptr<libcamera::Camera> camera_;
  std::string id_;
  std::string model_;
  // The camera's capture nodes (libcamera maps their device numbers to it):
  // not every pipeline handler signals `disconnected` (0.0.3's vimc handler
  // does not), so a vanished node is how an unplug is told from a fault.
  struct Node {
    std::string path;
    dev_t rdev = 0;
  };
  std::vector<Node> nodes_;
  bool started_ = false;
  bool abandoned_ = false;  // went away while running: left to libcamera, never released
  std::unique_ptr<libcamera::CameraConfiguration> lc_config_;
  std::unique_ptr<libcamera::FrameBufferAllocator> allocator_;
  libcamera::Stream* stream_ = nullptr;
  std::vector<std::unique_ptr<libcamera::Request>> requests_;
  std::map<const libcamera::FrameBuffer*, MappedFrame> mapped_;
  LibcameraNegotiated neg_;
  CameraSettings active_;
  libcamera::ControlList request_controls_;

  std::atomic<uint64_t> corrupt_frames_{0};
  std::atomic<uint64_t> unsettled_frames_{0};
  std::atomic<uint64_t> stale_frames_{0};

  mutable std::mutex mu_;  // guards everything below
  std::condition_variable cv_;
  bool disconnected_ = false;
  std::deque<libcamera::Request*> completed_;  // posted by OnRequestCompleted
  std::vector<libcamera::Request*> idle_;      // not queued to the camera
  int in_flight_ = 0;                          // queued, not yet completed
  StillWorker worker_{mu_, cv_};               // last: stopped before the rest goes
};

/// The process's CameraManager, started on first use and shared while any
/// backend holds it (libcamera allows one per process).
Result<std::shared_ptr<libcamera::CameraManager>> SharedCameraManager();

}  // namespace aggscan::lc
