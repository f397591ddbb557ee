#include "store/sample_files.h"

#include <algorithm>
#include <cstdint>
#include <set>

#include "store/layout.h"

namespace aggscan {
namespace {

using jsonio::Fields;
using jsonio::Put;
using nlohmann::json;

// A file name inside the side directory: nothing that could leave it.
bool IsPlainName(const std::string& n) {
  return !n.empty() && n[0] != '.' && n.find('/') == std::string::npos &&
         n.find('\0') == std::string::npos;
}

// The extra keys, then the record's own fields over them.
json Base(const json& extra) {
  json j = extra.is_object() ? extra : json::object();
  j["schema"] = kSampleFilesSchema;
  return j;
}

}  // namespace

// --- ViewSidecar -----------------------------------------------------------

json ViewSidecar::ToJson() const {
  json j = Base(extra);
  j["view"] = view;
  Put(j, "side", side);
  Put(j, "image", image);
  Put(j, "sample_id", sample_id);
  Put(j, "commanded_angle_deg", commanded_angle_deg);
  Put(j, "measured_angle_deg", measured_angle_deg);
  Put(j, "due_monotonic_ns", due_monotonic_ns);
  Put(j, "trigger_monotonic_ns", trigger_monotonic_ns);
  Put(j, "capture_monotonic_ns", capture_monotonic_ns);
  Put(j, "capture_utc", capture_utc);
  Put(j, "schedule_error_ms", schedule_error_ms);
  Put(j, "schedule_overrun", schedule_overrun);
  Put(j, "exposure_us", exposure_us);
  Put(j, "gain", gain);
  Put(j, "wb_red", wb_red);
  Put(j, "wb_blue", wb_blue);
  Put(j, "camera_id", camera_id);
  Put(j, "camera_backend", camera_backend);
  Put(j, "width", width);
  Put(j, "height", height);
  Put(j, "frame_sequence", frame_sequence);
  Put(j, "time_scale", time_scale);
  if (!missing_controls.empty()) j["missing_controls"] = missing_controls;
  return j;
}

Result<ViewSidecar> ViewSidecar::FromJson(const json& j, const jsonio::Source& src) {
  ViewSidecar c;
  Fields f(j, src);
  f.Schema(kSampleFilesSchema);
  f.Req("view", &c.view);
  f.Opt("side", &c.side);
  f.Opt("image", &c.image);
  f.Opt("sample_id", &c.sample_id);
  f.Opt("commanded_angle_deg", &c.commanded_angle_deg);
  f.Opt("measured_angle_deg", &c.measured_angle_deg);
  f.Opt("due_monotonic_ns", &c.due_monotonic_ns);
  f.Opt("trigger_monotonic_ns", &c.trigger_monotonic_ns);
  f.Opt("capture_monotonic_ns", &c.capture_monotonic_ns);
  f.Opt("capture_utc", &c.capture_utc);
  f.Opt("schedule_error_ms", &c.schedule_error_ms);
  f.Opt("schedule_overrun", &c.schedule_overrun);
  f.Opt("exposure_us", &c.exposure_us);
  f.Opt("gain", &c.gain);
  f.Opt("wb_red", &c.wb_red);
  f.Opt("wb_blue", &c.wb_blue);
  f.Opt("camera_id", &c.camera_id);
  f.Opt("camera_backend", &c.camera_backend);
  f.Opt("width", &c.width);
  f.Opt("height", &c.height);
  f.Opt("frame_sequence", &c.frame_sequence);
  f.Opt("time_scale", &c.time_scale);
  f.Strings("missing_controls", &c.missing_controls);
  if (f.ok() && c.view < 0) f.Fail(src.Bad("\"view\" is negative"));
  if (f.ok() && c.side && *c.side < 1) f.Fail(src.Bad("\"side\" is not 1 or more"));
  if (!f.ok()) return f.error();
  c.extra = f.Extra();
  return c;
}

// --- SideManifest ----------------------------------------------------------

json SideManifest::Entry::ToJson() const {
  json j = extra.is_object() ? extra : json::object();
  j["view"] = view;
  j["image"] = image;
  Put(j, "sidecar", sidecar);
  // Unsigned, as a parser reads a non-negative number back.
  if (bytes) j["bytes"] = static_cast<uint64_t>(std::max<int64_t>(*bytes, 0));
  return j;
}

Result<SideManifest::Entry> SideManifest::Entry::FromJson(const json& j,
                                                          const jsonio::Source& src) {
  Entry e;
  Fields f(j, src);
  f.Req("view", &e.view);
  f.Req("image", &e.image);
  f.Opt("sidecar", &e.sidecar);
  f.Opt("bytes", &e.bytes);
  if (!f.ok()) return f.error();
  if (e.view < 0) return src.Bad("\"view\" is negative");
  if (!IsPlainName(e.image))
    return src.Bad("\"image\" \"" + e.image + "\" is not a file name in the side directory");
  if (e.sidecar && !IsPlainName(*e.sidecar))
    return src.Bad("\"sidecar\" \"" + *e.sidecar + "\" is not a file name in the side directory");
  if (e.bytes && *e.bytes < 0) return src.Bad("\"bytes\" is negative");
  e.extra = f.Extra();
  return e;
}

json SideManifest::ToJson() const {
  json j = Base(extra);
  j["side"] = side;
  Put(j, "sample_id", sample_id);
  Put(j, "completed_utc", completed_utc);
  json v = json::array();
  for (const Entry& e : views) v.push_back(e.ToJson());
  j["views"] = std::move(v);
  return j;
}

Result<SideManifest> SideManifest::FromJson(const json& j, const jsonio::Source& src) {
  SideManifest m;
  Fields f(j, src);
  f.Schema(kSampleFilesSchema);
  f.Req("side", &m.side);
  f.Opt("sample_id", &m.sample_id);
  f.Opt("completed_utc", &m.completed_utc);
  if (f.ok() && m.side < 1) f.Fail(src.Bad("\"side\" is not 1 or more"));
  if (f.ok() && !j.contains("views")) f.Fail(src.Bad("\"views\" is missing"));
  f.List("views", &m.views, Entry::FromJson);
  if (!f.ok()) return f.error();
  std::set<int> seen;
  for (const Entry& e : m.views) {
    if (!seen.insert(e.view).second)
      return src.Bad("view " + std::to_string(e.view) + " is listed twice");
  }
  m.extra = f.Extra();
  return m;
}

// --- Files -----------------------------------------------------------------

Result<ViewSidecar> ReadViewSidecarFile(const std::string& path) {
  auto j = jsonio::ReadFile(path, kViewSidecarWhat);
  if (!j) return j.error();
  return ViewSidecar::FromJson(*j, jsonio::Source{kViewSidecarWhat, path, ""});
}

Result<ViewSidecar> ReadViewSidecar(const std::string& side_dir, int view) {
  const std::string path = side_dir + "/" + layout::ViewSidecarName(view);
  auto c = ReadViewSidecarFile(path);
  if (!c) return c;
  if (c->view != view) {
    return jsonio::Source{kViewSidecarWhat, path, ""}.Bad(
        "\"view\" is " + std::to_string(c->view) + ", its file name says " + std::to_string(view));
  }
  return c;
}

Result<SideManifest> ReadSideManifest(const std::string& side_dir) {
  const std::string path = side_dir + "/" + layout::kManifest;
  auto j = jsonio::ReadFile(path, kSideManifestWhat);
  if (!j) {
    if (j.error().cls == ErrorClass::kNotFound) {
      return MakeError(
          ErrorClass::kNotFound,
          "no side manifest " + path + ": the side was not captured, or its capture did not finish",
          j.error().detail);
    }
    return j.error();
  }
  return SideManifest::FromJson(*j, jsonio::Source{kSideManifestWhat, path, ""});
}

}  // namespace aggscan
