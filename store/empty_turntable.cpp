#include "store/empty_turntable.h"

#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <ctime>

#include "common/clock.h"
#include "common/fsutil.h"
#include "common/json_io.h"
#include "store/layout.h"
#include "store/sample_files.h"

namespace aggscan {
namespace {

using json = nlohmann::json;

constexpr const char* kFormat = "aggscan-empty-turntable-1";
constexpr const char* kManifest = "manifest.json";
constexpr const char* kCurrent = "current.json";

Result<json> ReadJsonFile(const std::string& path) {
  return jsonio::ReadFile(path, "empty-turntable record",
                          "shoot the empty turntable again (aggscan empty-turntable)");
}

// A set id from the time it is installed: sorts by time, no ':' (a path).
std::string NewSetId(const std::string& root) { return FreeTimedName(root + "/", ""); }

// A hard link of `from` at `to`, or a durable copy where the filesystem has
// no hard links (or they cross filesystems). The files are write-once: a link
// shares nothing that can change.
Status LinkOrCopy(const std::string& from, const std::string& to) {
  if (::link(from.c_str(), to.c_str()) == 0) return {};
  Result<std::string> bytes = ReadFile(from);
  if (!bytes) return bytes.error();
  return WriteFileAtomic(to, *bytes, /*no_replace=*/true);
}

}  // namespace

json EmptyTurntableSet::ToJson() const {
  json v = json::array();
  for (const auto& x : views) v.push_back({{"image", x.image}, {"angle_deg", x.angle_deg}});
  return {
      {"format", kFormat}, {"set", id},        {"source", source}, {"captured_utc", captured_utc},
      {"width", width},    {"height", height}, {"views", v}};
}

Result<EmptyTurntableSet> EmptyTurntableSet::FromJson(const json& j, const std::string& what) {
  auto bad = [&](const std::string& why) {
    return MakeError(ErrorClass::kCorrupt, what + ": " + why +
                                               "; install the empty-turntable photos again "
                                               "(aggscan empty-turntable SAMPLE_DIR)");
  };
  if (!j.is_object() || j.value("format", "") != kFormat)
    return bad("not an " + std::string(kFormat) + " manifest");
  EmptyTurntableSet s;
  if (!j.contains("width") || !j["width"].is_number_integer() || !j.contains("height") ||
      !j["height"].is_number_integer())
    return bad("no integer width and height");
  s.width = j["width"].get<int>();
  s.height = j["height"].get<int>();
  if (s.width < 1 || s.height < 1) return bad("width and height must be positive");
  s.id = j.value("set", "");
  s.source = j.value("source", "");
  s.captured_utc = j.value("captured_utc", "");
  if (!j.contains("views") || !j["views"].is_array() || j["views"].empty()) return bad("no views");
  for (const json& v : j["views"]) {
    if (!v.is_object() || !v.contains("image") || !v["image"].is_string() ||
        !v.contains("angle_deg") || !v["angle_deg"].is_number())
      return bad("a view without image or angle_deg");
    const std::string image = v["image"].get<std::string>();
    if (image.empty() || image.find('/') != std::string::npos || image[0] == '.')
      return bad("view image '" + image + "' is not a plain file name");
    const double a = v["angle_deg"].get<double>();
    if (!std::isfinite(a)) return bad("view " + image + " has a non-finite angle");
    s.views.push_back({image, a});
  }
  return s;
}

const EmptyTurntableView* EmptyTurntableSet::Nearest(double angle_deg, double* distance_deg) const {
  const EmptyTurntableView* best = nullptr;
  double best_d = 0;
  for (const auto& v : views) {
    double d = std::fmod(std::fabs(v.angle_deg - angle_deg), 360.0);
    d = std::min(d, 360.0 - d);
    if (!best || d < best_d) best = &v, best_d = d;
  }
  if (distance_deg) *distance_deg = best_d;
  return best;
}

std::string EmptyTurntableRoot(const std::string& state_dir) {
  return state_dir + "/empty-turntable";
}

Result<EmptyTurntableSet> LoadEmptyTurntableSet(const std::string& dir) {
  const std::string path = dir + "/" + kManifest;
  if (!PathExists(path))
    return MakeError(ErrorClass::kNotFound, "no empty-turntable photos in " + dir);
  Result<json> j = ReadJsonFile(path);
  if (!j) return j.error();
  Result<EmptyTurntableSet> s = EmptyTurntableSet::FromJson(*j, path);
  if (!s) return s.error();
  for (const auto& v : s->views) {
    if (!PathExists(dir + "/" + v.image))
      return MakeError(ErrorClass::kCorrupt, path + " lists " + v.image + ", which is not in " +
                                                 dir +
                                                 "; install the empty-turntable photos again");
  }
  return s;
}

Result<EmptyTurntableSet> CurrentEmptyTurntableSet(const std::string& state_dir) {
  const std::string root = EmptyTurntableRoot(state_dir);
  const std::string current = root + "/" + kCurrent;
  if (!PathExists(current))
    return MakeError(ErrorClass::kNotFound,
                     "no empty-turntable photos installed (" + current + ")");
  Result<json> j = ReadJsonFile(current);
  if (!j) return j.error();
  const std::string id = j->is_object() ? j->value("set", "") : "";
  if (id.empty() || id.find('/') != std::string::npos || id[0] == '.')
    return MakeError(ErrorClass::kCorrupt,
                     current + " names no set; install the empty-turntable photos again");
  return LoadEmptyTurntableSet(root + "/" + id);
}

Status WriteEmptyTurntableSet(const std::string& dir, const EmptyTurntableSet& set,
                              const std::vector<std::string>& photos) {
  if (photos.size() != set.views.size())
    return MakeError(ErrorClass::kInvalidArgument,
                     "an empty-turntable set needs one photo per view");
  if (Status s = MakeDirsDurable(dir); !s) return s;
  for (size_t i = 0; i < photos.size(); ++i) {
    const std::string to = dir + "/" + set.views[i].image;
    if (Status s = LinkOrCopy(photos[i], to); !s) return s;
  }
  if (Status s = FsyncDir(dir); !s) return s;
  return WriteFileAtomic(dir + "/" + kManifest, set.ToJson().dump(1) + "\n", /*no_replace=*/true);
}

Result<EmptyTurntableSet> InstallEmptyTurntableSet(const std::string& state_dir,
                                                   const std::string& sample_dir, int side,
                                                   int width, int height) {
  const std::string side_dir = sample_dir + "/" + layout::SideDirName(side);
  const std::string manifest_path = side_dir + "/" + layout::kManifest;
  if (!PathExists(manifest_path))
    return MakeError(ErrorClass::kNotFound, "side " + std::to_string(side) + " of " + sample_dir +
                                                " is not a complete capture (no " + manifest_path +
                                                ")");
  Result<SideManifest> manifest = ReadSideManifest(side_dir);
  if (!manifest) return manifest.error();
  if (manifest->views.empty())
    return MakeError(ErrorClass::kCorrupt, manifest_path + " lists no views");
  EmptyTurntableSet set;
  set.source = sample_dir + " side " + std::to_string(side);
  set.captured_utc = manifest->completed_utc.value_or("");
  set.width = width;
  set.height = height;
  std::vector<std::string> photos;
  for (const SideManifest::Entry& v : manifest->views) {
    const std::string sidecar = v.sidecar.value_or(layout::ViewSidecarName(v.view));
    Result<ViewSidecar> sc = ReadViewSidecarFile(side_dir + "/" + sidecar);
    if (!sc || !sc->measured_angle_deg)
      return MakeError(
          ErrorClass::kInvalidArgument,
          side_dir + "/" + sidecar + " gives no measured turntable angle for " + v.image +
              ": the empty-turntable photos are matched to a rock's views by that angle" +
              (sc ? std::string() : " (" + sc.error().message + ")"));
    set.views.push_back({v.image, *sc->measured_angle_deg});
    photos.push_back(side_dir + "/" + v.image);
  }
  const std::string root = EmptyTurntableRoot(state_dir);
  if (Status s = MakeDirsDurable(root); !s) return s.error();
  set.id = NewSetId(root);
  if (Status s = WriteEmptyTurntableSet(root + "/" + set.id, set, photos); !s) return s.error();
  if (Status s = WriteFileAtomic(root + "/" + kCurrent, json{{"set", set.id}}.dump() + "\n"); !s)
    return s.error();
  return set;
}

json LinkEmptyTurntableSet(const std::string& state_dir, const std::string& sample_dir) {
  const std::string dir = sample_dir + "/" + layout::kEmptyDir;
  if (Result<EmptyTurntableSet> own = LoadEmptyTurntableSet(dir); own)
    return {{"set", own->id}, {"captured_utc", own->captured_utc}, {"views", own->views.size()}};
  Result<EmptyTurntableSet> cur = CurrentEmptyTurntableSet(state_dir);
  if (!cur) return {{"set", nullptr}, {"reason", cur.error().message}};
  std::vector<std::string> photos;
  const std::string from = EmptyTurntableRoot(state_dir) + "/" + cur->id;
  for (const auto& v : cur->views) photos.push_back(from + "/" + v.image);
  if (PathExists(dir)) {
    // A link interrupted before its manifest: the files are the set's own.
    for (const auto& v : cur->views) std::remove((dir + "/" + v.image).c_str());
  }
  if (Status s = WriteEmptyTurntableSet(dir, *cur, photos); !s)
    return {{"set", nullptr},
            {"reason", "cannot link " + from + " into the sample: " + s.error().ToString()}};
  return {{"set", cur->id}, {"captured_utc", cur->captured_utc}, {"views", cur->views.size()}};
}

}  // namespace aggscan
