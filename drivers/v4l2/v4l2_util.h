// Device-free pieces of the V4L2 camera backend, kept apart so they are tested
// on any machine: pixel-format choice, raw-to-RGB conversion, the mapping of
// locked settings onto V4L2 controls, device-name resolution and the
// classification of errno values into the operator's error classes.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "common/error.h"
#include "drivers/camera.h"

namespace aggscan::v4l2 {

/// FourCC code as V4L2 builds it (v4l2_fourcc).
constexpr uint32_t FourCc(char a, char b, char c, char d) {
  return static_cast<uint32_t>(a) | (static_cast<uint32_t>(b) << 8) |
         (static_cast<uint32_t>(c) << 16) | (static_cast<uint32_t>(d) << 24);
}
/// "YUYV", "MJPG", ... (non-printable bytes as '?').
std::string FourCcName(uint32_t fourcc);

/// Config name ("mjpeg", "yuyv", ...) -> fourcc; nullopt for "auto" or unknown.
std::optional<uint32_t> FormatFromName(const std::string& name);
/// True for the formats this backend can turn into a JPEG still.
bool IsSupportedFormat(uint32_t fourcc);

/// Picks the capture format among those the device offers (in its order).
/// `wanted` "auto": MJPEG (JPEG) first, its bytes pass through as the still;
/// else the first supported raw format in the order YUYV, UYVY, NV12, RGB24,
/// BGR24, GREY. A named format must be offered, else the error lists what is.
Result<uint32_t> ChooseFormat(const std::vector<uint32_t>& offered, const std::string& wanted);

/// Converts one raw frame to packed RGB8. `stride` is bytesperline (0 = tight).
/// Fails (kDeviceFault) when the buffer is shorter than the format needs.
Result<std::vector<uint8_t>> ToRgb(uint32_t fourcc, std::span<const uint8_t> data, int width,
                                   int height, int stride);

/// The still for one captured buffer: an MJPEG/JPEG frame is passed through
/// (the Huffman tables many UVC cameras leave out are inserted, so any JPEG
/// reader takes it); a raw frame is converted and encoded at `quality`.
/// A buffer that is not what the format says is a kDeviceFault.
Result<std::vector<unsigned char>> EncodeStill(uint32_t fourcc, std::span<const uint8_t> data,
                                               int width, int height, int stride, int quality);
/// EncodeStill made into the Frame of a still request: its data, the
/// request's id, the driver's sequence, the size, "jpeg"; an encoding error
/// names the camera `who`. Exposure, time and controls are the caller's.
Result<std::shared_ptr<Frame>> EncodeStillFrame(const std::string& who, uint32_t fourcc,
                                                std::span<const uint8_t> data, int width,
                                                int height, int stride, int quality,
                                                uint64_t request_id, uint64_t sequence);
/// Inserts the standard Huffman tables (JPEG spec, Annex K.3) before the
/// first SOS of a JPEG that defines none (motion-JPEG as UVC cameras send
/// it); a JPEG with tables is returned unchanged.
Result<std::vector<unsigned char>> CompleteMjpeg(std::span<const uint8_t> jpeg);

/// Range and default of an integer control, as VIDIOC_QUERYCTRL reports it.
struct ControlRange {
  int64_t minimum = 0;
  int64_t maximum = 0;
  int64_t step = 1;
  int64_t default_value = 0;
};
/// Clamps-free mapping: the device value nearest to `value` on the control's
/// step grid; an error (kInvalidConfig) when it lies outside the range.
Result<int64_t> QuantizeControl(const ControlRange& r, double value, const std::string& what);
/// Exposure in microseconds -> V4L2_CID_EXPOSURE_ABSOLUTE units (100 us).
double ExposureUsToV4l2(double exposure_us);
double V4l2ToExposureUs(int64_t value);
/// Unitless factor (gain, red/blue balance) -> device value: factor x
/// reference, where reference is `unit` if > 0, else the control's default.
/// An error when the reference is 0 (the factor cannot be mapped).
Result<double> UnitlessToDevice(const ControlRange& r, double factor, int unit,
                                const std::string& what);

/// Resolves the configured device to a /dev node: an absolute path (symlinks
/// such as /dev/v4l/by-id/... followed), or a bare udev name looked up in
/// `by_dirs` (default /dev/v4l/by-id and /dev/v4l/by-path). Missing ->
/// kDeviceMissing naming every place looked at.
Result<std::string> ResolveDevice(const std::string& configured,
                                  const std::vector<std::string>& by_dirs = {"/dev/v4l/by-id",
                                                                             "/dev/v4l/by-path"});

/// Error class of a failed system call on the camera. `streaming` tells
/// whether the device had been working (then a vanished device is
/// "disconnected", not "missing").
ErrorClass ClassifyErrno(int err, bool streaming);
/// Error from a failed call with the errno text kept as detail.
Error V4l2Error(const std::string& device, const std::string& what, int err, bool streaming);

}  // namespace aggscan::v4l2
