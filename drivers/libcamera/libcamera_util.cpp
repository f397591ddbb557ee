#include "drivers/libcamera/libcamera_util.h"

#include <libcamera/control_ids.h>
#include <libcamera/formats.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>

#include "drivers/v4l2/v4l2_util.h"

namespace aggscan::lc {
namespace {

namespace formats = libcamera::formats;
namespace controls = libcamera::controls;

struct NamedFormat {
  const char* name;
  libcamera::PixelFormat format;
  uint32_t v4l2;  // same memory layout as a V4L2 format
};
// Config names; also the "auto" preference when the pipeline's default
// cannot be encoded (the camera's own JPEG first, then YUV, then RGB).
const NamedFormat kFormats[] = {
    {"mjpeg", formats::MJPEG, v4l2::FourCc('M', 'J', 'P', 'G')},
    {"yuyv", formats::YUYV, v4l2::FourCc('Y', 'U', 'Y', 'V')},
    {"uyvy", formats::UYVY, v4l2::FourCc('U', 'Y', 'V', 'Y')},
    {"nv12", formats::NV12, v4l2::FourCc('N', 'V', '1', '2')},
    {"bgr888", formats::BGR888, v4l2::FourCc('R', 'G', 'B', '3')},  // V4L2_PIX_FMT_RGB24
    {"rgb888", formats::RGB888, v4l2::FourCc('B', 'G', 'R', '3')},  // V4L2_PIX_FMT_BGR24
    {"r8", formats::R8, v4l2::FourCc('G', 'R', 'E', 'Y')},
};

std::string Number(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%g", v);
  return b;
}

// The control's min..max as doubles; false when the camera does not give both.
template <typename T>
bool Bounds(const libcamera::ControlInfo& ci, double* lo, double* hi) {
  if (ci.min().isNone() || ci.max().isNone()) return false;
  *lo = static_cast<double>(ci.min().get<T>());
  *hi = static_cast<double>(ci.max().get<T>());
  return true;
}

template <typename T>
Status CheckRange(const libcamera::ControlInfo& ci, double v, const char* what, const char* unit) {
  double lo = 0, hi = 0;
  if (Bounds<T>(ci, &lo, &hi) && (v < lo || v > hi)) {
    return MakeError(ErrorClass::kInvalidConfig, std::string(what) + " " + Number(v) + unit +
                                                     " is outside the camera's range " +
                                                     Number(lo) + ".." + Number(hi) + unit +
                                                     "; set camera.exposure to a value inside it");
  }
  return OkStatus();
}

bool Near(double got, double want) { return std::abs(got - want) <= 0.02 * std::abs(want); }

}  // namespace

std::optional<libcamera::StreamRole> RoleFromName(const std::string& name) {
  using libcamera::StreamRole;
  if (name == "still") return StreamRole::StillCapture;
  if (name == "raw") return StreamRole::Raw;
  if (name == "video") return StreamRole::VideoRecording;
  if (name == "viewfinder") return StreamRole::Viewfinder;
  return std::nullopt;
}

std::optional<libcamera::PixelFormat> FormatFromName(const std::string& name) {
  for (const auto& f : kFormats)
    if (name == f.name) return f.format;
  return std::nullopt;
}

uint32_t V4l2FourCcFor(const libcamera::PixelFormat& f) {
  for (const auto& k : kFormats)
    if (k.format == f) return k.v4l2;
  return 0;
}

Result<libcamera::PixelFormat> ChoosePixelFormat(const std::vector<libcamera::PixelFormat>& offered,
                                                 const libcamera::PixelFormat& pipeline_default,
                                                 const std::string& wanted) {
  auto has = [&](const libcamera::PixelFormat& f) {
    return std::find(offered.begin(), offered.end(), f) != offered.end();
  };
  std::string list;
  for (const auto& f : offered) list += (list.empty() ? "" : ", ") + f.toString();
  if (list.empty()) list = "none";
  if (wanted == "auto") {
    if (pipeline_default.isValid() && V4l2FourCcFor(pipeline_default) != 0 &&
        (offered.empty() || has(pipeline_default)))
      return pipeline_default;
    for (const auto& k : kFormats)
      if (has(k.format)) return k.format;
    return MakeError(ErrorClass::kInvalidConfig,
                     "the camera offers no pixel format this backend can encode (it offers " +
                         list +
                         "); use a stream role with a YUV or RGB format "
                         "(camera.libcamera.role)");
  }
  std::optional<libcamera::PixelFormat> f = FormatFromName(wanted);
  if (!f)
    return MakeError(ErrorClass::kInvalidConfig,
                     "camera.libcamera.pixel_format \"" + wanted + "\" is not known");
  if (!has(*f))
    return MakeError(ErrorClass::kInvalidConfig,
                     "the camera does not offer " + f->toString() +
                         " for this stream role; it offers " + list +
                         ": set camera.libcamera.pixel_format to one of them or \"auto\"");
  return *f;
}

Result<ControlPlan> PlanControls(const libcamera::ControlInfoMap& info, const CameraSettings& s) {
  ControlPlan plan{libcamera::ControlList(controls::controls), {}};
  auto find = [&](const libcamera::ControlId& id) -> const libcamera::ControlInfo* {
    auto it = info.find(id.id());
    return it == info.end() ? nullptr : &it->second;
  };
  const libcamera::ControlInfo* ae = find(controls::AeEnable);
  const libcamera::ControlInfo* awb = find(controls::AwbEnable);
  if (!s.manual_exposure) {
    if (ae) plan.controls.set(controls::AeEnable, true);
    if (awb) plan.controls.set(controls::AwbEnable, true);
    return plan;
  }
  // Automatic loops off, so the values below are the ones every view gets.
  if (ae) plan.controls.set(controls::AeEnable, false);
  if (awb) plan.controls.set(controls::AwbEnable, false);
  if (const auto* ci = find(controls::ExposureTime)) {
    if (Status st = CheckRange<int32_t>(*ci, std::round(s.exposure_us), "exposure", " us"); !st)
      return st.error();
    plan.controls.set(controls::ExposureTime, static_cast<int32_t>(std::lround(s.exposure_us)));
  } else {
    plan.missing.push_back("exposure");
  }
  if (const auto* ci = find(controls::AnalogueGain)) {
    if (Status st = CheckRange<float>(*ci, s.gain, "gain", ""); !st) return st.error();
    plan.controls.set(controls::AnalogueGain, static_cast<float>(s.gain));
  } else {
    plan.missing.push_back("gain");
  }
  if (const auto* ci = find(controls::ColourGains)) {
    (void)ci;  // an array control: libcamera gives no per-element range
    const float gains[2] = {static_cast<float>(s.wb_red), static_cast<float>(s.wb_blue)};
    plan.controls.set(controls::ColourGains, libcamera::Span<const float, 2>(gains));
  } else {
    plan.missing.push_back("wb_red");
    plan.missing.push_back("wb_blue");
  }
  return plan;
}

ReadBack ReadMetadata(const libcamera::ControlList& md) {
  ReadBack rb;
  if (auto e = md.get(controls::ExposureTime)) {
    rb.exposure_us = *e;
    rb.has_exposure = true;
  }
  if (auto g = md.get(controls::AnalogueGain)) {
    rb.gain = *g;
    rb.has_gain = true;
  }
  if (auto wb = md.get(controls::ColourGains)) {
    rb.wb_red = (*wb)[0];
    rb.wb_blue = (*wb)[1];
    rb.has_wb = true;
  }
  return rb;
}

std::string UnsettledReason(const ReadBack& rb, const CameraSettings& s,
                            const std::vector<std::string>& missing) {
  if (!s.manual_exposure) return {};
  auto locked = [&](const char* name) {
    return std::find(missing.begin(), missing.end(), name) == missing.end();
  };
  std::string why;
  auto add = [&](const std::string& w) { why += (why.empty() ? "" : ", ") + w; };
  if (locked("exposure") && rb.has_exposure && !Near(rb.exposure_us, s.exposure_us))
    add("exposure " + Number(rb.exposure_us) + " us (set " + Number(s.exposure_us) + " us)");
  if (locked("gain") && rb.has_gain && !Near(rb.gain, s.gain))
    add("gain " + Number(rb.gain) + " (set " + Number(s.gain) + ")");
  if (locked("wb_red") && rb.has_wb && (!Near(rb.wb_red, s.wb_red) || !Near(rb.wb_blue, s.wb_blue)))
    add("colour gains " + Number(rb.wb_red) + "/" + Number(rb.wb_blue) + " (set " +
        Number(s.wb_red) + "/" + Number(s.wb_blue) + ")");
  return why;
}

Result<std::string> PickCamera(const std::vector<std::string>& ids, const std::string& wanted_id,
                               int index) {
  if (!wanted_id.empty()) {
    if (std::find(ids.begin(), ids.end(), wanted_id) != ids.end()) return wanted_id;
  } else if (index >= 0 && static_cast<size_t>(index) < ids.size()) {
    return ids[static_cast<size_t>(index)];
  }
  std::string found;
  for (const auto& id : ids) found += (found.empty() ? "\"" : ", \"") + id + "\"";
  const std::string what = wanted_id.empty()
                               ? "no libcamera camera at index " + std::to_string(index)
                               : "no libcamera camera \"" + wanted_id + "\"";
  return MakeError(ErrorClass::kDeviceMissing,
                   what + "; cameras found: " + (found.empty() ? "none" : found) +
                       " — check the cable, `cam -l`, and camera.libcamera.camera_id / index");
}

Error LibcameraError(const std::string& camera, const std::string& what, int neg_errno,
                     bool was_running) {
  const int err = neg_errno < 0 ? -neg_errno : neg_errno;
  const ErrorClass cls = v4l2::ClassifyErrno(err, was_running);
  std::string hint;
  if (cls == ErrorClass::kDeviceMissing) hint = " — check the cable and `cam -l`";
  if (cls == ErrorClass::kDisconnected)
    hint = " — the camera went away; check the cable, it is reopened on reset";
  if (err == EBUSY) hint = " — another program is using the camera";
  return MakeError(cls, "camera " + camera + ": " + what + " failed" + hint, std::strerror(err));
}

}  // namespace aggscan::lc
