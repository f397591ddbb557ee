#include "store/sample_store.h"

#include <dirent.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <cstdint>
#include <filesystem>
#include <type_traits>

#include "common/clock.h"
#include "common/fsutil.h"
#include "common/json_io.h"
#include "common/rig_calibration.h"
#include "store/empty_turntable.h"
#include "store/layout.h"
#include "store/sample_files.h"
#include "store/sample_meta.h"

namespace aggscan {
namespace {

using nlohmann::json;
namespace fs = std::filesystem;

bool IsDir(const std::string& p) {
  struct stat st {};
  return ::stat(p.c_str(), &st) == 0 && S_ISDIR(st.st_mode);
}

std::vector<std::string> ListDir(const std::string& dir) {
  std::vector<std::string> names;
  DIR* d = ::opendir(dir.c_str());
  if (!d) return names;
  while (dirent* e = ::readdir(d)) {
    std::string n = e->d_name;
    if (n != "." && n != "..") names.push_back(n);
  }
  ::closedir(d);
  std::sort(names.begin(), names.end());
  return names;
}

// Complete views of a side directory: those whose sidecar exists.
std::vector<int> CompleteViews(const std::string& side_dir) {
  std::vector<int> views;
  for (const auto& n : ListDir(side_dir)) {
    int v = -1;
    char tail[8] = {0};
    if (std::sscanf(n.c_str(), "view_%d.%4s", &v, tail) == 2 && std::string(tail) == "json" &&
        v >= 0) {
      if (PathExists(side_dir + "/" + layout::ViewImageName(v))) views.push_back(v);
    }
  }
  std::sort(views.begin(), views.end());
  return views;
}

json PlanToJson(const SamplePlan& p) {
  return {{"profile", p.profile},
          {"sides", p.sides},
          {"views_per_side", p.views_per_side},
          {"step_deg", p.step_deg},
          {"interval_ms", p.interval_ms}};
}

bool SamePlan(const json& a, const SamplePlan& p) {
  return a.value("sides", -1) == p.sides && a.value("views_per_side", -1) == p.views_per_side &&
         std::abs(a.value("step_deg", -1.0) - p.step_deg) < 1e-9;
}

// Applies fn to the record's entry for `side`.
template <typename F>
void ForSide(json& rec, int side, F fn) {
  for (auto& sd : rec["sides"]) {
    if (sd.value("side", 0) == side) fn(sd);
  }
}

// JSON text of a record, sidecar or manifest. Strings that are not UTF-8 (a
// parser's message quoting the bytes of a damaged file, a device's name) are
// written with U+FFFD in their place: json::dump would throw on them.
std::string JsonText(const json& j) {
  return j.dump(2, ' ', false, json::error_handler_t::replace) + "\n";
}

Error BadId(const std::string& id) {
  return MakeError(ErrorClass::kInvalidArgument,
                   "invalid sample id \"" + id.substr(0, 80) +
                       "\": use 1-64 characters of A-Z a-z 0-9 . _ - (not starting with . or -)");
}

// What is wrong with a parsed sample record, empty when nothing: every field
// the store's readers take is there with its type (json::value throws when a
// field holds another type than its default).
std::string RecordShapeProblem(const json& rec) {
  auto typed = [](const json& j, const char* key, json::value_t t) {
    if (!j.contains(key)) return true;
    const json& v = j[key];
    switch (t) {
      case json::value_t::number_integer:  // counts: the store adds one to them
        return v.is_number_integer() && v.get<int64_t>() >= 0 &&
               v.get<int64_t>() < (int64_t{1} << 30);
      case json::value_t::number_float:
        return v.is_number();
      default:
        return v.type() == t;
    }
  };
  using T = json::value_t;
  if (!rec.contains("state") || !rec["state"].is_string()) return "state missing or not a string";
  for (const char* k : {"id", "created_utc", "updated_utc", "resumed_utc"})
    if (!typed(rec, k, T::string)) return std::string(k) + " is not a string";
  if (!typed(rec, "resumes", T::number_integer)) return "resumes is not a count";
  if (!rec.contains("plan") || !rec["plan"].is_object()) return "plan missing";
  const json& plan = rec["plan"];
  for (const char* k : {"sides", "views_per_side"})
    if (!plan.contains(k) || !plan[k].is_number_integer() || plan[k].get<int64_t>() < 1 ||
        plan[k].get<int64_t>() > 100000)
      return std::string("plan.") + k + " missing or not a count from 1 to 100000";
  if (!typed(plan, "step_deg", T::number_float)) return "plan.step_deg is not a number";
  if (!rec.contains("sides") || !rec["sides"].is_array()) return "sides missing";
  for (const auto& sd : rec["sides"]) {
    if (!sd.is_object() || !sd.contains("side") || !sd["side"].is_number_integer())
      return "a side entry has no integer \"side\"";
    if (!typed(sd, "state", T::string)) return "a side's state is not a string";
    for (const char* k : {"attempts", "views", "views_found"})
      if (!typed(sd, k, T::number_integer)) return std::string("a side's ") + k + " is not a count";
  }
  return "";
}

// The field `key` of a sidecar that does not read as a ViewSidecar (damaged,
// or hand-edited) when it holds the type of `fallback`, else `fallback`.
template <typename T>
T SidecarField(const json& car, const char* key, T fallback) {
  if (!car.contains(key)) return fallback;
  const json& v = car[key];
  if constexpr (std::is_same_v<T, double>) {
    return v.is_number() ? v.get<double>() : fallback;
  } else {
    return v.is_string() ? v.get<std::string>() : fallback;
  }
}

// The sidecar the capture hands over, as stored at `path`: the store's own
// coordinates (sample, side, view, image name) filled in where it leaves them
// out; a sidecar of another type, with a field of the wrong type or naming
// other coordinates is refused before anything is written.
Result<ViewSidecar> SidecarToStore(const json& given, const std::string& id, int side, int view,
                                   const std::string& path) {
  if (!given.is_null() && !given.is_object()) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "view sidecar for " + path + " is not a JSON object; view not stored");
  }
  json j = given.is_null() ? json::object() : given;
  const std::string image = layout::ViewImageName(view);
  for (const auto& [key, value] : {std::pair<const char*, json>{"sample_id", id},
                                   {"side", side},
                                   {"view", view},
                                   {"image", image}}) {
    if (!j.contains(key) || j[key].is_null()) j[key] = value;
  }
  Result<ViewSidecar> car = ViewSidecar::FromJson(j, jsonio::Source{kViewSidecarWhat, path, ""});
  if (!car) {
    return MakeError(ErrorClass::kInvalidArgument, car.error().message + "; view not stored");
  }
  auto mismatch = [&](const std::string& what) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "view sidecar " + path + ": " + what + "; view not stored");
  };
  if (car->sample_id != id) return mismatch("\"sample_id\" is not \"" + id + "\"");
  if (car->side != side) return mismatch("\"side\" is not " + std::to_string(side));
  if (car->view != view) return mismatch("\"view\" is not " + std::to_string(view));
  if (car->image != image) return mismatch("\"image\" is not \"" + image + "\"");
  return car;
}

// Writes side_dir/manifest.json listing the side's complete views.
Result<SideManifest> WriteSideManifest(const std::string& side_dir, const std::string& id,
                                       int side) {
  SideManifest m;
  m.side = side;
  m.sample_id = id;
  for (int v : CompleteViews(side_dir)) {
    struct stat st {};
    if (::stat((side_dir + "/" + layout::ViewImageName(v)).c_str(), &st) != 0) {
      return ErrnoError("cannot stat " + side_dir + "/" + layout::ViewImageName(v), errno);
    }
    SideManifest::Entry e;
    e.view = v;
    e.image = layout::ViewImageName(v);
    e.sidecar = layout::ViewSidecarName(v);
    e.bytes = static_cast<int64_t>(st.st_size);
    m.views.push_back(std::move(e));
  }
  m.completed_utc = NowUtcString();
  Status s = jsonio::WriteFile(side_dir + "/" + layout::kManifest, m.ToJson(), true);
  if (!s) return s.error();
  return m;
}

}  // namespace

std::string SampleStore::SampleDir(const std::string& id) const {
  return CollectionDir() + "/" + id;
}

Status SampleStore::Init() { return MakeDirsDurable(CollectionDir()); }

Status SampleStore::SaveRecord(const std::string& id, const json& rec) {
  json r = rec;
  r["updated_utc"] = NowUtcString();
  return WriteFileAtomic(SampleDir(id) + "/" + layout::kSampleRecord, JsonText(r));
}

Status SampleStore::UpdateRecord(const std::string& id, const std::function<void(json&)>& edit) {
  Result<json> rec = LoadRecord(id);
  if (!rec) return rec.error();
  json r = std::move(*rec);
  edit(r);
  return SaveRecord(id, r);
}

Result<json> SampleStore::EditMeta(const std::string& id, const json& doc, const std::string& by) {
  Result<json> rec = LoadRecord(id);
  if (!rec) return rec.error();
  json meta = rec->value("meta", json::object());
  if (!meta.is_object()) meta = json::object();
  Result<json> patch =
      sample_meta::CheckPatch(doc, /*allow_removal=*/true, {}, meta.value("material", json()));
  if (!patch) return patch.error();
  json changed = sample_meta::ApplyPatch(meta, *patch);
  if (!changed.empty()) {
    json r = std::move(*rec);
    r["meta"] = meta;
    if (!r.contains("meta_history") || !r["meta_history"].is_array())
      r["meta_history"] = json::array();
    r["meta_history"].push_back({{"utc", NowUtcString()}, {"by", by}, {"changed", changed}});
    if (Status s = SaveRecord(id, r); !s) return s.error();
  }
  return json{{"id", id}, {"meta", meta}, {"changed", changed}};
}

Result<json> SampleStore::LoadRecord(const std::string& id) const {
  if (!layout::IsValidSampleId(id)) return BadId(id);
  const std::string path = SampleDir(id) + "/" + layout::kSampleRecord;
  if (!PathExists(SampleDir(id)))
    return MakeError(ErrorClass::kNotFound, "no sample \"" + id + "\"");
  Result<std::string> text = ReadFile(path);
  if (!text) return text.error();
  json rec = json::parse(*text, nullptr, false);
  if (rec.is_discarded() || !rec.is_object()) {
    return MakeError(ErrorClass::kCorrupt, "sample record " + path + " is not valid JSON");
  }
  // Every reader below relies on this shape; a damaged record is refused
  // here, never allowed to throw later on the capture loop.
  if (const std::string bad = RecordShapeProblem(rec); !bad.empty()) {
    return MakeError(ErrorClass::kCorrupt,
                     "sample record " + path + " is damaged (" + bad +
                         "); its images are untouched — "
                         "move the sample directory aside to re-shoot under this id");
  }
  return rec;
}

Result<RecoveryReport> SampleStore::Recover() {
  RecoveryReport rep;
  const std::string samples = CollectionDir();
  rep.temp_files_removed += RemoveTempFiles(samples);
  for (const auto& id : ListDir(samples)) {
    const std::string dir = samples + "/" + id;
    if (!IsDir(dir) || !layout::IsValidSampleId(id)) continue;
    ++rep.samples;
    rep.temp_files_removed += RemoveTempFiles(dir);
    for (const auto& sub : ListDir(dir)) {
      if (IsDir(dir + "/" + sub)) rep.temp_files_removed += RemoveTempFiles(dir + "/" + sub);
    }
    Result<json> rec = LoadRecord(id);
    if (!rec) continue;  // a sample whose record never landed has no views either
    json r = *rec;
    const std::string st = r.value("state", "");
    const int views_planned = r["plan"].value("views_per_side", 0);
    bool changed = false;
    for (auto& side : r["sides"]) {
      const int n = side.value("side", 0);
      const std::string side_dir = dir + "/" + layout::SideDirName(n);
      const bool has_manifest = PathExists(side_dir + "/" + layout::kManifest);
      if (has_manifest) {
        // Crashed (or failed) between the manifest and the record update.
        if (side.value("state", "") != "done") {
          side["state"] = "done";
          changed = true;
        }
      } else if (side.value("state", "") == "capturing") {
        const size_t found = CompleteViews(side_dir).size();
        side["state"] = "interrupted";
        side["views_found"] = found;
        changed = true;
        // A side with every view stored is completed below, not re-shot.
        if (static_cast<int>(found) < views_planned) ++rep.sides_interrupted;
      }
    }
    if (st == "armed" || st == "capturing" || st == "awaiting_pose") {
      r["state"] = "interrupted";
      changed = true;
    }
    if (changed) {
      Status s = SaveRecord(id, r);
      if (!s) return s.error();
    }
    Result<Completion> done = CompleteStored(id);
    if (!done) return done.error();
    rep.sides_completed += static_cast<int>(done->sides_completed.size());
    if (done->sample_completed_now) {
      rep.completed_samples.push_back(id);
    } else if (!done->sample_captured && r.value("state", "") == "interrupted" &&
               st != "interrupted") {
      rep.interrupted_samples.push_back(id);
    }
  }
  return rep;
}

Result<Completion> SampleStore::CompleteStored(const std::string& id) {
  Result<json> rec = LoadRecord(id);
  if (!rec) return rec.error();
  Completion out;
  const std::string dir = SampleDir(id);
  const int views_planned = (*rec)["plan"].value("views_per_side", 0);
  const int sides_planned = (*rec)["plan"].value("sides", 0);
  int with_manifest = 0;
  for (int side = 1; side <= sides_planned; ++side) {
    const std::string side_dir = dir + "/" + layout::SideDirName(side);
    if (PathExists(side_dir + "/" + layout::kManifest)) {
      ++with_manifest;
      continue;
    }
    // Every planned view 0..N-1, each with image and sidecar: the side was
    // shot completely and only its manifest is missing.
    const std::vector<int> views = CompleteViews(side_dir);
    bool all = static_cast<int>(views.size()) >= views_planned;
    for (int v = 0; all && v < views_planned; ++v)
      all = std::binary_search(views.begin(), views.end(), v);
    if (!all) continue;
    Result<json> manifest = WriteManifest(id, side);
    if (!manifest) return manifest.error();
    out.sides_completed.push_back(side);
    ++with_manifest;
  }
  out.sample_captured = with_manifest == sides_planned;
  const bool was_captured = rec->value("state", "") == "captured";
  out.sample_completed_now = out.sample_captured && !was_captured;
  if (out.sides_completed.empty() && !out.sample_completed_now) {
    // Still mend a record that lags behind the manifests (kept "done" below).
    bool lag = false;
    for (const auto& sd : (*rec)["sides"]) {
      const int n = sd.value("side", 0);
      lag = lag || (sd.value("state", "") != "done" &&
                    PathExists(dir + "/" + layout::SideDirName(n) + "/" + layout::kManifest));
    }
    if (!lag) return out;
  }
  Status s = UpdateRecord(id, [&](json& r) {
    for (auto& sd : r["sides"]) {
      const int n = sd.value("side", 0);
      const std::string side_dir = dir + "/" + layout::SideDirName(n);
      if (sd.value("state", "") == "done" || !PathExists(side_dir + "/" + layout::kManifest))
        continue;
      sd["state"] = "done";
      sd["views"] = CompleteViews(side_dir).size();
      sd["completed_utc"] = NowUtcString();
    }
    if (out.sample_completed_now) {
      r["state"] = "captured";
      r["completed_from_store_utc"] = NowUtcString();
    }
  });
  if (!s) return s.error();
  return out;
}

Result<int> SampleStore::PrepareArm(const std::string& id, const SamplePlan& plan) const {
  if (!layout::IsValidSampleId(id)) return BadId(id);
  // No record yet (never created, or a crash before the record landed): new.
  if (!PathExists(SampleDir(id) + "/" + layout::kSampleRecord)) return 1;
  Result<json> rec = LoadRecord(id);
  if (!rec) return rec.error();
  const std::string st = rec->value("state", "");
  if (st == "captured") {
    return MakeError(ErrorClass::kConflict,
                     "sample \"" + id + "\" is already complete; choose a new id");
  }
  if (!SamePlan((*rec)["plan"], plan)) {
    return MakeError(ErrorClass::kConflict,
                     "sample \"" + id +
                         "\" was started with a different capture plan; resume it with the "
                         "same profile or choose a new id");
  }
  for (int side = 1; side <= plan.sides; ++side) {
    if (!PathExists(SampleDir(id) + "/" + layout::SideDirName(side) + "/" + layout::kManifest))
      return side;
  }
  return MakeError(ErrorClass::kConflict,
                   "sample \"" + id + "\" has every side captured; choose a new id");
}

Status SampleStore::CreateOrResume(const std::string& id, const SamplePlan& plan,
                                   const std::string& config_toml, const json& meta) {
  if (!layout::IsValidSampleId(id)) return BadId(id);
  const std::string dir = SampleDir(id);
  json rec;
  if (PathExists(dir + "/" + layout::kSampleRecord)) {
    Result<json> r = LoadRecord(id);
    if (!r) return r.error();
    rec = *r;
    rec["resumed_utc"] = NowUtcString();
  } else {
    Status s = MakeDirsDurable(dir);
    if (!s) return s;
    rec = {{"id", id},
           {"created_utc", NowUtcString()},
           {"plan", PlanToJson(plan)},
           {"sides", json::array()}};
    for (int side = 1; side <= plan.sides; ++side) {
      rec["sides"].push_back({{"side", side}, {"state", "pending"}, {"attempts", 0}});
    }
  }
  if (meta.is_object()) {
    json m = rec.value("meta", json::object());
    json given = meta;
    // A default from the config does not replace the material a resumed
    // sample already has (given when it was armed, or edited since).
    if (given.contains("material") && given["material"].is_object() &&
        given["material"].value("source", "") == "config" && m.is_object() &&
        m.contains("material"))
      given.erase("material");
    sample_meta::ApplyPatch(m, given);
    if (!m.empty() || rec.contains("meta")) rec["meta"] = std::move(m);
  }
  // The config in effect for this capture; a resume keeps the first copy too.
  const std::string cfg = dir + "/" + layout::kConfigCopy;
  if (PathExists(cfg)) {
    Status s = WriteFileAtomic(
        dir + "/config.resumed-" + std::to_string(rec.value("resumes", 0) + 1) + ".toml",
        config_toml, true);
    if (!s) return s;
    rec["resumes"] = rec.value("resumes", 0) + 1;
  } else {
    Status s = WriteFileAtomic(cfg, config_toml, true);
    if (!s) return s;
  }
  // The rig calibration in effect, recorded once: a resume after a new
  // calibration keeps the sample's first one (its views were shot with it).
  const std::string cal_copy = dir + "/" + layout::kCalibrationCopy;
  if (!PathExists(cal_copy)) {
    const std::string cal_path = CalibrationPath(state_dir_);
    Result<RigCalibration> cal = LoadCalibration(cal_path);
    Result<std::string> text = cal ? ReadFile(cal_path) : Result<std::string>(cal.error());
    if (text) {
      Status s = WriteFileAtomic(cal_copy, *text, /*no_replace=*/true);
      if (!s) return s;
      rec["calibration"] = {{"file", layout::kCalibrationCopy},
                            {"created_utc", cal->created_utc},
                            {"reprojection_rms_px", cal->reprojection_rms_px}};
    } else {
      rec["calibration"] = {{"file", nullptr}, {"reason", text.error().ToString()}};
    }
  }
  // The empty-turntable photos in effect, linked in once, like the
  // calibration: the sample keeps the set its views were shot against.
  if (!rec.contains("empty_turntable"))
    rec["empty_turntable"] = LinkEmptyTurntableSet(state_dir_, dir);
  rec["state"] = "armed";
  return SaveRecord(id, rec);
}

Status SampleStore::BeginSide(const std::string& id, int side) {
  const std::string dir = SampleDir(id);
  const std::string side_dir = dir + "/" + layout::SideDirName(side);
  if (PathExists(side_dir + "/" + layout::kManifest)) {
    return MakeError(ErrorClass::kConflict,
                     "side " + std::to_string(side) + " of \"" + id + "\" is already complete");
  }
  if (PathExists(side_dir)) {
    int k = 1;
    while (PathExists(side_dir + ".interrupted-" + std::to_string(k))) ++k;
    Status s = RenameDurable(side_dir, side_dir + ".interrupted-" + std::to_string(k));
    if (!s) return s;
  }
  Status s = MakeDirsDurable(side_dir);
  if (!s) return s;
  return UpdateRecord(id, [&](json& r) {
    r["state"] = "capturing";
    ForSide(r, side, [](json& sd) {
      sd["state"] = "capturing";
      sd["attempts"] = sd.value("attempts", 0) + 1;
      sd["started_utc"] = NowUtcString();
    });
  });
}

Status SampleStore::WriteView(const std::string& id, int side, int view,
                              std::span<const unsigned char> image, const json& sidecar) {
  const std::string side_dir = SampleDir(id) + "/" + layout::SideDirName(side);
  const std::string car_path = side_dir + "/" + layout::ViewSidecarName(view);
  // Checked before the image lands: a view is stored whole or not at all.
  Result<ViewSidecar> car = SidecarToStore(sidecar, id, side, view, car_path);
  if (!car) return car.error();
  Status s =
      WriteFileAtomic(side_dir + "/" + layout::ViewImageName(view), image, /*no_replace=*/true);
  if (!s) return s;
  return jsonio::WriteFile(car_path, car->ToJson(), /*no_replace=*/true);
}

Result<json> SampleStore::WriteManifest(const std::string& id, int side) {
  Result<SideManifest> m =
      WriteSideManifest(SampleDir(id) + "/" + layout::SideDirName(side), id, side);
  if (!m) return m.error();
  return m->ToJson();
}

Status SampleStore::FinishSide(const std::string& id, int side) {
  Result<SideManifest> manifest =
      WriteSideManifest(SampleDir(id) + "/" + layout::SideDirName(side), id, side);
  if (!manifest) return manifest.error();
  return UpdateRecord(id, [&](json& r) {
    ForSide(r, side, [&](json& sd) {
      sd["state"] = "done";
      sd["views"] = manifest->views.size();
      sd["completed_utc"] = manifest->completed_utc.value_or(NowUtcString());
    });
  });
}

Status SampleStore::SetSampleState(const std::string& id, const std::string& state,
                                   int side_in_progress, const std::string& side_state) {
  return UpdateRecord(id, [&](json& r) {
    r["state"] = state;
    if (side_in_progress > 0 && !side_state.empty()) {
      ForSide(r, side_in_progress, [&](json& sd) {
        if (sd.value("state", "") != "done") sd["state"] = side_state;
      });
    }
  });
}

Result<json> SampleStore::List() const {
  json out = json::array();
  const std::string samples = CollectionDir();
  for (const auto& id : ListDir(samples)) {
    if (!layout::IsValidSampleId(id) || !IsDir(samples + "/" + id)) continue;
    Result<json> rec = LoadRecord(id);
    if (!rec) {
      out.push_back({{"id", id}, {"state", "unreadable"}, {"error", rec.error().ToString()}});
      continue;
    }
    int sides_done = 0, views = 0;
    for (const auto& sd : (*rec)["sides"]) {
      if (sd.value("state", "") == "done") ++sides_done;
      views += static_cast<int>(
          CompleteViews(samples + "/" + id + "/" + layout::SideDirName(sd.value("side", 0)))
              .size());
    }
    out.push_back({{"id", id},
                   {"state", rec->value("state", "")},
                   {"created_utc", rec->value("created_utc", "")},
                   {"meta", rec->value("meta", json::object())},
                   {"sides", (*rec)["plan"].value("sides", 0)},
                   {"sides_done", sides_done},
                   {"views", views}});
  }
  std::sort(out.begin(), out.end(), [](const json& a, const json& b) {
    return a.value("created_utc", "") < b.value("created_utc", "");
  });
  return out;
}

std::vector<std::pair<std::string, int>> SampleStore::CapturedWork(const std::string& only) const {
  std::vector<std::pair<std::string, int>> work;
  const std::string samples = CollectionDir();
  for (const auto& id : only.empty() ? ListDir(samples) : std::vector<std::string>{only}) {
    if (!layout::IsValidSampleId(id) || !IsDir(samples + "/" + id)) continue;
    Result<json> rec = LoadRecord(id);
    if (!rec) continue;
    for (const auto& sd : (*rec)["sides"]) {
      const int side = sd["side"].get<int>();
      if (PathExists(samples + "/" + id + "/" + layout::SideDirName(side) + "/" +
                     layout::kManifest)) {
        work.emplace_back(id, side);
      }
    }
    if (rec->value("state", "") == "captured") work.emplace_back(id, 0);
  }
  return work;
}

std::pair<int, int64_t> SampleStore::StoredViewBytes(const std::string& id) const {
  std::pair<int, int64_t> out{0, 0};
  if (!layout::IsValidSampleId(id)) return out;
  const std::string dir = SampleDir(id);
  for (const auto& sub : ListDir(dir)) {
    if (sub.rfind("side", 0) != 0 || !IsDir(dir + "/" + sub)) continue;
    for (int v : CompleteViews(dir + "/" + sub)) {
      struct stat st {};
      if (::stat((dir + "/" + sub + "/" + layout::ViewImageName(v)).c_str(), &st) != 0) continue;
      ++out.first;
      out.second += st.st_size;
    }
  }
  return out;
}

Result<std::vector<std::pair<std::string, std::string>>> SampleStore::ImageFiles(
    const std::string& id) const {
  Result<json> rec = LoadRecord(id);
  if (!rec) return rec.error();
  const std::string dir = SampleDir(id);
  std::vector<std::pair<std::string, std::string>> files;
  auto add = [&](const std::string& name) {
    if (PathExists(dir + "/" + name)) files.emplace_back(dir + "/" + name, name);
  };
  add(layout::kSampleRecord);
  add(layout::kConfigCopy);
  add(layout::kCalibrationCopy);
  const json sides = rec->value("sides", json::array());
  for (const auto& sd : sides) {
    if (!sd.is_object()) continue;
    const std::string side = layout::SideDirName(sd.value("side", 0));
    for (int v : CompleteViews(dir + "/" + side)) {
      add(side + "/" + layout::ViewImageName(v));
      add(side + "/" + layout::ViewSidecarName(v));
    }
    add(side + "/" + layout::kManifest);
    for (int v : CompleteViews(dir + "/" + side))
      add(std::string(layout::kResultsDir) + "/masks/" + side + "/" + layout::ViewStem(v) + ".png");
  }
  return files;
}

Result<json> SampleStore::Describe(const std::string& id) const {
  Result<json> rec = LoadRecord(id);
  if (!rec) return rec.error();
  json out = *rec;
  const std::string dir = SampleDir(id);
  for (auto& sd : out["sides"]) {
    const std::string side_dir = dir + "/" + layout::SideDirName(sd.value("side", 0));
    json views = json::array();
    for (int v : CompleteViews(side_dir)) {
      json view = {
          {"view", v},
          {"image", layout::SideDirName(sd.value("side", 0)) + "/" + layout::ViewImageName(v)}};
      if (Result<ViewSidecar> car = ReadViewSidecar(side_dir, v)) {
        view["commanded_angle_deg"] = car->commanded_angle_deg.value_or(0.0);
        // A hand-turned table measures no angle: null, not a 0 that reads as one.
        view["measured_angle_deg"] =
            car->measured_angle_deg ? json(*car->measured_angle_deg) : json(nullptr);
        view["capture_utc"] = car->capture_utc.value_or("");
        view["schedule_error_ms"] = car->schedule_error_ms.value_or(0.0);
      } else {
        // A damaged or hand-edited sidecar: what still reads, and why the rest does not.
        Result<std::string> t = ReadFile(side_dir + "/" + layout::ViewSidecarName(v));
        json raw = t ? json::parse(*t, nullptr, false) : json();
        if (!raw.is_object()) raw = json::object();
        view["commanded_angle_deg"] = SidecarField(raw, "commanded_angle_deg", 0.0);
        view["measured_angle_deg"] = SidecarField(raw, "measured_angle_deg", 0.0);
        view["capture_utc"] = SidecarField(raw, "capture_utc", std::string());
        view["schedule_error_ms"] = SidecarField(raw, "schedule_error_ms", 0.0);
        view["sidecar_problem"] = car.error().message;
      }
      views.push_back(std::move(view));
    }
    sd["captured_views"] = views;
    json attempts = json::array();
    for (const auto& n : ListDir(dir)) {
      if (n.rfind(layout::SideDirName(sd.value("side", 0)) + ".interrupted-", 0) == 0) {
        attempts.push_back({{"dir", n}, {"views", CompleteViews(dir + "/" + n).size()}});
      }
    }
    sd["interrupted_attempts"] = attempts;
  }
  return out;
}

}  // namespace aggscan
