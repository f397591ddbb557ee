// V4L2 camera backend: a UVC webcam, an industrial USB camera or any capture
// node the kernel exposes as /dev/videoN, driven with plain V4L2 ioctls.
//
// Open() resolves camera.device (a path, a /dev/v4l/by-id or by-path symlink,
// or a bare udev name looked up there) and checks the node captures video and
// streams. Configure() picks the pixel format (MJPEG passed through as the
// JPEG still when offered, else a raw format converted and encoded), sets the
// resolution (a device that cannot give exactly the configured size is
// refused), locks exposure, gain, white balance and focus through controls and
// reads each back, then maps the buffers and starts streaming. A still is the
// first frame that starts after the request; stale frames queued before it
// are dropped. Frames are delivered on the backend's own thread.
//
// Errors: node absent -> kDeviceMissing; ENODEV/EPIPE once opened (unplug,
// vivid's "Disconnect") -> kDisconnected; no frame within
// camera.v4l2.frame_timeout -> kTimeout. After a disconnect the camera must be
// closed and opened again (that is the recovery path).
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "config/config.h"
#include "drivers/camera.h"
#include "drivers/still_worker.h"
#include "drivers/v4l2/v4l2_util.h"

namespace aggscan::v4l2 {

/// An owned file descriptor (closed on destruction).
class UniqueFd {
 public:
  UniqueFd() = default;
  explicit UniqueFd(int fd) : fd_(fd) {}
  ~UniqueFd() { Reset(); }
  UniqueFd(UniqueFd&& o) noexcept : fd_(o.Release()) {}
  UniqueFd& operator=(UniqueFd&& o) noexcept;
  int get() const { return fd_; }
  bool valid() const { return fd_ >= 0; }
  int Release();
  void Reset();

 private:
  int fd_ = -1;
};

/// One driver buffer mapped into our address space (unmapped on destruction).
class MappedBuffer {
 public:
  MappedBuffer(void* addr, size_t length) : addr_(addr), length_(length) {}
  ~MappedBuffer();
  MappedBuffer(MappedBuffer&& o) noexcept : addr_(o.addr_), length_(o.length_) {
    o.addr_ = nullptr;
  }
  MappedBuffer& operator=(MappedBuffer&&) = delete;
  const uint8_t* data() const { return static_cast<const uint8_t*>(addr_); }
  size_t length() const { return length_; }

 private:
  void* addr_;
  size_t length_;
};

/// What Configure negotiated and read back.
struct V4l2Negotiated {
  uint32_t fourcc = 0;
  int width = 0;
  int height = 0;
  int bytes_per_line = 0;
  uint32_t size_image = 0;
  std::vector<uint32_t> offered;              // formats the device listed
  std::vector<std::string> missing_controls;  // locked settings without a control
};

class V4l2Camera final : public Camera {
 public:
  V4l2Camera(Clock& clock, const CameraConfig& config);
  ~V4l2Camera() override;

  CameraInfo Info() const override;
  /// The device node Open() resolved camera.device to ("" before).
  std::string device_path() const;
  /// Result of the last successful Configure().
  V4l2Negotiated negotiated() const;
  /// Frames skipped because the driver flagged them corrupt (V4L2_BUF_FLAG_ERROR).
  uint64_t corrupt_frames() const { return corrupt_frames_.load(); }
  /// Frames skipped because their exposure began before the still request.
  uint64_t stale_frames() const { return stale_frames_.load(); }

 protected:
  Status DoOpen() override;
  Status DoConfigure(const CameraSettings& settings) override;
  Status DoRequestStill(const StillRequest& req, FrameCallback done) override;
  void DoClose() override;

 private:
  using Job = StillWorker::Job;
  struct ReadBack {  // device values after the last still
    double exposure_us = 0, gain = 0, wb_red = 1, wb_blue = 1;
  };

  Status ApplyControls(const CameraSettings& s, std::vector<std::string>* missing);
  Status SetAndVerify(uint32_t id, const char* what, int64_t value);
  std::optional<ControlRange> Query(uint32_t id) const;
  Result<int64_t> Get(uint32_t id) const;
  ReadBack ReadControls() const;
  Status StartStreaming();
  void StopStreaming();
  Result<FramePtr> Capture(const Job& job);
  Result<FramePtr> MakeFrame(const Job& job, const uint8_t* data, size_t bytes, int64_t ts_mono_ns,
                             uint64_t sequence);
  Error Fail(const std::string& what, int err) const;

  Clock& clock_;
  CameraConfig config_;

  // Device state: touched by Open/Configure/Close (the owner's thread, with the
  // worker idle) and by the worker while it serves a job.
  std::string path_;
  std::string model_;
  UniqueFd fd_;
  std::vector<MappedBuffer> buffers_;
  bool streaming_ = false;
  V4l2Negotiated neg_;
  CameraSettings active_;
  std::optional<ControlRange> gain_range_, red_range_, blue_range_;
  uint32_t gain_id_ = 0;
  int64_t frame_period_ns_ = 0;  // from VIDIOC_G_PARM; 0 when the driver does not say

  std::atomic<uint64_t> corrupt_frames_{0};
  std::atomic<uint64_t> stale_frames_{0};

  mutable std::mutex mu_;  // guards the worker's job slot and stop flag
  std::condition_variable cv_;
  StillWorker worker_{mu_, cv_};  // last: stopped before the rest goes
};

}  // namespace aggscan::v4l2
