#include "pipeline/sfm/sfm_poses.h"

#include <chrono>
#include <cmath>
#include <cstdio>
#include <opencv2/imgcodecs.hpp>

#include "pipeline/core/geometry.h"
#include "pipeline/core/image_io.h"
#include "pipeline/markers/aruco_scale.h"
#include "pipeline/markers/markers.h"
#include "pipeline/sfm/colmap_sfm.h"
#include "store/layout.h"

namespace aggscan {

using nlohmann::json;

std::string SfmModelDirName(int side) { return "sfm/" + layout::SideDirName(side); }

namespace {

json Vec(const Eigen::Vector3d& p) { return json::array({p.x(), p.y(), p.z()}); }

std::string Fmt(const char* f, double v) {
  char b[64];
  std::snprintf(b, sizeof b, f, v);
  return b;
}

// One reference point: located in the SfM frame, configured in the table frame.
struct Reference {
  std::string name;
  Eigen::Vector3d sfm, table;
};

}  // namespace

Result<records::PosesRecord> RunSfmPoses(const SfmPosesInput& in, const SfmPosesOptions& opts) {
  const std::string side_name = layout::SideDirName(in.side);
  const std::string what = "poses stage (sfm), " + side_name + ": ";
  if (in.views.size() < 3) {
    return MakeError(ErrorClass::kCorrupt,
                     what + "only " + std::to_string(in.views.size()) +
                         " views with a rock; at least 3 are needed: re-capture the side");
  }
  const auto t0 = std::chrono::steady_clock::now();
  ColmapSfmOptions o;
  o.colmap_binary = opts.colmap_binary;
  o.workspace = in.sample_dir + "/work/" + side_name + "/sfm";
  for (const SampleView& v : in.views) {
    o.images.push_back(v.image);
    o.masks.push_back(v.mask);
    if (in.angles_measured && !in.moving_camera) o.angles_deg.push_back(v.angle_deg);
  }
  o.fixed_camera = in.fixed_camera;
  if (!in.fixed_camera) {
    o.expected_focal_px = in.expected_focal_px;
    o.hold_focal_hint =
        in.expected_focal_px.has_value();  // the worker's hint is a lens's nominal focal  // the
                                           // worker's hint is a lens's nominal focal
  }
  o.free_camera_model = opts.free_camera_model;
  o.sift.max_image_size = opts.max_image_size;
  o.crop_to_masks = opts.crop_to_masks;
  o.matching.circular_neighbours = opts.circular_neighbours;
  o.mapper.init_min_num_inliers = opts.init_min_num_inliers;
  o.mapper.init_min_tri_angle_deg = opts.init_min_tri_angle_deg;
  o.mapper.abs_pose_min_num_inliers = opts.abs_pose_min_num_inliers;
  o.expect_ring = !in.moving_camera;
  if (in.moving_camera) o.matching.mode = SfmMatching::kExhaustive;
  o.num_threads = opts.num_threads;
  o.cancel = in.cancel;
  auto sfm = RunColmapSfm(o);
  if (!sfm) {
    std::string advice;
    if (sfm.error().cls == ErrorClass::kNotFound) {
      advice =
          " (install Debian's colmap package, or use the calibrated turntable: [worker] poses = "
          "\"turntable\")";
    }
    return MakeError(sfm.error().cls, what + sfm.error().message + advice, sfm.error().detail);
  }
  const double sfm_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();

  // The camera the views were posed with, in OpenCV's convention.
  CameraModel cam;
  if (in.fixed_camera) {
    cam = *in.fixed_camera;
  } else {
    const SfmCamera* c = sfm->model.cameras.empty() ? nullptr : &sfm->model.cameras.front();
    if (!c || sfm->model.cameras.size() != 1) {
      return MakeError(ErrorClass::kCorrupt, what + "the SfM model has " +
                                                 std::to_string(sfm->model.cameras.size()) +
                                                 " cameras, one shared camera was asked for");
    }
    auto oc = OpenCvCameraFromColmap(*c);
    if (!oc) return MakeError(ErrorClass::kCorrupt, what + oc.error().message);
    cam = *oc;
  }

  // Background labels and ArUco markers, triangulated with the SfM poses.
  const auto t_ref = std::chrono::steady_clock::now();
  std::vector<std::string> label_colors;
  for (const RigMarker& m : in.rig.markers) label_colors.push_back(m.color);
  MarkerDetectOptions mopts;
  if (in.calibration) mopts.expected_label_side_px = ExpectedLabelSidePx(*in.calibration, in.rig);
  const bool want_aruco = !in.rig.aruco_markers.empty();
  std::vector<ViewMarkers> vm;
  std::vector<ArucoViewDetections> va;
  std::vector<geom::Rigid3> poses;
  std::vector<int> registered;  // input indices
  json unregistered = json::array();
  // The sample's evidence, when it asks for what is asked here with the
  // same lens and options (it also holds the object markers, which the label
  // search does not depend on: every colour class is classified either way).
  ViewEvidenceCache* cache = nullptr;
  if (in.evidence) {
    EvidenceOptions wanted = in.evidence->options();  // its object colours: the labels ignore them
    wanted.camera = cam;
    wanted.label_colors = label_colors;
    wanted.markers = mopts;
    wanted.rig = in.rig;
    if (in.evidence->Serves(wanted)) cache = in.evidence;
  }
  int from_cache = 0;
  for (size_t i = 0; i < in.views.size(); ++i) {
    const SfmImage* img = sfm->ImageForInput(static_cast<int>(i));
    if (!img) {
      unregistered.push_back(in.views[i].view);
      continue;
    }
    if (in.cancel && in.cancel->load())
      return MakeError(ErrorClass::kCancelled, what + "interrupted");
    std::shared_ptr<const ViewEvidence> e = cache ? cache->Find(in.views[i].image) : nullptr;
    if (e) {
      ++from_cache;
      registered.push_back(static_cast<int>(i));
      poses.push_back({img->R_cam_world, img->t_cam_world});
      vm.push_back(e->markers_found ? e->markers : ViewMarkers{});
      if (want_aruco) va.push_back(e->aruco_found ? e->aruco : ArucoViewDetections{});
      continue;
    }
    auto loaded = LoadImage(in.views[i].image, ImageMode::kColor);
    auto loaded_mask = LoadImage(in.views[i].mask, ImageMode::kGray);
    const cv::Mat bgr = loaded ? *loaded : cv::Mat();
    const cv::Mat mask = loaded_mask ? *loaded_mask : cv::Mat();
    if (bgr.empty() || mask.empty() || mask.size() != bgr.size()) {
      return MakeError(ErrorClass::kCorrupt,
                       what + "photo " + in.views[i].image + " or its mask " + in.views[i].mask +
                           " is unreadable or of different sizes; the sample's photos must not "
                           "change (delete the side's results to compute its masks again)");
    }
    registered.push_back(static_cast<int>(i));
    poses.push_back({img->R_cam_world, img->t_cam_world});
    if (cache) {
      // Found once for the stages after this one too.
      cache->Add(in.views[i].image, bgr, mask);
      e = cache->Find(in.views[i].image);
      vm.push_back(e && e->markers_found ? e->markers : ViewMarkers{});
      if (want_aruco) va.push_back(e && e->aruco_found ? e->aruco : ArucoViewDetections{});
      continue;
    }
    auto m = DetectViewMarkers(bgr, mask, label_colors, {}, &cam, mopts);
    vm.push_back(m ? std::move(*m) : ViewMarkers{});
    if (want_aruco) {
      auto a = DetectArucoMarkers(bgr, mask, in.rig, &cam);
      va.push_back(a ? std::move(*a) : ArucoViewDetections{});
    }
  }
  std::vector<Reference> refs;
  json jlabels = json::array();
  const Result<LabelScale> labels = LocateLabels(vm, poses, cam, in.rig);
  std::string problems;
  if (labels) {
    for (const LabelPoint& l : labels->labels) {
      json jl = {{"color", l.color},
                 {"located", l.located},
                 {"views_seen", l.views_seen},
                 {"views_used", l.views_used}};
      if (l.located) {
        refs.push_back({"label " + l.color, l.position, l.configured});
        jl["rms_px"] = l.rms_px;
      } else {
        jl["problem"] = l.problem;
      }
      jlabels.push_back(jl);
    }
  } else {
    problems += "background labels: " + labels.error().message;
  }
  bool by_aruco = false;
  json jaruco = {{"configured", want_aruco}};
  if (want_aruco) {
    const Result<ArucoScale> as = LocateArucoMarkers(va, poses, cam, in.rig);
    if (as) {
      for (const ArucoMarkerPoint& m : as->markers) {
        if (!m.located) continue;
        for (int k = 0; k < 4; ++k) {
          refs.push_back({"aruco " + std::to_string(m.id) + " corner " + std::to_string(k),
                          m.corners[k], m.configured[k]});
        }
        by_aruco = true;
      }
      jaruco["markers_used"] = as->markers_used;
    } else {
      jaruco["problem"] = as.error().message;
      problems +=
          std::string(problems.empty() ? "" : "; ") + "ArUco markers: " + as.error().message;
    }
  }
  const bool by_labels = labels.ok();
  if (!by_labels && !by_aruco) {
    return MakeError(
        ErrorClass::kCorrupt,
        what + "no metric scale: " + problems +
            ". The SfM model has no scale of its own; it takes it from the background labels "
            "(rig.markers, at least 3 located) or the ArUco markers (rig.aruco_markers): check "
            "that "
            "they lie on the disc where [rig] says, uncovered and in view, or use the calibrated "
            "turntable ([worker] poses = \"turntable\")");
  }
  std::vector<Eigen::Vector3d> src, dst;
  for (const Reference& r : refs) {
    src.push_back(r.sfm);
    dst.push_back(r.table);
  }
  double rms = 0;
  auto sim = EstimateSimilarity(src, dst, true, &rms);
  if (!sim)
    return MakeError(ErrorClass::kCorrupt, what + "scale references: " + sim.error().message);
  json jrefs = json::array();
  double worst = 0;
  for (const Reference& r : refs) {
    const double e = (sim->Apply(r.sfm) - r.table).norm();
    worst = std::max(worst, e);
    jrefs.push_back({{"name", r.name}, {"table_mm", Vec(r.table)}, {"residual_mm", e}});
  }
  const std::string reference =
      by_labels && by_aruco ? "labels+aruco" : (by_labels ? "labels" : "aruco");
  if (!(rms <= opts.max_scale_residual_mm)) {
    return MakeError(
        ErrorClass::kCorrupt,
        what + "SfM model rejected: the " + reference +
            " located in it do not fit their configured " + "positions (RMS " + Fmt("%.2f", rms) +
            " mm, worst " + Fmt("%.2f", worst) + " mm, limit " +
            Fmt("%.2f", opts.max_scale_residual_mm) +
            " mm): either the model is distorted or [rig] does not describe the labels as placed; "
            "measure the label positions again, or use the calibrated turntable ([worker] poses = "
            "\"turntable\")");
  }
  const double ref_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t_ref).count();

  // Into the metric turntable frame.
  SfmModel model = sfm->model;
  ApplySimilarity(*sim, &model);
  const std::string results_dir = in.sample_dir + "/" + layout::kResultsDir;
  if (Status s = WriteColmapTextModel(results_dir + "/" + SfmModelDirName(in.side), model); !s) {
    return MakeError(s.error().cls, what + "exporting the model: " + s.error().message,
                     s.error().detail);
  }
  records::PosesRecord rec;
  std::optional<RigCalibration> cal;
  json pose_only = json::array();
  for (int i : registered) {
    const SampleView& v = in.views[static_cast<size_t>(i)];
    const SfmImage* img = model.FindImage(sfm->ImageForInput(i)->id);
    if (v.pose_only) {
      // Registered with the rest, its cut silhouette kept out of the surface.
      pose_only.push_back(v.view);
      continue;
    }
    records::PosedViewRecord pv;
    pv.view = v.view;
    pv.image = v.image_rel;
    pv.mask = v.mask_rel;
    pv.angle_deg = v.angle_deg;
    pv.cam_from_table = ToPose(geom::Rigid3{img->R_cam_world, img->t_cam_world});
    rec.views.push_back(std::move(pv));
    if (!cal) {
      // A turntable pose consistent with CamFromTable(angle) at this view:
      // cam_from_table0 = cam_from_table * Rz(-angle).
      const geom::Rigid3 t0 =
          geom::Rigid3{img->R_cam_world, img->t_cam_world} * geom::Rigid3::RotZ(-v.angle_deg);
      cal.emplace();
      for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) cal->R_cam_table0[r * 3 + c] = t0.R(r, c);
        cal->t_cam_table0[r] = t0.t(r);
      }
    }
  }
  if (!cal) return MakeError(ErrorClass::kCorrupt, what + "no view registered");
  cal->camera = cam;
  cal->method = "sfm";
  cal->reprojection_rms_px = sfm->mean_reprojection_px;
  cal->views_used = sfm->num_registered;
  cal->source = in.camera_source;
  json jtimings = json::array();
  for (const SfmStepTiming& t : sfm->timings) {
    jtimings.push_back({{"step", t.step}, {"wall_s", t.wall_s}, {"skipped", t.skipped}});
  }
  json jsfm = {{"registered_views", sfm->num_registered},
               {"input_views", sfm->num_input_images},
               {"mean_reprojection_px", sfm->mean_reprojection_px},
               {"points", model.points.size()},
               {"verified_pairs", sfm->num_verified_pairs},
               {"other_models_registered", sfm->other_models_registered},
               {"checks_passed", sfm->checks.ok()},
               {"checks", sfm->checks.ToJson()},
               {"camera_source", in.camera_source},
               {"camera_model", in.fixed_camera ? "fixed" : opts.free_camera_model},
               {"max_image_size_px", opts.max_image_size},
               {"pairs", in.moving_camera ? "exhaustive" : "circular"},
               {"circular_neighbours", opts.circular_neighbours},
               {"capture_mode", in.moving_camera ? "moving_camera" : "turntable"},
               {"window_px", sfm->window[2] == 0 ? json(nullptr) : json(sfm->window)},
               {"posed_not_carved", pose_only},
               {"workspace", "work/" + side_name + "/sfm"},
               {"model_dir", SfmModelDirName(in.side)},
               {"timings_s", jtimings},
               {"colmap_s", sfm_s},
               {"references_s", ref_s},
               {"references_from_evidence", from_cache}};
  if (!in.fixed_camera && in.expected_focal_px) {
    jsfm["focal_hint_px"] = *in.expected_focal_px;
    jsfm["focal_hint_source"] = in.focal_hint_source;
  }
  rec.side = in.side;
  rec.method = "sfm";
  rec.method_detail =
      std::string("full SfM through COLMAP (masked SIFT") +
      (sfm->window[2] == 0 ? "" : " on the masks' window") +
      (in.moving_camera ? ", every pair matched (a camera walked round a still rock)"
                        : ", circular pair list") +
      ", mapper), scaled into the turntable frame by a similarity onto the configured " + reference;
  rec.sfm = std::move(jsfm);
  rec.scale = {{"reference", reference},
               {"scale", sim->scale},
               {"residual_mm", rms},
               {"max_residual_mm", worst},
               {"limit_mm", opts.max_scale_residual_mm},
               {"references", jrefs},
               {"labels", jlabels},
               {"aruco", jaruco}};
  rec.calibration = CalibrationToJson(*cal);
  rec.unregistered_views = unregistered;
  return rec;
}

std::optional<FocalHint> FocalHintFromConfig(const Config& cfg, int image_width) {
  if (image_width <= 0) return std::nullopt;
  const CameraConfig& c = cfg.camera;
  if (c.lens_focal_mm > 0 && c.sensor_width_mm > 0) {
    return FocalHint{c.lens_focal_mm / c.sensor_width_mm * image_width,
                     "camera.lens_focal_mm " + Fmt("%g", c.lens_focal_mm) +
                         " / camera.sensor_width_mm " + Fmt("%g", c.sensor_width_mm) +
                         " of the sample's config"};
  }
  if (c.backend == "sim" && cfg.sim.hfov_deg > 0 && cfg.sim.hfov_deg < 180) {
    return FocalHint{FocalPxFromHfov(cfg.sim.hfov_deg, image_width),
                     "sim.hfov_deg " + Fmt("%g", cfg.sim.hfov_deg) + " of the sample's config"};
  }
  return std::nullopt;
}

}  // namespace aggscan
