#include "pipeline/core/records.h"

namespace aggscan::records {

using nlohmann::json;

namespace {

using jsonio::Fields;
using jsonio::Put;

void PoseReq(Fields& f, const json& j, const char* key, Pose* out) {
  f.Use(key, PoseField(j, key, f.source()), out);
}

// Writes `extra` first and the record's own fields over it.
json Base(const json& extra) { return extra.is_object() ? extra : json::object(); }

}  // namespace

// --- Stats -----------------------------------------------------------------

json StatsToJson(const Stats& s) {
  return {{"mean", s.mean}, {"min", s.min}, {"max", s.max},
          {"std", s.std},   {"cov", s.cov}, {"n", s.n}};
}

Result<Stats> StatsFromJson(const json& j, const jsonio::Source& src) {
  Stats s;
  Fields f(j, src);
  f.Req("mean", &s.mean);
  f.Req("min", &s.min);
  f.Req("max", &s.max);
  f.Req("std", &s.std);
  f.Req("cov", &s.cov);
  f.Req("n", &s.n);
  if (!f.ok()) return f.error();
  return s;
}

// --- SideResult --------------------------------------------------------------

json View2D::ToJson() const {
  json j = Base(extra);
  j["view"] = view;
  j["image"] = image;
  if (!mask.empty()) j["mask"] = mask;
  j["ok"] = ok;
  if (!error.empty()) j["error"] = error;
  if (!image_problem.empty()) j["image_problem"] = image_problem;
  Put(j, "commanded_angle_deg", commanded_angle_deg);
  Put(j, "measured_angle_deg", measured_angle_deg);
  Put(j, "mask_area_fraction", mask_area_fraction);
  Put(j, "mask_frame_px", mask_frame_px);
  if (ok) {
    j["l_max_px"] = l_max_px;
    j["l_min_px"] = l_min_px;
    j["fer_2d"] = fer_2d;
    j["area_px"] = area_px;
    j["perimeter_px"] = perimeter_px;
    j["circularity"] = circularity;
    j["l_max_angle_deg"] = l_max_angle_deg;
  }
  Put(j, "timing_ms", timing_ms);
  return j;
}

Result<View2D> View2D::FromJson(const json& j, const jsonio::Source& src) {
  View2D v;
  Fields f(j, src);
  f.Req("view", &v.view);
  f.Opt("image", &v.image);
  f.Opt("mask", &v.mask);
  f.Req("ok", &v.ok);
  f.Opt("error", &v.error);
  f.Opt("image_problem", &v.image_problem);
  f.Opt("commanded_angle_deg", &v.commanded_angle_deg);
  f.Opt("measured_angle_deg", &v.measured_angle_deg);
  f.Opt("mask_area_fraction", &v.mask_area_fraction);
  f.Opt("mask_frame_px", &v.mask_frame_px);
  // A view with figures has all of them; one without has none to read.
  auto fig = [&](const char* key, double* out) { v.ok ? f.Req(key, out) : f.Opt(key, out); };
  fig("l_max_px", &v.l_max_px);
  fig("l_min_px", &v.l_min_px);
  fig("fer_2d", &v.fer_2d);
  fig("area_px", &v.area_px);
  fig("perimeter_px", &v.perimeter_px);
  fig("circularity", &v.circularity);
  f.Opt("l_max_angle_deg", &v.l_max_angle_deg);
  f.Opt("timing_ms", &v.timing_ms);
  if (f.ok() && v.ok && v.mask.empty()) f.Fail(src.Bad("a view with figures names no mask"));
  if (!f.ok()) return f.error();
  v.extra = f.Extra();
  return v;
}

json SideResult::ToJson() const {
  json j = Base(extra);
  j["schema"] = kRecordSchema;
  j["sample_id"] = sample_id;
  j["side"] = side;
  json jv = json::array();
  for (const View2D& v : views) jv.push_back(v.ToJson());
  j["views"] = std::move(jv);
  j["views_total"] = views_total;
  j["views_ok"] = views_ok;
  j["mask_problems"] = mask_problems;
  j["image_problems"] = image_problems;
  json js = json::object();
  for (const auto& [k, s] : stats) js[k] = StatsToJson(s);
  j["stats"] = std::move(js);
  j["std_kind"] = std_kind;
  j["mask_method"] = mask_method;
  j["mask_empty_turntable"] = mask_empty_turntable ? json(*mask_empty_turntable) : json(nullptr);
  j["mask_empty_turntable_views"] = mask_empty_turntable_views;
  if (!mask_empty_turntable_problems.empty())
    j["mask_empty_turntable_problems"] = mask_empty_turntable_problems;
  j["timing_ms"] = timing_ms;
  return j;
}

Result<SideResult> SideResult::FromJson(const json& j, const jsonio::Source& src) {
  SideResult r;
  Fields f(j, src);
  f.Schema(kRecordSchema);
  f.Opt("sample_id", &r.sample_id);
  f.Req("side", &r.side);
  f.List("views", &r.views, View2D::FromJson);
  f.Req("views_total", &r.views_total);
  f.Req("views_ok", &r.views_ok);
  f.Opt("mask_problems", &r.mask_problems);
  f.Opt("image_problems", &r.image_problems);
  json stats = json::object();
  f.Raw("stats", &stats);
  if (f.ok() && !stats.is_object()) f.Fail(src.Bad("\"stats\" is not an object"));
  if (f.ok()) {
    for (const auto& [k, v] : stats.items()) {
      auto s =
          StatsFromJson(v, jsonio::Source{src.what + " (stats " + k + ")", src.path, src.redo});
      if (!s) {
        f.Fail(s.error());
        break;
      }
      r.stats[k] = *s;
    }
  }
  f.Opt("std_kind", &r.std_kind);
  f.Opt("mask_method", &r.mask_method);
  f.Opt("mask_empty_turntable", &r.mask_empty_turntable);
  f.Opt("mask_empty_turntable_views", &r.mask_empty_turntable_views);
  f.Strings("mask_empty_turntable_problems", &r.mask_empty_turntable_problems);
  f.Opt("timing_ms", &r.timing_ms);
  if (f.ok() && r.side < 1) f.Fail(src.Bad("\"side\" is below 1"));
  if (!f.ok()) return f.error();
  r.extra = f.Extra();
  return r;
}

// --- PosesRecord -------------------------------------------------------------

json PosedViewRecord::ToJson() const {
  json j = Base(extra);
  j["view"] = view;
  j["image"] = image;
  j["mask"] = mask;
  j["angle_deg"] = angle_deg;
  Put(j, "measured_angle_deg", measured_angle_deg);
  Put(j, "angle_correction_deg", angle_correction_deg);
  Put(j, "ba_adjusted", ba_adjusted);
  j["cam_from_table_4x4"] = PoseToJson(cam_from_table);
  return j;
}

Result<PosedViewRecord> PosedViewRecord::FromJson(const json& j, const jsonio::Source& src) {
  PosedViewRecord v;
  Fields f(j, src);
  f.Req("view", &v.view);
  f.Req("image", &v.image);
  f.Req("mask", &v.mask);
  f.Req("angle_deg", &v.angle_deg);
  f.Opt("measured_angle_deg", &v.measured_angle_deg);
  f.Opt("angle_correction_deg", &v.angle_correction_deg);
  f.Opt("ba_adjusted", &v.ba_adjusted);
  PoseReq(f, j, "cam_from_table_4x4", &v.cam_from_table);
  if (!f.ok()) return f.error();
  v.extra = f.Extra();
  return v;
}

json PosesRecord::ToJson() const {
  json j = Base(extra);
  j["schema"] = kRecordSchema;
  j["side"] = side;
  j["method"] = method;
  j["method_detail"] = method_detail;
  json jv = json::array();
  for (const PosedViewRecord& v : views) jv.push_back(v.ToJson());
  j["views"] = std::move(jv);
  j["stage_seconds"] = stage_seconds;
  if (!bundle_adjustment.is_null()) j["bundle_adjustment"] = bundle_adjustment;
  if (!sfm.is_null()) j["sfm"] = sfm;
  if (!scale.is_null()) j["scale"] = scale;
  if (!calibration.is_null()) j["calibration"] = calibration;
  if (!unregistered_views.is_null()) j["unregistered_views"] = unregistered_views;
  return j;
}

Result<PosesRecord> PosesRecord::FromJson(const json& j, const jsonio::Source& src) {
  PosesRecord r;
  Fields f(j, src);
  f.Schema(kRecordSchema);
  f.Req("side", &r.side);
  f.Req("method", &r.method);
  f.Opt("method_detail", &r.method_detail);
  f.List("views", &r.views, PosedViewRecord::FromJson);
  f.Opt("stage_seconds", &r.stage_seconds);
  // The method's own blocks: objects when present, null when absent.
  for (auto [k, out] : {std::pair<const char*, json*>{"bundle_adjustment", &r.bundle_adjustment},
                        {"sfm", &r.sfm},
                        {"scale", &r.scale},
                        {"calibration", &r.calibration}}) {
    f.Raw(k, out);
    if (f.ok() && !out->is_null() && !out->is_object())
      f.Fail(src.Bad(std::string("\"") + k + "\" is not an object"));
  }
  f.Raw("unregistered_views", &r.unregistered_views);
  if (f.ok() && r.IsSfm() && !r.calibration.is_object())
    f.Fail(src.Bad("an SfM poses record without the camera it posed with (\"calibration\")"));
  if (!f.ok()) return f.error();
  r.extra = f.Extra();
  return r;
}

// --- StitchRecord ------------------------------------------------------------

json SourceEstimate::ToJson() const {
  json j = Base(detail);
  j["valid"] = valid;
  if (moving_to_reference) j["moving_to_reference_4x4"] = PoseToJson(*moving_to_reference);
  return j;
}

Result<SourceEstimate> SourceEstimate::FromJson(const json& j, const jsonio::Source& src) {
  SourceEstimate e;
  Fields f(j, src);
  f.Req("valid", &e.valid);
  constexpr const char* kT = "moving_to_reference_4x4";
  if (j.is_object() && j.contains(kT)) {
    Pose T = Pose::Identity();
    PoseReq(f, j, kT, &T);
    if (f.ok()) e.moving_to_reference = T;
  } else if (f.ok() && e.valid) {
    f.Fail(src.Bad(std::string("a valid estimate without \"") + kT + "\""));
  }
  if (!f.ok()) return f.error();
  e.detail = f.Extra();
  return e;
}

bool SideStitch::SilhouettesAvailable() const {
  return silhouettes.is_object() && silhouettes.value("available", false);
}

double SideStitch::SilhouetteDeficit() const {
  if (!SilhouettesAvailable()) return 0;
  const auto it = silhouettes.find("deficit");
  return it != silhouettes.end() && it->is_number() ? it->get<double>() : 0.0;
}

json SideStitch::ToJson() const {
  json j = Base(extra);
  j["side"] = side;
  j["onto_side"] = onto_side;
  j["source"] = source;
  j["consistent"] = consistent;
  j["warning"] = warning;
  if (markers) j["markers"] = markers->ToJson();
  if (features) j["features"] = features->ToJson();
  j["silhouettes"] = silhouettes;
  return j;
}

Result<SideStitch> SideStitch::FromJson(const json& j, const jsonio::Source& src) {
  SideStitch s;
  Fields f(j, src);
  f.Req("side", &s.side);
  f.Opt("onto_side", &s.onto_side);
  f.Req("source", &s.source);
  f.Opt("consistent", &s.consistent);
  f.Opt("warning", &s.warning);
  for (const char* k : {"markers", "features"}) {
    json e;
    f.Raw(k, &e);
    if (!f.ok() || e.is_null()) continue;
    auto est = SourceEstimate::FromJson(
        e, jsonio::Source{src.what + " (" + k + " estimate)", src.path, src.redo});
    if (!est) {
      f.Fail(est.error());
      continue;
    }
    (std::string(k) == "markers" ? s.markers : s.features) = std::move(*est);
  }
  f.Raw("silhouettes", &s.silhouettes);
  if (f.ok() && !s.silhouettes.is_object()) f.Fail(src.Bad("\"silhouettes\" is not an object"));
  if (!f.ok()) return f.error();
  s.extra = f.Extra();
  return s;
}

json StitchRecord::ToJson() const {
  json j = Base(extra);
  j["schema"] = kRecordSchema;
  j["method"] = method;
  json sides = json::array();
  for (const auto& [side, T] : table_from_object)
    sides.push_back({{"side", side}, {"table_from_object_4x4", PoseToJson(T)}});
  j["sides"] = std::move(sides);
  json st = json::array();
  for (const SideStitch& s : stitches) st.push_back(s.ToJson());
  j["stitches"] = std::move(st);
  Put(j, "rms_mm", rms_mm);
  Put(j, "max_mm", max_mm);
  Put(j, "silhouette_deficit", silhouette_deficit);
  Put(j, "scale_residual_mm", scale_residual_mm);
  Put(j, "scale_reference", scale_reference);
  j["stage_seconds"] = stage_seconds;
  j["per_side"] = per_side;
  return j;
}

Result<StitchRecord> StitchRecord::FromJson(const json& j, const jsonio::Source& src) {
  StitchRecord r;
  Fields f(j, src);
  f.Schema(kRecordSchema);
  f.Req("method", &r.method);
  struct SideT {
    int side = 0;
    Pose T;
  };
  std::vector<SideT> sides;
  f.List("sides", &sides, [](const json& e, const jsonio::Source& s) -> Result<SideT> {
    SideT out;
    Fields g(e, s);
    g.Req("side", &out.side);
    PoseReq(g, e, "table_from_object_4x4", &out.T);
    if (!g.ok()) return g.error();
    return out;
  });
  for (const SideT& s : sides) {
    if (r.table_from_object.count(s.side))
      f.Fail(src.Bad("side " + std::to_string(s.side) + " is listed twice"));
    r.table_from_object[s.side] = s.T;
  }
  if (f.ok() && r.table_from_object.empty()) f.Fail(src.Bad("it lists no side"));
  f.List("stitches", &r.stitches, SideStitch::FromJson);
  f.Opt("rms_mm", &r.rms_mm);
  f.Opt("max_mm", &r.max_mm);
  f.Opt("silhouette_deficit", &r.silhouette_deficit);
  f.Opt("scale_residual_mm", &r.scale_residual_mm);
  f.Opt("scale_reference", &r.scale_reference);
  f.Opt("stage_seconds", &r.stage_seconds);
  f.Raw("per_side", &r.per_side);
  if (!f.ok()) return f.error();
  r.extra = f.Extra();
  return r;
}

// --- SurfaceRecord -----------------------------------------------------------

namespace {

json NoteToJson(const ViewNote& n) {
  json j = Base(n.extra);
  j["side"] = n.side;
  j["view"] = n.view;
  j["reason"] = n.reason;
  return j;
}

Result<ViewNote> NoteFromJson(const json& j, const jsonio::Source& src) {
  ViewNote n;
  Fields f(j, src);
  f.Req("side", &n.side);
  f.Req("view", &n.view);
  f.Opt("reason", &n.reason);
  if (!f.ok()) return f.error();
  n.extra = f.Extra();
  return n;
}

Result<ViewIoU> IoUFromJson(const json& j, const jsonio::Source& src) {
  ViewIoU v;
  Fields f(j, src);
  f.Req("side", &v.side);
  f.Req("view", &v.view);
  f.Req("iou", &v.iou);
  f.Opt("outline_loss", &v.outline_loss);
  if (!f.ok()) return f.error();
  return v;
}

Result<std::map<std::string, std::string>> StringMap(const json& j, const char* key,
                                                     const jsonio::Source& src) {
  auto o = jsonio::ObjectOr(j, key, src);
  if (!o) return o.error();
  std::map<std::string, std::string> m;
  for (const auto& [k, v] : o->items()) {
    if (!v.is_string()) return src.Bad(std::string("\"") + key + "\"." + k + " is not a string");
    m[k] = v.get<std::string>();
  }
  return m;
}

Result<std::map<std::string, double>> NumberMap(const json& j, const char* key,
                                                const jsonio::Source& src) {
  auto o = jsonio::ObjectOr(j, key, src);
  if (!o) return o.error();
  std::map<std::string, double> m;
  for (const auto& [k, v] : o->items()) {
    if (!v.is_number()) return src.Bad(std::string("\"") + key + "\"." + k + " is not a number");
    m[k] = v.get<double>();
  }
  return m;
}

}  // namespace

json SurfaceRecord::SilhouetteIoUJson() const {
  json iou = json::array();
  for (const ViewIoU& v : silhouette_iou) {
    json e = {{"side", v.side}, {"view", v.view}, {"iou", v.iou}};
    if (v.outline_loss) e["outline_loss"] = *v.outline_loss;
    iou.push_back(std::move(e));
  }
  return iou;
}

json SurfaceRecord::ToJson() const {
  json j = Base(extra);
  j["schema"] = kRecordSchema;
  j["method"] = method;
  j["method_detail"] = method_detail;
  j["vertices"] = vertices;
  j["faces"] = faces;
  j["views"] = views;
  j["voxel_mm"] = voxel_mm;
  j["files"] = files;
  j["silhouette_iou"] = SilhouetteIoUJson();
  json out = json::array(), dis = json::array();
  for (const ViewNote& n : views_left_out) out.push_back(NoteToJson(n));
  for (const ViewNote& n : views_disagreeing) dis.push_back(NoteToJson(n));
  j["views_left_out"] = std::move(out);
  j["views_disagreeing"] = std::move(dis);
  j["stage_seconds"] = stage_seconds;
  j["timings_s"] = timings_s;
  j["photo_refine"] = photo_refine;
  j["consistency"] = consistency;
  return j;
}

Result<SurfaceRecord> SurfaceRecord::FromJson(const json& j, const jsonio::Source& src) {
  SurfaceRecord r;
  Fields f(j, src);
  f.Schema(kRecordSchema);
  f.Req("method", &r.method);
  f.Opt("method_detail", &r.method_detail);
  f.Opt("vertices", &r.vertices);
  f.Opt("faces", &r.faces);
  f.Opt("views", &r.views);
  f.Opt("voxel_mm", &r.voxel_mm);
  f.Use("files", StringMap(j, "files", src), &r.files);
  f.List("silhouette_iou", &r.silhouette_iou, IoUFromJson);
  f.List("views_left_out", &r.views_left_out, NoteFromJson);
  f.List("views_disagreeing", &r.views_disagreeing, NoteFromJson);
  f.Opt("stage_seconds", &r.stage_seconds);
  f.Use("timings_s", NumberMap(j, "timings_s", src), &r.timings_s);
  f.Raw("photo_refine", &r.photo_refine);
  f.Raw("consistency", &r.consistency);
  if (!f.ok()) return f.error();
  r.extra = f.Extra();
  return r;
}

// --- Morphology --------------------------------------------------------------

Status Morphology::Read3D(const jsonio::Source& src) {
  jsonio::Source s = src;
  s.what += " (morphology_3d)";
  Fields f(morphology_3d, s);
  f.Req("volume_mm3", &volume_mm3);
  f.Req("surface_area_mm2", &surface_area_mm2);
  f.Req("a_mm", &a_mm);
  f.Req("b_mm", &b_mm);
  f.Req("c_mm", &c_mm);
  f.Req("fer_3d", &fer_3d);
  f.Req("sphericity", &sphericity);
  f.Opt("watertight", &watertight);
  if (!f.ok()) return f.error();
  return OkStatus();
}

json Morphology::ToJson() const {
  json j = Base(extra);
  j["schema"] = kRecordSchema;
  j["format"] = kFormat;
  j["sample_id"] = sample_id;
  j["created_utc"] = created_utc;
  j["units"] = units;
  j["methods"] = methods;
  json m3 = morphology_3d.is_object() ? morphology_3d : json::object();
  m3["volume_mm3"] = volume_mm3;
  m3["surface_area_mm2"] = surface_area_mm2;
  m3["a_mm"] = a_mm;
  m3["b_mm"] = b_mm;
  m3["c_mm"] = c_mm;
  m3["fer_3d"] = fer_3d;
  m3["sphericity"] = sphericity;
  m3["watertight"] = watertight;
  j["morphology_3d"] = std::move(m3);
  json poses_j = json::array();
  for (const PosesSummary& p : poses) {
    json e = p.figures.is_object() ? p.figures : json::object();
    e["side"] = p.side;
    e["method"] = p.method;
    poses_j.push_back(std::move(e));
  }
  j["poses"] = std::move(poses_j);
  json v2 = json::array();
  for (const MorphView2D& v : views_2d) {
    json e = {{"side", v.side}, {"view", v.view}};
    Put(e, "angle_deg", v.angle_deg);
    e.update({{"fer_2d", v.fer_2d},
              {"circularity", v.circularity},
              {"l_max_px", v.l_max_px},
              {"l_min_px", v.l_min_px},
              {"area_px", v.area_px},
              {"perimeter_px", v.perimeter_px},
              {"mm_per_px_at_rock", v.mm_per_px_at_rock},
              {"l_max_mm", v.l_max_mm},
              {"l_min_mm", v.l_min_mm}});
    v2.push_back(std::move(e));
  }
  j["views_2d"] = std::move(v2);
  j["stats_2d"] = stats_2d;
  j["comparison_2d_3d"] = comparison_2d_3d;
  json q = quality.is_object() ? quality : json::object();
  q["confident"] = confident;
  j["quality"] = std::move(q);
  j["warnings"] = warnings;
  j["timings_s"] = timings_s;
  j["files"] = files;
  if (software.is_object() && !software.empty()) j["software"] = software;
  return j;
}

Result<Morphology> Morphology::FromJson(const json& j, const jsonio::Source& src) {
  Morphology m;
  Fields f(j, src);
  f.Schema(kRecordSchema);
  std::string format;
  f.Req("format", &format);
  if (f.ok() && format != kFormat) f.Fail(src.Bad("format \"" + format + "\" is not " + kFormat));
  f.Opt("sample_id", &m.sample_id);
  f.Opt("created_utc", &m.created_utc);
  f.Opt("units", &m.units);
  f.Use("methods", StringMap(j, "methods", src), &m.methods);
  f.Raw("morphology_3d", &m.morphology_3d);
  if (f.ok() && !m.morphology_3d.is_object())
    f.Fail(src.Bad("\"morphology_3d\" is missing or not an object"));
  if (f.ok()) {
    if (Status s = m.Read3D(src); !s) f.Fail(s.error());
  }
  f.List("poses", &m.poses, [](const json& e, const jsonio::Source& s) -> Result<PosesSummary> {
    PosesSummary p;
    Fields g(e, s);
    g.Req("side", &p.side);
    g.Opt("method", &p.method);
    if (!g.ok()) return g.error();
    p.figures = g.Extra();
    return p;
  });
  f.List("views_2d", &m.views_2d,
         [](const json& e, const jsonio::Source& s) -> Result<MorphView2D> {
           MorphView2D v;
           Fields g(e, s);
           g.Req("side", &v.side);
           g.Req("view", &v.view);
           g.Opt("angle_deg", &v.angle_deg);
           g.Req("fer_2d", &v.fer_2d);
           g.Req("circularity", &v.circularity);
           g.Req("l_max_px", &v.l_max_px);
           g.Req("l_min_px", &v.l_min_px);
           g.Opt("area_px", &v.area_px);
           g.Opt("perimeter_px", &v.perimeter_px);
           g.Opt("mm_per_px_at_rock", &v.mm_per_px_at_rock);
           g.Opt("l_max_mm", &v.l_max_mm);
           g.Opt("l_min_mm", &v.l_min_mm);
           if (!g.ok()) return g.error();
           return v;
         });
  f.Raw("stats_2d", &m.stats_2d);
  f.Raw("comparison_2d_3d", &m.comparison_2d_3d);
  f.Raw("quality", &m.quality);
  if (f.ok() && !m.quality.is_object()) f.Fail(src.Bad("\"quality\" is not an object"));
  if (f.ok()) {
    auto c = jsonio::BoolOr(m.quality, "confident", false, src);
    if (!c) f.Fail(c.error());
    if (f.ok()) m.confident = *c;
  }
  f.Strings("warnings", &m.warnings);
  f.Raw("timings_s", &m.timings_s);
  f.Use("files", StringMap(j, "files", src), &m.files);
  f.Raw("software", &m.software);
  if (!f.ok()) return f.error();
  if (!m.software.is_object()) m.software = json::object();
  m.extra = f.Extra();
  return m;
}

}  // namespace aggscan::records
