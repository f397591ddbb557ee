#include "pipeline/stitch/stitch_stage.h"

#include <atomic>
#include <chrono>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <thread>

#include "common/clock.h"
#include "pipeline/core/geometry.h"
#include "pipeline/core/image_io.h"
#include "pipeline/core/parallel_for.h"
#include "pipeline/markers/aruco_scale.h"
#include "pipeline/markers/markers.h"
#include "pipeline/stitch/stitch.h"

namespace aggscan {

using nlohmann::json;

namespace {

json Vec(const Eigen::Vector3d& p) { return json::array({p.x(), p.y(), p.z()}); }

records::SourceEstimate EstimateRecord(const StitchEstimate& e) {
  records::SourceEstimate r;
  r.valid = e.valid;
  if (e.valid) r.moving_to_reference = ToPose(e.T);
  r.detail = {{"pairs", e.pairs},   {"inliers", e.inliers}, {"rms_mm", e.rms_mm},
              {"max_mm", e.max_mm}, {"points", e.points},   {"note", e.note}};
  if (e.rotation_sigma_deg > 0) r.detail["rotation_sigma_deg"] = e.rotation_sigma_deg;
  if (!e.guided_from.empty()) {
    r.detail["guided_from"] = e.guided_from;
    r.detail["unguided_inliers"] = e.unguided_inliers;
  }
  return r;
}

json MarkersJson(const SideMarkers& m) {
  json pts = json::array();
  for (const MarkerPoint& p : m.points) {
    json jp = {{"name", p.Name()},
               {"located", p.located},
               {"views_seen", p.views_seen},
               {"views_used", p.views_used}};
    if (p.located) {
      jp["position_mm"] = Vec(p.position);
      jp["rms_px"] = p.rms_px;
      jp["max_px"] = p.max_px;
    } else {
      jp["problem"] = p.problem;
    }
    pts.push_back(jp);
  }
  return {{"located", m.located()}, {"points", pts}};
}

json LabelsJson(const Result<LabelScale>& ls) {
  if (!ls) return {{"ok", false}, {"problem", ls.error().message}};
  json labels = json::array();
  for (const LabelPoint& l : ls->labels) {
    json jl = {{"color", l.color},
               {"located", l.located},
               {"views_seen", l.views_seen},
               {"views_used", l.views_used}};
    if (l.located) {
      jl["position_mm"] = Vec(l.position);
      jl["rms_px"] = l.rms_px;
    } else {
      jl["problem"] = l.problem;
    }
    labels.push_back(jl);
  }
  return {{"ok", true},
          {"labels_used", ls->labels_used},
          {"scale", ls->scale},
          {"pair_rms_mm", ls->pair_rms_mm},
          {"pair_max_mm", ls->pair_max_mm},
          {"align_rms_mm", ls->align_rms_mm},
          {"align_max_mm", ls->align_max_mm},
          {"labels", labels}};
}

json ArucoJson(const Result<ArucoScale>& as, const RigConfig& rig, int detect_failures,
               double detect_ms_per_view) {
  json j = {{"configured", true},
            {"dictionary", rig.aruco_dictionary},
            {"size_mm", rig.aruco_size_mm},
            {"markers_configured", rig.aruco_markers.size()},
            {"detection_failures", detect_failures},
            {"detect_ms_per_view", detect_ms_per_view}};
  if (!as) {
    j["ok"] = false;
    j["problem"] = as.error().message;
    return j;
  }
  json markers = json::array();
  for (const ArucoMarkerPoint& m : as->markers) {
    json jm = {{"id", m.id},
               {"located", m.located},
               {"views_seen", m.views_seen},
               {"views_used", m.views_used}};
    if (m.located) {
      jm["center_mm"] = Vec(m.center);
      jm["rms_px"] = m.rms_px;
      jm["max_px"] = m.max_px;
    } else {
      jm["problem"] = m.problem;
    }
    markers.push_back(jm);
  }
  j["ok"] = true;
  j["markers_used"] = as->markers_used;
  j["views_with_markers"] = as->views_with_markers;
  j["scale"] = as->scale;
  j["measured_over_configured"] = as->scale > 0 ? 1.0 / as->scale : 0.0;
  j["lengths"] = as->lengths;
  j["rms_mm"] = as->rms_mm;
  j["max_mm"] = as->max_mm;
  j["edge_rms_mm"] = as->edge_rms_mm;
  j["edge_max_mm"] = as->edge_max_mm;
  j["centre_pairs"] = as->centre_pairs;
  j["centre_rms_mm"] = as->centre_rms_mm;
  j["centre_max_mm"] = as->centre_max_mm;
  j["align_rms_mm"] = as->align_rms_mm;
  j["align_max_mm"] = as->align_max_mm;
  j["markers"] = markers;
  return j;
}

// Everything one side contributes to the stitch.
struct SideEvidence {
  SideMarkers markers;
  FeatureCloud cloud;
  SilhouetteSideInput silhouettes;    // the distinct viewpoints' masks and poses
  std::vector<int> silhouette_views;  // their view numbers
  json record;
};

Result<SideEvidence> GatherSide(const StitchStageInput& in, int side,
                                const std::vector<SampleView>& views, bool want_features) {
  const CameraModel& cam = in.calibration->camera;
  std::vector<geom::Rigid3> poses;
  poses.reserve(views.size());
  for (const SampleView& v : views) poses.push_back(ToRigid3(v.cam_from_table));
  const std::vector<int> distinct = want_features ? DistinctViewpoints(poses) : std::vector<int>{};
  std::vector<bool> is_distinct(views.size(), false);
  for (int i : distinct) is_distinct[static_cast<size_t>(i)] = true;

  const EvidenceOptions eo = StitchEvidenceOptions(in, 0);
  // The cache's evidence is used when it was found with this stage's
  // parameters (its window margin is the surface stage's business).
  ViewEvidenceCache* cache = nullptr;
  if (in.evidence && in.evidence->Serves(eo)) cache = in.evidence;
  std::vector<ViewMarkers> vm(views.size());
  std::vector<ViewFeatures> vf(views.size());
  const bool want_aruco = eo.want_aruco();
  std::vector<ArucoViewDetections> va(views.size());
  // Views are independent: two threads (the rig's two cores) share them.
  // Each view's outputs go to its own slot; sums are per thread.
  struct ViewOut {
    cv::Mat mask;  // kept for the silhouettes when the view is a distinct viewpoint
    bool marker_failure = false, aruco_failure = false;
    bool decoded = false;  // false: everything came from the evidence cache
    std::optional<Error> error;
  };
  std::vector<ViewOut> out(views.size());
  struct Sums {
    TimeNs decode = 0, features = 0;
    double markers_s = 0, aruco_s = 0;
  };
  Sums sums[kWorkerThreads];
  auto work = [&](size_t i, int thread) {
    Sums* t = &sums[thread];
    ViewOut& o = out[i];
    const TimeNs t_decode = MonotonicNs();
    std::shared_ptr<const ViewEvidence> e = cache ? cache->Find(views[i].image) : nullptr;
    // The photo is decoded unless the cache holds its markers and, for a
    // distinct viewpoint, the rock's window of it for the features.
    cv::Mat bgr, mask;
    if (!e || (is_distinct[i] && e->bgr.empty())) {
      o.decoded = true;
      auto loaded = LoadImage(views[i].image, ImageMode::kColor);
      if (!loaded) {
        o.error = MakeError(
            ErrorClass::kCorrupt,
            "stitch stage: " + loaded.error().message + "; the sample's photos must not change",
            loaded.error().detail);
        return;
      }
      bgr = std::move(*loaded);
      auto loaded_mask = LoadImage(views[i].mask, ImageMode::kGray);
      if (loaded_mask) mask = std::move(*loaded_mask);
      if (mask.empty() || mask.size() != bgr.size()) {
        o.error = MakeError(ErrorClass::kCorrupt,
                            "stitch stage: mask " + views[i].mask +
                                " is missing, unreadable or not the photo's size; delete the "
                                "side's results to compute the masks again");
        return;
      }
    }
    t->decode += MonotonicNs() - t_decode;
    if (!e) {
      if (cache) {
        cache->Add(views[i].image, bgr, mask);
        e = cache->Find(views[i].image);
      } else {
        e = std::make_shared<const ViewEvidence>(GatherViewEvidence(bgr, mask, eo, false));
      }
    }
    t->markers_s += e->markers_s;
    t->aruco_s += e->aruco_s;
    if (e->markers_found) {
      vm[i] = e->markers;
    } else {
      o.marker_failure = true;
    }
    if (is_distinct[i]) {
      const TimeNs t_features = MonotonicNs();
      if (!bgr.empty()) {
        vf[i] = ExtractRockFeatures(bgr, mask);
        o.mask = mask;
      } else {
        // The window holds the rock and a margin wider than SIFT's: the same
        // keypoints as from the whole frame.
        vf[i] = ExtractRockFeatures(e->bgr, e->mask, {}, e->window.tl());
        o.mask = e->FullMask();
      }
      t->features += MonotonicNs() - t_features;
    }
    if (want_aruco) {
      if (e->aruco_found) {
        va[i] = e->aruco;
      } else {
        o.aruco_failure = true;
      }
    }
  };
  ParallelFor(views.size(), kWorkerThreads, work);
  int aruco_failures = 0, detect_failures = 0, decoded = 0;
  SilhouetteSideInput sil;
  std::vector<int> sil_views;
  for (size_t i = 0; i < views.size(); ++i) {
    if (out[i].error) return *out[i].error;
    decoded += out[i].decoded ? 1 : 0;
    detect_failures += out[i].marker_failure ? 1 : 0;
    aruco_failures += out[i].aruco_failure ? 1 : 0;
    if (is_distinct[i]) {
      sil.masks.push_back(out[i].mask);
      sil.cam_from_table.push_back(poses[i]);
      sil_views.push_back(views[i].view);
    }
  }
  TimeNs decode_ns = 0, features_ns = 0;
  double markers_s = 0, aruco_s = 0;
  for (const Sums& t : sums) {
    decode_ns += t.decode;
    markers_s += t.markers_s;
    features_ns += t.features;
    aruco_s += t.aruco_s;
  }
  SideEvidence ev;
  ev.silhouettes = std::move(sil);
  ev.silhouette_views = std::move(sil_views);
  ev.markers = LocateObjectMarkers(vm, poses, cam, in.object_colors);
  const Result<LabelScale> labels = LocateLabels(vm, poses, cam, in.rig);
  const TimeNs t_cloud = MonotonicNs();
  if (want_features) ev.cloud = BuildFeatureCloud(vf, poses, cam);
  const TimeNs cloud_ns = MonotonicNs() - t_cloud;
  ev.record = {{"side", side},
               {"views", views.size()},
               {"marker_detection_failures", detect_failures},
               {"photos_decoded", decoded},
               {"object_markers", MarkersJson(ev.markers)},
               {"background_labels", LabelsJson(labels)}};
  if (want_aruco) {
    const double ms = views.empty() ? 0.0 : aruco_s * 1e3 / static_cast<double>(views.size());
    ev.record["aruco_scale"] =
        ArucoJson(LocateArucoMarkers(va, poses, cam, in.rig), in.rig, aruco_failures, ms);
  } else {
    ev.record["aruco_scale"] = {{"configured", false}, {"ok", false}};
  }
  // decode: this stage's own; markers and aruco: the detections' cost,
  // wherever they ran (an earlier stage may have found them: evidence_cached).
  ev.record["timings_s"] = {{"decode", static_cast<double>(decode_ns) / 1e9},
                            {"markers", markers_s},
                            {"features", static_cast<double>(features_ns) / 1e9},
                            {"feature_matching", static_cast<double>(cloud_ns) / 1e9},
                            {"aruco", aruco_s}};
  if (want_features) {
    ev.record["feature_cloud"] = {{"viewpoints", ev.cloud.views},
                                  {"view_pairs", ev.cloud.view_pairs},
                                  {"points", ev.cloud.points.size()}};
  }
  return ev;
}

}  // namespace

EvidenceOptions StitchEvidenceOptions(const StitchStageInput& in, int window_margin) {
  EvidenceOptions o;
  o.camera = in.calibration->camera;
  for (const RigMarker& m : in.rig.markers) o.label_colors.push_back(m.color);
  o.object_colors = in.object_colors;
  o.markers.expected_label_side_px = ExpectedLabelSidePx(*in.calibration, in.rig);
  o.rig = in.rig;
  o.window_margin = window_margin;
  return o;
}

Result<records::StitchRecord> RunStitchStage(const StitchStageInput& in) {
  const auto t0 = std::chrono::steady_clock::now();
  if (in.views.empty()) return MakeError(ErrorClass::kInvalidArgument, "stitch stage: no sides");
  if (!in.calibration)
    return MakeError(ErrorClass::kInvalidArgument, "stitch stage: no calibration");
  const bool several = in.views.size() > 1;

  std::map<int, SideEvidence> sides;
  json side_records = json::array();
  std::vector<double> scale_residuals;
  bool by_labels = false, by_aruco = false;
  for (const auto& [side, views] : in.views) {
    auto ev = GatherSide(in, side, views, several);
    if (!ev) return ev.error();
    const json& lab = ev->record["background_labels"];
    if (lab.value("ok", false)) {
      scale_residuals.push_back(lab.value("pair_rms_mm", 0.0));
      by_labels = true;
    }
    const json& aru = ev->record["aruco_scale"];
    if (aru.value("ok", false)) {
      scale_residuals.push_back(aru.value("rms_mm", 0.0));
      by_aruco = true;
    }
    side_records.push_back(ev->record);
    sides.emplace(side, std::move(*ev));
  }
  records::StitchRecord rec;
  rec.per_side = side_records;
  // The scale check: the worst RMS length residual over the sides and the
  // references each located (colour label distances, ArUco marker sides,
  // diagonals and centre distances); the calibrated rig measures in mm, the
  // references confirm it. Null when no side located either.
  if (!scale_residuals.empty()) {
    rec.scale_residual_mm = *std::max_element(scale_residuals.begin(), scale_residuals.end());
    rec.scale_reference = by_labels && by_aruco ? "labels+aruco" : (by_labels ? "labels" : "aruco");
  }

  const int ref = in.views.begin()->first;
  rec.table_from_object[ref] = Pose::Identity();
  if (!several) {
    rec.method = "single-side";
  } else {
    double worst_rms = 0, worst_max = 0, worst_deficit = -1;
    bool residual_known = true;
    std::string method;
    for (const auto& [side, ev] : sides) {
      if (side == ref) continue;
      StitchOptions so;
      so.reference_side = ref;
      so.moving_side = side;
      const SideEvidence& r = sides.at(ref);
      // Silhouette coherence needs no markers or features: it refines and
      // checks their estimates, and rescues a stitch each is too weak for.
      const auto ts = std::chrono::steady_clock::now();
      auto sil = SilhouetteStitcher::Create(r.silhouettes, ev.silhouettes, in.calibration->camera);
      json sil_record = {
          {"available", sil.ok()},
          {"prepare_s",
           std::chrono::duration<double>(std::chrono::steady_clock::now() - ts).count()}};
      if (!sil) sil_record["problem"] = sil.error().message;
      auto st = StitchSides(r.markers, ev.markers, &r.cloud, &ev.cloud, so, sil ? &*sil : nullptr);
      if (!st) {
        return MakeError(st.error().cls,
                         "stitch stage: side " + std::to_string(side) + " onto side " +
                             std::to_string(ref) + ": " + st.error().message,
                         st.error().detail);
      }
      // The residual of the estimate the chosen motion came from (none for a
      // silhouette rescue: its figure is the silhouette deficit).
      const bool from_features = st->source.rfind("features", 0) == 0;
      const bool from_markers = st->source.rfind("markers", 0) == 0;
      if (from_features || from_markers) {
        const StitchEstimate& chosen = from_features ? st->features : st->markers;
        worst_rms = std::max(worst_rms, chosen.rms_mm);
        worst_max = std::max(worst_max, chosen.max_mm);
      } else {
        residual_known = false;
      }
      // A motion the silhouettes chose (a marker estimate refined, or a
      // rescue) is polished on the finer grid (sim seeds 6, 7, 13 at
      // 2016x1512: 0.61 / 0.59 / 0.88 deg from the true flip, polished 0.15 /
      // 0.19 / 0.39 deg; seed 13's long axis -2.7 -> -1.8 %).
      json polish = {{"done", false}};
      if (sil && st->silhouettes.used) {
        const SilhouettePolish p = PolishSilhouetteStitch(*sil, r.silhouettes, ev.silhouettes,
                                                          in.calibration->camera, st->T);
        polish = {
            {"done", p.done},       {"voxel_mm", p.voxel_mm},   {"deficit_start", p.deficit_start},
            {"deficit", p.deficit}, {"moved_deg", p.moved_deg}, {"evaluations", p.evaluations},
            {"seconds", p.seconds}};
        if (!p.problem.empty()) polish["problem"] = p.problem;
        st->T = p.T;
      }
      const SilhouetteRefinement& sr = st->silhouettes;
      if (sil) {
        sil_record["polish"] = polish;
        sil_record["voxel_mm"] = sil->voxel_mm();
        sil_record["views_per_side"] = sil->views_used();
        sil_record["tried"] = sr.tried;
        sil_record["used"] = sr.used;
        sil_record["start"] = sr.start;
        sil_record["deficit_start"] = sr.deficit_start;
        sil_record["deficit"] = sr.deficit;
        sil_record["own_deficit"] = sr.own_deficit;
        sil_record["accept_above_own"] = so.silhouette_accept;
        sil_record["moved_deg"] = sr.moved_deg;
        sil_record["moved_mm"] = sr.moved_mm;
        sil_record["evaluations"] = sr.evaluations;
        sil_record["seconds"] = sr.seconds;
        sil_record["note"] = sr.note;
        // Views whose masks alone carved away rock the side's others hold.
        json left_out = json::array();
        for (int k = 0; k < 2; ++k) {
          const std::vector<int>& numbers = k == 0 ? r.silhouette_views : ev.silhouette_views;
          for (int i : sil->left_out(k)) {
            left_out.push_back({{"side", k == 0 ? ref : side},
                                {"view", i < static_cast<int>(numbers.size()) ? numbers[i] : i}});
          }
        }
        sil_record["left_out"] = left_out;
        if (sr.searched) {
          sil_record["search"] = {{"fits", sr.search_fits},
                                  {"runner_up_deficit", sr.search_runner_up},
                                  {"runner_up_deg", sr.search_runner_up_deg},
                                  {"seconds", sr.search_seconds}};
        }
        if (sr.tried) worst_deficit = std::max(worst_deficit, sr.deficit);
      }
      method = method.empty() ? st->source : (method == st->source ? method : "mixed");
      // T maps the moving side's table frame into side 1's (the object frame).
      rec.table_from_object[side] = ToPose(st->T.Inverse());
      records::SideStitch ss;
      ss.side = side;
      ss.onto_side = ref;
      ss.source = st->source;
      ss.markers = EstimateRecord(st->markers);
      ss.features = EstimateRecord(st->features);
      ss.consistent = st->consistent;
      ss.warning = st->warning;
      ss.silhouettes = sil_record;
      ss.extra = {{"cross_checked", st->cross_checked},
                  {"disagreement_deg", st->disagreement_deg},
                  {"disagreement_mm", st->disagreement_mm}};
      rec.stitches.push_back(std::move(ss));
    }
    rec.method = method;
    if (residual_known) {
      rec.rms_mm = worst_rms;
      rec.max_mm = worst_max;
    }
    if (worst_deficit >= 0) rec.silhouette_deficit = worst_deficit;
  }
  rec.stage_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return rec;
}

}  // namespace aggscan
