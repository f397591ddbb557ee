#include "store/sample_files.h"

#include <algorithm>
#include <cstdint>
#include <set>
#include <span>
#include <type_traits>

#include "store/layout.h"

namespace aggscan {
namespace {

using nlohmann::json;

std::string Field(const char* key) { return std::string("\"") + key + "\""; }

bool Absent(const json& j, const char* key) { return !j.contains(key) || j[key].is_null(); }

// Optional fields: nullopt when absent or null, an error naming the field
// when present with another type.
Result<std::optional<double>> OptNumber(const json& j, const char* key, const jsonio::Source& src) {
  if (Absent(j, key)) return std::optional<double>();
  auto v = jsonio::Number(j, key, src);
  if (!v) return v.error();
  return std::optional<double>(*v);
}

Result<std::optional<int>> OptInt(const json& j, const char* key, const jsonio::Source& src) {
  if (Absent(j, key)) return std::optional<int>();
  auto v = jsonio::Int(j, key, src);
  if (!v) return v.error();
  return std::optional<int>(*v);
}

Result<std::optional<int64_t>> OptInt64(const json& j, const char* key, const jsonio::Source& src) {
  if (Absent(j, key)) return std::optional<int64_t>();
  const json& v = j[key];
  if (!v.is_number_integer()) return src.Bad(Field(key) + " is not a whole number");
  if (v.is_number_unsigned() && v.get<uint64_t>() > static_cast<uint64_t>(INT64_MAX))
    return src.Bad(Field(key) + " is out of range");
  return std::optional<int64_t>(v.get<int64_t>());
}

Result<std::optional<uint64_t>> OptUInt64(const json& j, const char* key,
                                          const jsonio::Source& src) {
  if (Absent(j, key)) return std::optional<uint64_t>();
  const json& v = j[key];
  if (!v.is_number_integer()) return src.Bad(Field(key) + " is not a whole number");
  if (!v.is_number_unsigned() && v.get<int64_t>() < 0) return src.Bad(Field(key) + " is negative");
  return std::optional<uint64_t>(v.get<uint64_t>());
}

Result<std::optional<std::string>> OptString(const json& j, const char* key,
                                             const jsonio::Source& src) {
  if (Absent(j, key)) return std::optional<std::string>();
  auto v = jsonio::String(j, key, src);
  if (!v) return v.error();
  return std::optional<std::string>(std::move(*v));
}

Result<std::optional<bool>> OptBool(const json& j, const char* key, const jsonio::Source& src) {
  if (Absent(j, key)) return std::optional<bool>();
  auto v = jsonio::Bool(j, key, src);
  if (!v) return v.error();
  return std::optional<bool>(*v);
}

// Reads one optional field into `out`; on a bad one returns false with `err` set.
template <typename T, typename Reader>
bool Read(const json& j, const char* key, const jsonio::Source& src, Reader reader,
          std::optional<T>& out, std::optional<Error>& err) {
  if (err) return false;
  auto v = reader(j, key, src);
  if (!v) {
    err = v.error();
    return false;
  }
  out = std::move(*v);
  return true;
}

// The members of `j` whose keys are not in `known` (nor "schema").
json Extra(const json& j, std::span<const char* const> known) {
  json extra = json::object();
  for (const auto& [k, v] : j.items()) {
    if (k == "schema") continue;
    bool is_known = false;
    for (const char* n : known) is_known = is_known || k == n;
    if (!is_known) extra[k] = v;
  }
  return extra;
}

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

template <typename T>
void Put(json& j, const char* key, const std::optional<T>& v) {
  if (!v) return;
  if constexpr (std::is_same_v<T, double>) {
    j[key] = jsonio::Finite(*v);
  } else {
    j[key] = *v;
  }
}

constexpr const char* kSidecarKeys[] = {"view",
                                        "side",
                                        "image",
                                        "sample_id",
                                        "commanded_angle_deg",
                                        "measured_angle_deg",
                                        "due_monotonic_ns",
                                        "trigger_monotonic_ns",
                                        "capture_monotonic_ns",
                                        "capture_utc",
                                        "schedule_error_ms",
                                        "schedule_overrun",
                                        "exposure_us",
                                        "gain",
                                        "wb_red",
                                        "wb_blue",
                                        "camera_id",
                                        "camera_backend",
                                        "width",
                                        "height",
                                        "frame_sequence",
                                        "time_scale",
                                        "missing_controls"};
constexpr const char* kEntryKeys[] = {"view", "image", "sidecar", "bytes"};
constexpr const char* kManifestKeys[] = {"side", "sample_id", "completed_utc", "views"};

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
  auto schema = jsonio::SchemaVersion(j, "schema", kSampleFilesSchema, src);
  if (!schema) return schema.error();
  ViewSidecar c;
  auto view = jsonio::Int(j, "view", src);
  if (!view) return view.error();
  if (*view < 0) return src.Bad("\"view\" is negative");
  c.view = *view;
  std::optional<Error> err;
  Read(j, "side", src, OptInt, c.side, err);
  Read(j, "image", src, OptString, c.image, err);
  Read(j, "sample_id", src, OptString, c.sample_id, err);
  Read(j, "commanded_angle_deg", src, OptNumber, c.commanded_angle_deg, err);
  Read(j, "measured_angle_deg", src, OptNumber, c.measured_angle_deg, err);
  Read(j, "due_monotonic_ns", src, OptInt64, c.due_monotonic_ns, err);
  Read(j, "trigger_monotonic_ns", src, OptInt64, c.trigger_monotonic_ns, err);
  Read(j, "capture_monotonic_ns", src, OptInt64, c.capture_monotonic_ns, err);
  Read(j, "capture_utc", src, OptString, c.capture_utc, err);
  Read(j, "schedule_error_ms", src, OptNumber, c.schedule_error_ms, err);
  Read(j, "schedule_overrun", src, OptBool, c.schedule_overrun, err);
  Read(j, "exposure_us", src, OptNumber, c.exposure_us, err);
  Read(j, "gain", src, OptNumber, c.gain, err);
  Read(j, "wb_red", src, OptNumber, c.wb_red, err);
  Read(j, "wb_blue", src, OptNumber, c.wb_blue, err);
  Read(j, "camera_id", src, OptString, c.camera_id, err);
  Read(j, "camera_backend", src, OptString, c.camera_backend, err);
  Read(j, "width", src, OptInt, c.width, err);
  Read(j, "height", src, OptInt, c.height, err);
  Read(j, "frame_sequence", src, OptUInt64, c.frame_sequence, err);
  Read(j, "time_scale", src, OptNumber, c.time_scale, err);
  if (err) return *err;
  if (c.side && *c.side < 1) return src.Bad("\"side\" is not 1 or more");
  if (!Absent(j, "missing_controls")) {
    const json& m = j["missing_controls"];
    if (!m.is_array()) return src.Bad("\"missing_controls\" is not a list");
    for (const json& s : m) {
      if (!s.is_string()) return src.Bad("\"missing_controls\" holds something not a string");
      c.missing_controls.push_back(s.get<std::string>());
    }
  }
  c.extra = Extra(j, kSidecarKeys);
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
  if (!j.is_object()) return src.Bad("not a JSON object");
  Entry e;
  auto view = jsonio::Int(j, "view", src);
  if (!view) return view.error();
  if (*view < 0) return src.Bad("\"view\" is negative");
  e.view = *view;
  auto image = jsonio::String(j, "image", src);
  if (!image) return image.error();
  if (!IsPlainName(*image))
    return src.Bad("\"image\" \"" + *image + "\" is not a file name in the side directory");
  e.image = std::move(*image);
  std::optional<Error> err;
  Read(j, "sidecar", src, OptString, e.sidecar, err);
  Read(j, "bytes", src, OptInt64, e.bytes, err);
  if (err) return *err;
  if (e.sidecar && !IsPlainName(*e.sidecar))
    return src.Bad("\"sidecar\" \"" + *e.sidecar + "\" is not a file name in the side directory");
  if (e.bytes && *e.bytes < 0) return src.Bad("\"bytes\" is negative");
  e.extra = Extra(j, kEntryKeys);
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
  auto schema = jsonio::SchemaVersion(j, "schema", kSampleFilesSchema, src);
  if (!schema) return schema.error();
  SideManifest m;
  auto side = jsonio::Int(j, "side", src);
  if (!side) return side.error();
  if (*side < 1) return src.Bad("\"side\" is not 1 or more");
  m.side = *side;
  std::optional<Error> err;
  Read(j, "sample_id", src, OptString, m.sample_id, err);
  Read(j, "completed_utc", src, OptString, m.completed_utc, err);
  if (err) return *err;
  if (!j.contains("views")) return src.Bad("\"views\" is missing");
  if (!j["views"].is_array()) return src.Bad("\"views\" is not a list");
  std::set<int> seen;
  for (size_t i = 0; i < j["views"].size(); ++i) {
    const jsonio::Source at{src.what, src.path + " (views[" + std::to_string(i) + "])", src.redo};
    auto e = Entry::FromJson(j["views"][i], at);
    if (!e) return e.error();
    if (!seen.insert(e->view).second)
      return at.Bad("view " + std::to_string(e->view) + " is listed twice");
    m.views.push_back(std::move(*e));
  }
  m.extra = Extra(j, kManifestKeys);
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
