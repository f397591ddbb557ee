// Device-free pieces of the libcamera camera backend, kept apart so they are
// tested on any machine: stream-role and pixel-format choice (and the V4L2
// layout each libcamera format is encoded from), the mapping of the locked
// settings onto libcamera controls, reading them back from a completed
// request's metadata, picking the configured camera from libcamera's list,
// and the classification of libcamera's negative errno returns.
#pragma once

#include <libcamera/controls.h>
#include <libcamera/pixel_format.h>
#include <libcamera/stream.h>

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "common/error.h"
#include "drivers/camera.h"

namespace aggscan::lc {

/// Config role name ("still", "raw", "video", "viewfinder") -> libcamera role.
std::optional<libcamera::StreamRole> RoleFromName(const std::string& name);

/// Config name ("bgr888", "nv12", ...) -> libcamera format; nullopt for
/// "auto" or an unknown name. Names are libcamera's (DRM's), lower case.
std::optional<libcamera::PixelFormat> FormatFromName(const std::string& name);
/// The V4L2 fourcc with the same memory layout (what v4l2::EncodeStill
/// converts), 0 for a format this backend cannot turn into a JPEG still.
/// libcamera's BGR888 is V4L2's RGB24 (R, G, B in memory) and RGB888 is BGR24.
uint32_t V4l2FourCcFor(const libcamera::PixelFormat& f);

/// Picks the stream's pixel format among those the pipeline offers for the
/// role. `wanted` "auto": the pipeline's own default when it can be encoded,
/// else the first offered in the order MJPEG, YUYV, UYVY, NV12, BGR888,
/// RGB888, R8. A named format must be offered; else an error (kInvalidConfig)
/// lists what is.
Result<libcamera::PixelFormat> ChoosePixelFormat(const std::vector<libcamera::PixelFormat>& offered,
                                                 const libcamera::PixelFormat& pipeline_default,
                                                 const std::string& wanted);

/// The controls every request carries, and the locked settings the camera
/// has no control for ("exposure", "gain", "wb_red", "wb_blue").
struct ControlPlan {
  libcamera::ControlList controls;
  std::vector<std::string> missing;
};
/// Maps settings onto the camera's controls (`info` = Camera::controls()):
/// manual exposure switches AeEnable/AwbEnable off and sets ExposureTime (us),
/// AnalogueGain and ColourGains where the camera has them; automatic exposure
/// switches AeEnable/AwbEnable on. A value outside a control's range is a
/// kInvalidConfig naming the range.
Result<ControlPlan> PlanControls(const libcamera::ControlInfoMap& info, const CameraSettings& s);

/// Settings in effect for one frame, from its request's metadata.
struct ReadBack {
  double exposure_us = 0, gain = 0, wb_red = 1, wb_blue = 1;
  bool has_exposure = false, has_gain = false, has_wb = false;  // reported in the metadata
};
ReadBack ReadMetadata(const libcamera::ControlList& metadata);

/// For manual exposure: empty when every locked value the metadata reports
/// matches the setting (within 2 %: sensors quantise exposure to whole lines
/// and gain to their register steps), else what differs, e.g. "exposure 3000
/// us (set 6000 us)". Values the metadata does not report cannot be checked.
std::string UnsettledReason(const ReadBack& rb, const CameraSettings& s,
                            const std::vector<std::string>& missing);

/// Picks the configured camera among libcamera's (ids in its order): the one
/// with id `wanted_id`, or the one at `index` when wanted_id is empty. None ->
/// kDeviceMissing listing the cameras found.
Result<std::string> PickCamera(const std::vector<std::string>& ids, const std::string& wanted_id,
                               int index);

/// Error from a failed libcamera call (a negative errno). `was_running`:
/// the camera had been working, so a vanished device is "disconnected".
Error LibcameraError(const std::string& camera, const std::string& what, int neg_errno,
                     bool was_running);

}  // namespace aggscan::lc
