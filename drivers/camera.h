// Camera interface: still capture with locked exposure.
//
// Designed for V4L2 and libcamera stills as well as the sim: the camera is
// opened, configured once per capture (resolution, manual exposure, gain and
// white balance locked so every view of a rock shares them), then asked for
// one still at a time. The still is delivered on the driver's own thread
// through the callback; the callback must only post an event to the owner's
// loop, never touch state. Frame timeouts are enforced by the caller (the
// daemon's loop owns all deadlines).
//
// States:   Closed --Open()--> Opened --Configure()--> Ready
//           Ready --RequestStill()--> Busy --(callback)--> Ready
//           any --Close()--> Closed
// Calls in the wrong state return kInvalidState and do nothing. A Configure
// the device refuses leaves the camera Opened, whatever it was before.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "common/clock.h"
#include "common/error.h"

namespace aggscan {

struct CameraSettings {
  int width = 2016;
  int height = 1512;
  int jpeg_quality = 92;
  bool manual_exposure = true;
  double exposure_us = 8000.0;
  double gain = 1.0;
  double wb_red = 1.0;
  double wb_blue = 1.0;
};

/// What the caller knows about the shot; recorded in metadata. Real cameras
/// ignore it; the sim uses `side` to show the rock in that side's pose (its
/// simulated operator always flips the rock between sides).
struct StillRequest {
  uint64_t request_id = 0;
  std::string sample_id;
  int side = 1;  // 1-based
  int view = 0;  // 0-based
  /// A calibration capture: the printed board lies on the disc, not a rock
  /// (the sim camera then draws its board world).
  bool board = false;
};

/// An encoded still. Travels as shared_ptr<const Frame>.
struct Frame {
  uint64_t request_id = 0;
  uint64_t sequence = 0;  // driver frame counter
  int width = 0;
  int height = 0;
  std::string encoding = "jpeg";  // the bytes' format
  std::vector<unsigned char> data;
  TimeNs exposure_start = 0;  // on the daemon's clock
  int64_t utc_ns = 0;
  // Settings actually in effect for this frame (as read back from the device).
  double exposure_us = 0.0;
  double gain = 0.0;
  double wb_red = 1.0;
  double wb_blue = 1.0;
  // Locked settings the device has no control for (e.g. "exposure" on a
  // camera without V4L2_CID_EXPOSURE_ABSOLUTE): their values above are not
  // the device's and read 0 (exposure, gain) or 1 (white balance), never the
  // value asked for. Empty when every setting was applied and read back.
  std::vector<std::string> missing_controls;
};
using FramePtr = std::shared_ptr<const Frame>;
using FrameCallback = std::function<void(Result<FramePtr>)>;

struct CameraInfo {
  std::string id;       // stable id recorded in sidecars
  std::string backend;  // "sim", "v4l2", ...
  std::string model;    // human-readable
};

class Camera {
 public:
  enum class State { kClosed, kOpened, kReady, kBusy };
  virtual ~Camera() = default;
  Camera(const Camera&) = delete;
  Camera& operator=(const Camera&) = delete;

  /// Finds and opens the device.
  Status Open();
  /// Applies settings; verifies exposure lock where the device can report it.
  /// Settings out of range are refused before the device is touched; a
  /// refusal by the device leaves the camera Opened (configure it again).
  Status Configure(const CameraSettings& settings);
  /// Starts one still; `done` is called exactly once, on the driver's thread.
  Status RequestStill(const StillRequest& req, FrameCallback done);
  /// Stops and releases the device; waits for an in-flight still to finish.
  void Close();

  State state() const;
  const CameraSettings& settings() const { return settings_; }
  virtual CameraInfo Info() const = 0;

 protected:
  Camera() = default;
  virtual Status DoOpen() = 0;
  virtual Status DoConfigure(const CameraSettings& settings) = 0;
  /// Must eventually call `done` (from any thread but the caller's stack is fine
  /// too); the base wraps it to return the state to Ready.
  virtual Status DoRequestStill(const StillRequest& req, FrameCallback done) = 0;
  virtual void DoClose() = 0;

 private:
  mutable std::mutex mu_;
  State state_ = State::kClosed;
  CameraSettings settings_;
};

const char* CameraStateName(Camera::State s);

}  // namespace aggscan
