#include "pipeline/worker/reconstruct.h"

#include <openssl/evp.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>

#include "common/clock.h"
#include "common/fsutil.h"
#include "common/json_io.h"
#include "common/log.h"
#include "common/mesh_check.h"
#include "common/mesh_props.h"
#include "common/rig_calibration.h"
#include "common/version.h"
#include "pipeline/core/geometry.h"
#include "pipeline/core/image_io.h"
#include "pipeline/core/parallel_for.h"
#include "pipeline/core/records.h"
#include "pipeline/core/stage.h"
#include "pipeline/core/stage_runner.h"
#include "pipeline/core/stats.h"
#include "pipeline/markers/markers.h"
#include "pipeline/markers/view_evidence.h"
#include "pipeline/masks/mask_dataset.h"
#include "pipeline/morph/morph2d.h"
#include "pipeline/stitch/stitch_stage.h"
#include "pipeline/worker/options_json.h"
#include "pipeline/worker/quality.h"
#include "store/layout.h"
#include "store/library_csv.h"

namespace aggscan {

namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr const char* kCat = "worker";

using layout::ResultsPath;

Status WriteJson(const std::string& path, const json& j) { return jsonio::WriteFile(path, j); }

Result<json> ReadJson(const std::string& path, const std::string& what) {
  return jsonio::ReadFile(path, what, "delete it to recompute that stage");
}

double Seconds(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// The records of the stages (records.h), read with what to do when one is bad.
Result<records::SideResult> ReadSideResult(const std::string& sample_dir, int side) {
  return records::Read<records::SideResult>(SideResultPath(sample_dir, side), "side result",
                                            "delete it to recompute the side's masks");
}

Result<records::PosesRecord> ReadPoses(const std::string& sample_dir, int side) {
  return records::Read<records::PosesRecord>(
      ResultsPath(sample_dir, layout::PosesName(side)), "poses record",
      "run the reconstruction again from the poses (aggscan reconstruct --from poses)");
}

// --- stage: calibration --------------------------------------------------

Result<RigCalibration> CalibrationStage(const std::string& sample_dir,
                                        const ReconstructOptions& opts, const cv::Size& image_size,
                                        json* timings) {
  const std::string out = ResultsPath(sample_dir, layout::kCalibrationUsed);
  if (PathExists(out)) {
    auto j = ReadJson(out, "calibration record");
    if (!j) return j.error();
    auto cal = CalibrationFromJson(*j, out);
    if (!cal) return cal.error();
    (*timings)["calibration_s"] = j->value("stage_seconds", 0.0);
    return cal;
  }
  const auto t0 = std::chrono::steady_clock::now();
  std::string path = sample_dir + "/calibration.json";
  if (!PathExists(path) && !opts.state_dir.empty()) path = CalibrationPath(opts.state_dir);
  auto cal = LoadCalibration(path);
  if (!cal) {
    std::string alt;
    if (cal.error().cls == ErrorClass::kNotFound) {
      alt =
          "; or pose the views by full SfM, which needs no calibration: [worker] poses = \"auto\" "
          "or \"sfm\" "
          "(aggscan reconstruct --poses sfm)";
    }
    return MakeError(cal.error().cls, "calibration stage: " + cal.error().message + alt,
                     cal.error().detail);
  }
  if (Status s = CheckCalibrationFits(*cal, image_size.width, image_size.height); !s) {
    return MakeError(ErrorClass::kInvalidConfig, "calibration stage: " + s.error().message);
  }
  if (cal->camera.width != image_size.width)
    cal->camera = cal->camera.Resized(image_size.width, image_size.height);
  json j = CalibrationToJson(*cal);
  j["origin"] = path;
  j["stage_seconds"] = Seconds(t0);
  if (Status s = WriteJson(out, j); !s) return s.error();
  (*timings)["calibration_s"] = j["stage_seconds"];
  return cal;
}

// --- poses path -----------------------------------------------------------

// Whether a rig calibration is there for the sample (what CalibrationStage
// reads): its own copy, else the state directory's.
bool HasCalibration(const std::string& sample_dir, const ReconstructOptions& opts) {
  return PathExists(sample_dir + "/" + layout::kCalibrationCopy) ||
         (!opts.state_dir.empty() && PathExists(CalibrationPath(opts.state_dir)));
}

// True for the SfM path. "auto" takes the turntable whenever there is a rig
// calibration; a sample posed by SfM before one was installed is then posed
// again (the stages' fingerprints name the path).
// A camera walked round a still rock has no turntable to pose it by: SfM,
// whatever the rig's poses setting (made for its turntable captures) says.
Result<bool> ChoosePosesPath(const std::string& sample_dir, const ReconstructOptions& opts,
                             bool moving_camera) {
  if (moving_camera) return true;
  switch (opts.poses) {
    case PosesPath::kSfm:
      return true;
    case PosesPath::kAuto:
      return !HasCalibration(sample_dir, opts);
    case PosesPath::kTurntable:
      return false;
  }
  return false;
}

// The calibration record of a side's SfM poses (the camera it was posed with).
Result<RigCalibration> SfmCalibrationOfSide(const std::string& sample_dir, int side) {
  const std::string path = ResultsPath(sample_dir, layout::PosesName(side));
  auto j = ReadPoses(sample_dir, side);
  if (!j) return j.error();
  if (!j->IsSfm()) {
    return MakeError(ErrorClass::kCorrupt, path + " holds no SfM camera (method " + j->method +
                                               "); delete it to pose that side again");
  }
  return CalibrationFromJson(j->calibration, path);
}

// --- stage: poses --------------------------------------------------------

// The figures of a bundle adjustment for the poses record.
json BundleAdjustJson(const BundleAdjustResult& r) {
  json j = {{"refined", r.refined},
            {"views_used", r.views_used},
            {"tracks", r.tracks},
            {"observations", r.observations},
            {"outliers_dropped", r.outliers_dropped},
            {"initial_rms_px", r.initial_rms_px},
            {"final_rms_px", r.final_rms_px},
            {"iterations", r.iterations},
            {"gauge_view_index", r.fixed_view},
            {"features_s", r.features_s},
            {"matching_s", r.matching_s},
            {"solve_s", r.solve_s}};
  if (!r.reason.empty()) j["reason"] = r.reason;
  double max_abs = 0;
  for (double c : r.correction_deg) max_abs = std::max(max_abs, std::abs(c));
  j["max_abs_correction_deg"] = max_abs;
  return j;
}

// A side result view's measured turntable angle (from its sidecar).
Result<double> MeasuredAngle(const records::View2D& v, int side) {
  if (!v.measured_angle_deg) {
    return MakeError(ErrorClass::kCorrupt, "poses stage: view " + std::to_string(v.view) + " of " +
                                               layout::SideDirName(side) +
                                               " has no measured turntable angle in its sidecar");
  }
  return *v.measured_angle_deg;
}

// The SfM poses record of a side (sfm_poses.h) from its side result.
// `setup`: what the side needs besides its views (camera, focal hint, rig).
Result<records::PosesRecord> SfmPosesRecord(const std::string& sample_dir, int side,
                                            const records::SideResult& side_result,
                                            const SfmPosesInput& setup,
                                            const ReconstructOptions& opts,
                                            ViewEvidenceCache* evidence) {
  SfmPosesInput in = setup;
  in.evidence = evidence;
  in.sample_dir = sample_dir;
  in.side = side;
  for (const records::View2D& v : side_result.views) {
    const bool cut = !v.ok && v.extra.value("cut_by_frame", false) && !v.mask.empty();
    if (!v.ok && !cut) continue;
    // SfM poses the views itself; a hand-turned table's plan angle only
    // orders them, and is no check of the model.
    if (!v.measured_angle_deg) in.angles_measured = false;
    auto angle = v.measured_angle_deg || !v.commanded_angle_deg
                     ? MeasuredAngle(v, side)
                     : Result<double>(*v.commanded_angle_deg);
    if (!angle) return angle.error();
    SampleView sv;
    sv.side = side;
    sv.view = v.view;
    sv.angle_deg = *angle;
    sv.image_rel = v.image;
    sv.mask_rel = v.mask;
    sv.image = sample_dir + "/" + layout::SideDirName(side) + "/" + sv.image_rel;
    sv.mask = ResultsPath(sample_dir, sv.mask_rel);
    sv.pose_only = cut;
    in.views.push_back(std::move(sv));
  }
  in.cancel = opts.cancel;
  return RunSfmPoses(in, opts.sfm);
}

// A table turned by hand: the views of a side that carry no measured angle
// get theirs from the disc's labels and ArUco markers (hand_turned.h). Views
// shot while the table turned (sharpness below the limit against the side's
// median) and views whose references give no angle are left out, each named
// with what to do in `left_out`. Angles are unwrapped along the capture
// order: each near the previous one plus the plan's step.
struct HandAngles {
  std::map<int, double> angle_deg;  // by view number
  std::map<int, json> detail;       // the fit, by view number
  json left_out = json::array();    // [{view, reason}]
};

Result<HandAngles> MeasureHandTurnedAngles(const std::string& sample_dir, int side,
                                           const std::vector<const records::View2D*>& views,
                                           const RigCalibration& cal,
                                           const ReconstructOptions& opts,
                                           ViewEvidenceCache* evidence) {
  if (!evidence) {
    return MakeError(ErrorClass::kInternal, "poses stage: no view evidence for a hand-turned side");
  }
  const std::string side_dir = sample_dir + "/" + layout::SideDirName(side);
  struct One {
    TableAngleFit fit;
    double sharpness = 0;
    std::string problem;  // the photo or mask could not be read
  };
  std::vector<One> out(views.size());
  const cv::Point2d turn = TurnDirection(cal);
  ParallelFor(views.size(), kWorkerThreads, [&](size_t i) {
    const std::string image = side_dir + "/" + views[i]->image;
    auto img = LoadImage(image, ImageMode::kColor, opts.worker.image_limits);
    auto m = LoadImage(ResultsPath(sample_dir, views[i]->mask), ImageMode::kGray,
                       opts.worker.image_limits);
    if (!img || !m || img->size() != m->size()) {
      out[i].problem = !img ? img.error().message
                            : (!m ? m.error().message : "the photo and its mask differ in size");
      return;
    }
    evidence->Add(image, *img, *m);
    const std::shared_ptr<const ViewEvidence> e = evidence->Find(image);
    out[i].sharpness = RockSharpness(*img, *m, turn);
    if (!e || !e->markers_found) {
      out[i].fit.problem = "the disc's labels could not be searched for in this photo";
      return;
    }
    out[i].fit = FitTableAngle(e->markers, e->aruco_found ? &e->aruco : nullptr, cal,
                               evidence->options().rig, opts.hand);
  });
  std::vector<double> sharp;
  for (const One& o : out)
    if (o.sharpness > 0) sharp.push_back(o.sharpness);
  const double median = Median(std::move(sharp));
  HandAngles h;
  std::optional<double> prev_angle, prev_plan;
  for (size_t i = 0; i < views.size(); ++i) {
    const records::View2D& v = *views[i];
    const One& o = out[i];
    const double ratio = median > 0 ? o.sharpness / median : 1.0;
    auto leave_out = [&](const std::string& reason) {
      h.left_out.push_back({{"view", v.view}, {"reason", reason}});
    };
    if (!o.problem.empty()) {
      leave_out("cannot be read: " + o.problem);
      continue;
    }
    if (ratio < opts.hand_min_sharpness_ratio) {
      char buf[96];
      std::snprintf(buf, sizeof buf, "%.0f %% of the side's median", 100.0 * ratio);
      leave_out(std::string("shot while the table was turning (sharpness inside the rock ") + buf +
                "): turn the table as soon as the rig prompts and let go before the hands-off "
                "moment, or lengthen capture.interval");
      continue;
    }
    if (!o.fit.ok) {
      leave_out("no turntable angle from the disc: " + o.fit.problem);
      continue;
    }
    const double plan = v.commanded_angle_deg.value_or(0.0);
    const double near = prev_angle ? *prev_angle + (plan - *prev_plan) : plan;
    const double angle = UnwrapNear(o.fit.angle_deg, near);
    prev_angle = angle;
    prev_plan = plan;
    h.angle_deg[v.view] = angle;
    json d = {{"angle_source", "labels"},
              {"angle_fit_rms_px", o.fit.rms_px},
              {"angle_fit_max_px", o.fit.max_px},
              {"angle_fit_labels", o.fit.labels},
              {"angle_fit_aruco_markers", o.fit.aruco_markers},
              {"sharpness_ratio", ratio}};
    if (!o.fit.dropped.empty()) d["angle_fit_dropped"] = o.fit.dropped;
    h.detail[v.view] = std::move(d);
  }
  return h;
}

Result<std::vector<SampleView>> PosesStage(const std::string& sample_dir, int side,
                                           const RigCalibration* cal, const SfmPosesInput* sfm,
                                           const ReconstructOptions& opts, json* timings,
                                           std::string* method, ViewEvidenceCache* evidence) {
  const std::string out = ResultsPath(sample_dir, layout::PosesName(side));
  const std::string side_dir = sample_dir + "/" + layout::SideDirName(side);
  std::vector<SampleView> views;
  if (!PathExists(out) && sfm) {
    const auto t0 = std::chrono::steady_clock::now();
    auto side_result = ReadSideResult(sample_dir, side);
    if (!side_result) return side_result.error();
    auto j = SfmPosesRecord(sample_dir, side, *side_result, *sfm, opts, evidence);
    if (!j) return j.error();
    j->stage_seconds = Seconds(t0);
    if (Status s = records::Write(out, *j); !s) return s.error();
    StageLog(LogLevel::kInfo, kCat, layout::SampleIdOfDir(sample_dir),
             layout::SideDirName(side) + ": SfM registered " +
                 std::to_string(j->sfm.value("registered_views", 0)) + " views, scale residual " +
                 std::to_string(j->scale.value("residual_mm", 0.0)) + " mm");
  } else if (!PathExists(out)) {
    if (!cal)
      return MakeError(ErrorClass::kInternal, "poses stage: no calibration for the turntable path");
    const auto t0 = std::chrono::steady_clock::now();
    auto side_result = ReadSideResult(sample_dir, side);
    if (!side_result) return side_result.error();
    if (Status s = SideHasEnoughWholeViews(*side_result); !s) {
      return MakeError(s.error().cls, "poses stage: " + s.error().message);
    }
    records::PosesRecord rec;
    std::vector<records::PosedViewRecord>& jviews = rec.views;
    // Views without a measured angle come from a table turned by hand.
    std::vector<const records::View2D*> unmeasured;
    for (const records::View2D& v : side_result->views) {
      if (v.ok && !v.measured_angle_deg) unmeasured.push_back(&v);
    }
    std::optional<HandAngles> hand;
    if (!unmeasured.empty()) {
      auto h = MeasureHandTurnedAngles(sample_dir, side, unmeasured, *cal, opts, evidence);
      if (!h) return h.error();
      hand = std::move(*h);
    }
    for (const records::View2D& v : side_result->views) {
      if (!v.ok) continue;  // no rock in this view: it cannot bound the hull
      records::PosedViewRecord pv;
      if (v.measured_angle_deg) {
        pv.angle_deg = *v.measured_angle_deg;
      } else if (hand && hand->angle_deg.count(v.view)) {
        pv.angle_deg = hand->angle_deg.at(v.view);
        pv.extra = hand->detail.at(v.view);
      } else {
        continue;  // named in the hand-turned views left out
      }
      pv.view = v.view;
      pv.image = v.image;
      pv.mask = v.mask;
      pv.cam_from_table = geom::IsoFromRowMajor(cal->CamFromTable(pv.angle_deg));
      jviews.push_back(std::move(pv));
    }
    if (jviews.size() < 3) {
      std::string why;
      if (hand && !hand->left_out.empty()) {
        why = " (" + std::to_string(hand->left_out.size()) + " left out, first: view " +
              std::to_string(hand->left_out[0].value("view", 0)) + " " +
              hand->left_out[0].value("reason", "") + ")";
      }
      return MakeError(ErrorClass::kCorrupt, "poses stage: " + layout::SideDirName(side) +
                                                 " has only " + std::to_string(jviews.size()) +
                                                 " posed views with a rock" + why +
                                                 "; at least 3 are needed: re-capture the side");
    }
    rec.side = side;
    rec.method = "turntable";
    rec.method_detail = "calibrated turntable: cam_from_table0 * Rz(measured angle)";
    if (hand) {
      rec.method_detail =
          "calibrated turntable turned by hand: cam_from_table0 * Rz(angle measured from the "
          "disc's labels and markers)";
      rec.extra["hand_turned"] = true;
      rec.extra["views_left_out"] = hand->left_out;
      for (const json& l : hand->left_out) {
        StageLog(LogLevel::kWarning, kCat, layout::SampleIdOfDir(sample_dir),
                 layout::SideDirName(side) + " view " + std::to_string(l.value("view", 0)) +
                     " left out: " + l.value("reason", ""));
      }
    }
    if (opts.bundle_adjust) {
      // Eq. 2 of the study: only the features inside the rock masks refine the
      // poses; the photos are read one at a time.
      std::vector<double> measured;
      measured.reserve(jviews.size());
      for (const auto& v : jviews) measured.push_back(v.angle_deg);
      // What the stitch and the surface need of each photo is kept while it
      // is decoded here (view_evidence.h).
      auto load = [&](int i, cv::Mat* bgr, cv::Mat* mask) {
        const std::string image = side_dir + "/" + jviews[i].image;
        auto img = LoadImage(image, ImageMode::kColor, opts.worker.image_limits);
        auto m = LoadImage(ResultsPath(sample_dir, jviews[i].mask), ImageMode::kGray,
                           opts.worker.image_limits);
        if (!img || !m) return false;
        *bgr = std::move(*img);
        *mask = std::move(*m);
        if (bgr->size() != mask->size()) return false;
        if (evidence) evidence->Add(image, *bgr, *mask);
        return true;
      };
      const BundleAdjustResult ba =
          BundleAdjustSideImages(static_cast<int>(jviews.size()), load, measured, *cal, opts.ba);
      rec.bundle_adjustment = BundleAdjustJson(ba);
      if (ba.refined) {
        rec.method = "turntable+ba";
        rec.method_detail =
            "calibrated turntable, angles refined by bundle adjustment (Ceres) over feature tracks "
            "inside the rock masks";
        for (size_t i = 0; i < jviews.size(); ++i) {
          jviews[i].measured_angle_deg = measured[i];
          jviews[i].angle_deg = ba.angle_deg[i];
          jviews[i].angle_correction_deg = ba.correction_deg[i];
          jviews[i].ba_adjusted = static_cast<bool>(ba.adjusted[i]);
          jviews[i].cam_from_table =
              geom::IsoFromRowMajor(ba.calibration.CamFromTable(ba.angle_deg[i]));
        }
      } else {
        StageLog(LogLevel::kWarning, kCat, layout::SampleIdOfDir(sample_dir),
                 layout::SideDirName(side) + ": poses not refined: " + ba.reason);
      }
    } else {
      rec.bundle_adjustment = {{"refined", false}, {"reason", "bundle adjustment is turned off"}};
    }
    rec.stage_seconds = Seconds(t0);
    if (Status s = records::Write(out, rec); !s) return s.error();
  }
  auto j = ReadPoses(sample_dir, side);
  if (!j) return j.error();
  for (const records::PosedViewRecord& v : j->views) {
    SampleView in;
    in.side = side;
    in.view = v.view;
    in.angle_deg = v.angle_deg;
    in.image_rel = v.image;
    in.mask_rel = v.mask;
    in.image = side_dir + "/" + v.image;
    in.mask = ResultsPath(sample_dir, v.mask);
    in.cam_from_table = v.cam_from_table;
    views.push_back(std::move(in));
  }
  (*timings)["poses_" + layout::SideDirName(side) + "_s"] = j->stage_seconds;
  *method = j->method;
  return views;
}

// --- stage: surface ------------------------------------------------------

// A view's rock mask cut down to the rock's box and a margin, and the lens of
// that window (CameraModel::Cropped): carving, photo refinement, colouring
// and the silhouette check work on the window alone, as they would on the
// whole frame (outside it, as outside the frame, is background). The rock
// fills a few per cent of the frame, so this is where the surface stage's
// time and memory go down: a float distance map per view of 2016 x 1512
// would be 12 MB, 730 MB for 60 views.
struct ViewWindow {
  cv::Rect roi;        // in the full frame; even corners and sides (half-size photos crop exactly)
  CameraModel camera;  // the window's lens
  cv::Mat mask;        // the mask inside roi (a copy: the full frame is not kept)
};

// The margin around the rock's box: the carving reads the distance map up to
// 3 coarse cells (12 mm) outside the surface exactly, the photo refinement's
// patches reach a few mm past it. 24 mm at the disc, in pixels.
int WindowMarginPx(const RigCalibration& cal) {
  const double at_disc = PxPerMmAtDisc(cal);
  const double px_per_mm = at_disc > 0 ? at_disc : 1.0;
  return 2 * static_cast<int>(std::ceil(12.0 * px_per_mm)) + 16;
}

ViewWindow WindowIn(const CameraModel& cam, const cv::Rect& roi, cv::Mat mask) {
  return {roi, cam.Cropped(roi.x, roi.y, roi.width, roi.height), std::move(mask)};
}

ViewWindow WindowOf(const cv::Mat& full_mask, const CameraModel& cam, int margin) {
  const cv::Rect roi = RockWindow(full_mask, margin);
  return WindowIn(cam, roi, CropPadded(full_mask, roi));
}

// The same from what an earlier stage kept of the view, when it kept it with
// this margin.
std::optional<ViewWindow> CachedWindow(const ViewEvidenceCache* evidence, const std::string& image,
                                       const CameraModel& cam, int margin) {
  if (!evidence || evidence->options().window_margin != margin) return std::nullopt;
  const std::shared_ptr<const ViewEvidence> e = evidence->Find(image);
  if (!e || e->frame != cv::Size(cam.width, cam.height)) return std::nullopt;
  return WindowIn(cam, e->window, e->mask);
}

// The photo `image` inside `roi`.
Status ReadColourWindow(const std::string& image, const cv::Rect& roi, cv::Size full_size,
                        const ImageLimits& limits, cv::Mat* out) {
  auto loaded = LoadImage(image, ImageMode::kColor, limits);
  if (!loaded) {
    return MakeError(loaded.error().cls, "surface stage: " + loaded.error().message,
                     loaded.error().detail);
  }
  if (loaded->size() != full_size) {
    return MakeError(ErrorClass::kCorrupt, "surface stage: the photo " + image +
                                               " is not the size of its mask; the sample's photos "
                                               "must not change");
  }
  *out = CropPadded(*loaded, roi);
  return OkStatus();
}

// Per-vertex colour from the view that sees the vertex most head-on among
// those where it lies well inside the silhouette.
Result<VertexColors> ColourVertices(const Mesh& mesh, const std::vector<SampleView>& views,
                                    const std::vector<Eigen::Isometry3d>& cam_from_object,
                                    const std::vector<ViewWindow>& windows, cv::Size full_size,
                                    const ImageLimits& limits, const ViewEvidenceCache* evidence) {
  const size_t nv = mesh.vertices.size();
  std::vector<Eigen::Vector3d> normals(nv, Eigen::Vector3d::Zero());
  for (const auto& f : mesh.faces) {
    const Eigen::Vector3d a(mesh.vertices[f[0]].data()), b(mesh.vertices[f[1]].data()),
        c(mesh.vertices[f[2]].data());
    const Eigen::Vector3d n = (b - a).cross(c - a);
    for (int i : f) normals[i] += n;
  }
  std::vector<int> best(nv, -1);
  std::vector<double> score(nv, 0.0);
  std::vector<Eigen::Vector2f> uv(nv);
  for (size_t vi = 0; vi < views.size(); ++vi) {
    const Eigen::Isometry3d& T = cam_from_object[vi];
    const CameraModel& cam = windows[vi].camera;
    const Eigen::Vector3d C = T.inverse().translation();
    for (size_t i = 0; i < nv; ++i) {
      const Eigen::Vector3d p(mesh.vertices[i].data());
      const Eigen::Vector3d to_cam = (C - p).normalized();
      const double s = normals[i].normalized().dot(to_cam);
      if (s <= score[i]) continue;
      const Eigen::Vector3d pc = T * p;
      double u, v;
      if (!cam.Project({pc.x(), pc.y(), pc.z()}, &u, &v)) continue;
      const int x = static_cast<int>(std::lround(u)), y = static_cast<int>(std::lround(v));
      if (x < 2 || y < 2 || x >= cam.width - 2 || y >= cam.height - 2) continue;
      if (windows[vi].mask.at<uint8_t>(y, x) == 0) continue;
      score[i] = s;
      best[i] = static_cast<int>(vi);
      uv[i] = Eigen::Vector2f(static_cast<float>(u), static_cast<float>(v));
    }
  }
  VertexColors colors(nv, {128, 128, 128});
  // Photos read two at a time; each vertex takes its colour from its one best view.
  std::vector<std::optional<Error>> failed(views.size());
  ParallelFor(views.size(), kWorkerThreads, [&](size_t vi) {
    bool any = false;
    for (size_t i = 0; i < nv && !any; ++i) any = best[i] == static_cast<int>(vi);
    if (!any) return;
    cv::Mat img;
    if (const auto e = evidence ? evidence->Find(views[vi].image) : nullptr;
        e && !e->bgr.empty() && e->window == windows[vi].roi) {
      img = e->bgr;
    } else if (Status s =
                   ReadColourWindow(views[vi].image, windows[vi].roi, full_size, limits, &img);
               !s) {
      failed[vi] = s.error();
      return;
    }
    for (size_t i = 0; i < nv; ++i) {
      if (best[i] != static_cast<int>(vi)) continue;
      cv::Mat patch;
      cv::getRectSubPix(img, cv::Size(1, 1), cv::Point2f(uv[i].x(), uv[i].y()), patch);
      const cv::Vec3b bgr = patch.at<cv::Vec3b>(0, 0);
      colors[i] = {bgr[2], bgr[1], bgr[0]};
    }
  });
  for (const auto& e : failed)
    if (e) return *e;
  return colors;
}

// Each view's silhouette of `mesh`, at its window's size.
std::vector<cv::Mat> Silhouettes(const Mesh& mesh,
                                 const std::vector<Eigen::Isometry3d>& cam_from_object,
                                 const std::vector<ViewWindow>& windows) {
  std::vector<cv::Mat> sil(windows.size());
  ParallelFor(windows.size(), kWorkerThreads, [&](size_t vi) {
    sil[vi] = RenderMeshSilhouette(mesh, cam_from_object[vi], windows[vi].camera);
  });
  return sil;
}

struct ViewAgreement {
  double iou = 0;
  double outline_loss = 0;
};

// IoU between each view's mask and the surface's silhouette in it: how well the masks and poses
// agree. A visual hull's silhouette lies inside every mask; a mask that disagrees with the others
// (a leak, a wrong pose) loses area. And the fraction of the carved hull's silhouette the surface
// no longer covers: the hull's outline in a view is where the true surface touches that view's
// silhouette cone, so a surface that lies inside it there was moved in against the masks.
std::vector<ViewAgreement> SilhouetteAgreement(const std::vector<cv::Mat>& surface,
                                               const std::vector<cv::Mat>& hull,
                                               const std::vector<ViewWindow>& windows) {
  std::vector<ViewAgreement> out(windows.size());
  ParallelFor(windows.size(), kWorkerThreads, [&](size_t vi) {
    const cv::Mat& sil = surface[vi];
    const cv::Mat small_mask = windows[vi].mask > 127;
    const double inter = cv::countNonZero(sil & small_mask);
    const double uni = cv::countNonZero(sil | small_mask);
    out[vi].iou = uni > 0 ? inter / uni : 0.0;
    const double hull_px = cv::countNonZero(hull[vi]);
    out[vi].outline_loss = hull_px > 0 ? cv::countNonZero(hull[vi] & ~sil) / hull_px : 0.0;
  });
  return out;
}

struct SurfaceOut {
  Mesh mesh;
  json record;
};

// Per view, the volume that view alone carves away from what every other view
// (and the floors) holds to be rock, sampled on a grid over the hull's region
// grown by half its size each way. A mask that lost part of the rock (a photo
// decoded half grey, a segmentation that failed) carves that part out of the
// hull, and in that view the hull then fits the mask well: the view's IoU
// does not show it, the other views' IoUs do. Its sole carving does, and
// names it. Good views carve alone only a thin shell at their outline.
struct SoleCarving {
  std::vector<double> volume_mm3;  // per view
  double agreed_mm3 = 0;           // inside every view and floor
};

SoleCarving SoleCarvingVolumes(const std::vector<SilhouetteView>& sv,
                               const std::vector<HalfSpace>& floors,
                               const Eigen::AlignedBox3d& hull_box,
                               const Eigen::AlignedBox3d& search) {
  SoleCarving out;
  out.volume_mm3.assign(sv.size(), 0.0);
  const Eigen::Vector3d ext = hull_box.sizes();
  Eigen::AlignedBox3d box(hull_box.min() - 0.5 * ext, hull_box.max() + 0.5 * ext);
  box = box.intersection(search);
  if (box.isEmpty()) return out;
  // About 2 million samples: a few per cent of a rock's volume is thousands.
  const double step = std::max(0.25, std::cbrt(box.volume() / 2e6));
  const int nx = static_cast<int>(box.sizes().x() / step) + 1,
            ny = static_cast<int>(box.sizes().y() / step) + 1,
            nz = static_cast<int>(box.sizes().z() / step) + 1;
  std::vector<std::vector<int64_t>> veto(kWorkerThreads, std::vector<int64_t>(sv.size(), 0));
  std::vector<int64_t> agreed(kWorkerThreads, 0);
  auto inside = [&](size_t k, const Eigen::Vector3d& p) {
    const Eigen::Vector3d pc = sv[k].cam_from_object * p;
    double u = 0, v = 0;
    if (pc.z() <= 0 || !sv[k].camera.Project({pc.x(), pc.y(), pc.z()}, &u, &v)) return false;
    const int x = static_cast<int>(std::lround(u)), y = static_cast<int>(std::lround(v));
    if (x < 0 || y < 0 || x >= sv[k].mask.cols || y >= sv[k].mask.rows) return false;
    return sv[k].mask.at<uint8_t>(y, x) > 127;
  };
  ParallelFor(nz, kWorkerThreads, [&](int iz, int t) {
    for (int iy = 0; iy < ny; ++iy) {
      for (int ix = 0; ix < nx; ++ix) {
        const Eigen::Vector3d p = box.min() + step * Eigen::Vector3d(ix + 0.5, iy + 0.5, iz + 0.5);
        bool below = false;
        for (const HalfSpace& h : floors) below = below || h.normal.dot(p) + h.offset < 0;
        if (below) continue;
        int outside = 0;
        size_t first = 0;
        for (size_t k = 0; k < sv.size() && outside < 2; ++k) {
          if (!inside(k, p)) {
            if (outside == 0) first = k;
            ++outside;
          }
        }
        if (outside == 0) ++agreed[t];
        if (outside == 1) ++veto[t][first];
      }
    }
  });
  const double cell = step * step * step;
  int64_t agreed_cells = 0;
  for (int64_t a : agreed) agreed_cells += a;
  out.agreed_mm3 = static_cast<double>(agreed_cells) * cell;
  for (size_t k = 0; k < sv.size(); ++k) {
    int64_t cells = 0;
    for (const auto& per_thread : veto) cells += per_thread[k];
    out.volume_mm3[k] = static_cast<double>(cells) * cell;
  }
  return out;
}

// A view whose mask has an IoU with the model's silhouette below this, and
// far below the other views', is named as disagreeing.
constexpr double kIouFloor = 0.90;

// When the hull fails: the views whose mask is far smaller than their side's
// largest (a rock's outline changes by a factor of 2-3 with the angle, not
// 7), where the segmentation most likely lost the rock: ashlar 923 scaled to
// 220 mm reaches the top of the frame, and the mask of 21 of its side-2 views
// became a colour label. Empty when no view stands out.
std::string SuspectMasks(const std::vector<SampleView>& views,
                         const std::vector<ViewWindow>& windows) {
  std::map<int, std::vector<double>> areas;
  for (size_t i = 0; i < views.size(); ++i)
    areas[views[i].side].push_back(cv::countNonZero(windows[i].mask));
  std::string out;
  for (auto& [side, a] : areas) {
    const double largest = *std::max_element(a.begin(), a.end());
    std::string list;
    size_t k = 0;
    for (size_t i = 0; i < views.size(); ++i) {
      if (views[i].side != side) continue;
      if (a[k++] < 0.15 * largest)
        list += (list.empty() ? "" : ", ") + std::to_string(views[i].view);
    }
    if (!list.empty()) out += "; side " + std::to_string(side) + " view(s) " + list;
  }
  if (out.empty()) return out;
  return ". The mask of" + out.substr(1) +
         " covers under 15 % of the area of its side's largest mask: the segmentation lost the "
         "rock there (see "
         "results/masks/). A rock that reaches the edge of the photo cannot be segmented: the "
         "whole rock must "
         "stay inside the frame at every angle (move the camera back or use a wider lens)";
}

Result<records::SurfaceRecord> SurfaceStage(
    const std::string& sample_dir, const std::vector<SampleView>& views,
    const std::map<int, Eigen::Isometry3d>& table_from_object, const RigCalibration& cal,
    const ReconstructOptions& opts, const std::string& sample_id,
    const ViewEvidenceCache* evidence) {
  const std::string out = ResultsPath(sample_dir, layout::kSurface);
  if (PathExists(out)) {
    return records::Read<records::SurfaceRecord>(
        out, "surface record",
        "run the reconstruction again from the surface (aggscan reconstruct --from surface)");
  }
  const auto t0 = std::chrono::steady_clock::now();
  // The masks, each kept as its window: from the evidence of an earlier
  // stage, or read (side by side).
  const int margin = WindowMarginPx(cal);
  std::vector<ViewWindow> windows(views.size());
  std::vector<std::optional<Error>> load_error(views.size());
  ParallelFor(views.size(), kWorkerThreads, [&](size_t i) {
    const SampleView& v = views[i];
    if (auto w = CachedWindow(evidence, v.image, cal.camera, margin)) {
      windows[i] = std::move(*w);
      return;
    }
    auto loaded = LoadImage(v.mask, ImageMode::kGray, opts.worker.image_limits);
    if (!loaded || loaded->empty()) {
      load_error[i] = MakeError(ErrorClass::kCorrupt,
                                "surface stage: mask " + v.mask + " is missing or unreadable (" +
                                    (loaded ? std::string("empty") : loaded.error().message) +
                                    "); delete results/" + layout::SideDirName(v.side) +
                                    "_morph2d.json to recompute the side's masks");
      return;
    }
    if (loaded->cols != cal.camera.width || loaded->rows != cal.camera.height) {
      load_error[i] =
          MakeError(ErrorClass::kCorrupt,
                    "surface stage: mask " + v.mask + " is " + std::to_string(loaded->cols) + "x" +
                        std::to_string(loaded->rows) + ", the calibration is " +
                        std::to_string(cal.camera.width) + "x" + std::to_string(cal.camera.height));
      return;
    }
    windows[i] = WindowOf(*loaded, cal.camera, margin);
  });
  for (const auto& e : load_error)
    if (e) return *e;
  std::vector<SilhouetteView> sv;
  std::vector<Eigen::Isometry3d> cam_from_object;
  for (size_t i = 0; i < views.size(); ++i) {
    SilhouetteView s;
    s.mask = windows[i].mask;
    s.camera = windows[i].camera;
    s.cam_from_object = views[i].cam_from_table * table_from_object.at(views[i].side);
    cam_from_object.push_back(s.cam_from_object);
    sv.push_back(std::move(s));
  }
  // Each side's turntable top is a floor: the rock lies on it.
  std::vector<HalfSpace> floors;
  for (const auto& [side, T] : table_from_object) {
    HalfSpace h;
    h.normal = T.linear().row(2).transpose();
    h.offset = T.translation().z();
    floors.push_back(h);
  }
  // The search region: the side-1 disc, up to the largest riprap size above it.
  const Eigen::Vector3d lo(-260, -260, -5), hi(260, 260, 320);
  auto hull = CarveVisualHull(sv, floors, Eigen::AlignedBox3d(lo, hi), opts.hull);
  if (!hull) {
    return MakeError(hull.error().cls,
                     "surface stage: " + hull.error().message + SuspectMasks(views, windows),
                     hull.error().detail);
  }
  // Views that disagree with the others: left out and the hull carved again
  // without them; a side that would lose more than a third of its views is
  // refused (the capture itself is in doubt).
  std::vector<records::ViewNote> left_out;
  json consistency = json::object();
  std::vector<SampleView> kept_views = views;
  {
    const auto tsc = std::chrono::steady_clock::now();
    const SoleCarving sc = SoleCarvingVolumes(sv, floors, hull->box, Eigen::AlignedBox3d(lo, hi));
    json per_view = json::array();
    for (size_t k = 0; k < views.size(); ++k) {
      per_view.push_back({{"side", views[k].side},
                          {"view", views[k].view},
                          {"sole_carving_mm3", sc.volume_mm3[k]}});
    }
    consistency = {{"method",
                    "per view, the volume its mask alone carves from what every other view and the "
                    "floors hold to "
                    "be rock; a view far above the others (median + 5 MAD) and above 5 % of that "
                    "agreed volume is "
                    "left out and the hull carved again"},
                   {"agreed_mm3", sc.agreed_mm3},
                   {"views", per_view},
                   {"seconds", Seconds(tsc)}};
    const std::vector<size_t> bad = DisagreeingViews(sc.volume_mm3, sc.agreed_mm3);
    if (!bad.empty()) {
      std::map<int, int> per_side_total, per_side_bad;
      for (const SampleView& v : views) ++per_side_total[v.side];
      std::string names;
      for (size_t k : bad) {
        ++per_side_bad[views[k].side];
        const double frac = sc.volume_mm3[k] / std::max(1e-9, sc.agreed_mm3 + sc.volume_mm3[k]);
        char why[256];
        std::snprintf(why, sizeof why,
                      "its mask alone carves away %.0f mm3 (%.1f %%) of what every other view "
                      "holds to be rock "
                      "(median of all views %.0f mm3): the photo or its mask lost part of the rock",
                      sc.volume_mm3[k], 100 * frac, Median(sc.volume_mm3));
        left_out.push_back(
            {views[k].side, views[k].view, why, {{"sole_carving_mm3", sc.volume_mm3[k]}}});
        names += (names.empty() ? "" : ", ") + layout::SideDirName(views[k].side) + " view " +
                 std::to_string(views[k].view);
      }
      for (const auto& [side, n] : per_side_bad) {
        if (3 * n > per_side_total[side]) {
          return MakeError(
              ErrorClass::kCorrupt,
              "surface stage: " + std::to_string(n) + " of the " +
                  std::to_string(per_side_total[side]) + " views of " + layout::SideDirName(side) +
                  " disagree with the others (" + names +
                  "): too many to leave out; check the photos and masks and re-shoot the side");
        }
      }
      StageLog(LogLevel::kWarning, kCat, sample_id,
               "surface: left out " + names +
                   ": each carves away rock every other view sees; carving again");
      std::vector<SilhouetteView> sv2;
      std::vector<ViewWindow> windows2;
      std::vector<Eigen::Isometry3d> cfo2;
      kept_views.clear();
      for (size_t k = 0; k < views.size(); ++k) {
        if (std::find(bad.begin(), bad.end(), k) != bad.end()) continue;
        sv2.push_back(sv[k]);
        windows2.push_back(windows[k]);
        cfo2.push_back(cam_from_object[k]);
        kept_views.push_back(views[k]);
      }
      sv = std::move(sv2);
      windows = std::move(windows2);
      cam_from_object = std::move(cfo2);
      const double first_s = hull->seconds;
      hull = CarveVisualHull(sv, floors, Eigen::AlignedBox3d(lo, hi), opts.hull);
      if (!hull) {
        return MakeError(hull.error().cls,
                         "surface stage (without " + names + "): " + hull.error().message,
                         hull.error().detail);
      }
      hull->seconds += first_s;
    }
  }
  const std::vector<SampleView>& used_views = kept_views;
  const double carve_s = hull->seconds;
  const auto th = std::chrono::steady_clock::now();
  const std::vector<cv::Mat> hull_silhouettes = Silhouettes(hull->mesh, cam_from_object, windows);
  const double hull_silhouettes_s = Seconds(th);
  // Photo-consistency: the hull is an upper bound; concavities are recovered
  // where the textured photos agree on a deeper surface.
  json photo = {{"enabled", opts.photo_refine}};
  double photo_s = 0;
  if (opts.photo_refine) {
    const auto tp = std::chrono::steady_clock::now();
    // The photos are used at most photo_max_width wide: the NCC patch then
    // covers the same part of the rock as at the resolution it was tuned on.
    // Decoding at half size is much faster than decoding and shrinking.
    const double scale = std::min(opts.photo.image_scale,
                                  opts.photo_max_width > 0
                                      ? static_cast<double>(opts.photo_max_width) / cal.camera.width
                                      : 1.0);
    const bool half = scale <= 0.5;
    PhotoRefineOptions po = opts.photo;
    po.image_scale = scale;
    std::vector<PhotoView> pv(used_views.size());
    std::vector<std::string> unreadable(used_views.size());
    ParallelFor(used_views.size(), kWorkerThreads, [&](size_t i) {
      auto img = LoadImage(used_views[i].image, half ? ImageMode::kGrayHalf : ImageMode::kGray,
                           opts.worker.image_limits);
      const ViewWindow& w = windows[i];
      // The window at the decoded scale (its corners and sides are even).
      const cv::Rect roi =
          half ? cv::Rect(w.roi.x / 2, w.roi.y / 2, w.roi.width / 2, w.roi.height / 2) : w.roi;
      // A half-size decode is (W + 1) / 2 wide.
      const cv::Size expected =
          half ? cv::Size((cal.camera.width + 1) / 2, (cal.camera.height + 1) / 2)
               : cv::Size(cal.camera.width, cal.camera.height);
      if (!img) {
        unreadable[i] = img.error().message;
      } else if (img->size() != expected) {
        unreadable[i] = used_views[i].image + " is not the size of its mask";
      } else {
        pv[i].image = CropPadded(*img, roi);
      }
      pv[i].camera = half ? w.camera.Resized(roi.width, roi.height) : w.camera;
      pv[i].cam_from_object = cam_from_object[i];
      pv[i].mask = w.mask;  // full scale: the refinement brings it to its working scale
    });
    if (half) po.image_scale = std::min(1.0, scale * 2);
    for (size_t i = 0; i < used_views.size(); ++i) {
      if (pv[i].image.empty()) {
        return MakeError(ErrorClass::kCorrupt,
                         "surface stage: " + unreadable[i] +
                             " (the photo refinement needs it); restore it, or turn "
                             "the refinement off");
      }
    }
    auto refined = RefineByPhotoConsistency(hull->mesh, pv, po);
    if (!refined)
      return MakeError(refined.error().cls, "surface stage: " + refined.error().message);
    if (Status st = CheckClosedManifold(refined->mesh, "the photo-refined hull"); !st) {
      return MakeError(ErrorClass::kInternal, "surface stage: " + st.error().message);
    }
    hull->mesh = std::move(refined->mesh);
    photo_s = Seconds(tp);
    photo.update({{"vertices", refined->vertices},
                  {"vertices_scored", refined->vertices_scored},
                  {"vertices_confident", refined->vertices_confident},
                  {"vertices_highlight", refined->vertices_highlight},
                  {"vertices_moved", refined->vertices_moved},
                  {"mean_displacement_mm", refined->mean_displacement_mm},
                  {"max_displacement_mm", refined->max_displacement_mm},
                  {"faces_folded", refined->faces_folded},
                  {"max_direction_passes", refined->max_direction_passes},
                  {"fold_passes", refined->fold_passes},
                  {"untangle_passes", refined->untangle_passes},
                  {"refine_s", refined->seconds},
                  {"max_depth_mm", opts.photo.max_depth_mm},
                  {"image_scale", scale}});
  }
  // Ripples a pixel or two high (the silhouettes' pixel steps, the depth
  // search's noise) inflate the area: a few Taubin passes remove them.
  if (opts.surface_smooth_iterations > 0) TaubinSmooth(&hull->mesh, opts.surface_smooth_iterations);
  const auto tc = std::chrono::steady_clock::now();
  auto colors = ColourVertices(hull->mesh, used_views, cam_from_object, windows,
                               cv::Size(cal.camera.width, cal.camera.height),
                               opts.worker.image_limits, evidence);
  if (!colors) return colors.error();
  const double colour_s = Seconds(tc);
  const auto ti = std::chrono::steady_clock::now();
  const std::vector<ViewAgreement> agreement = SilhouetteAgreement(
      Silhouettes(hull->mesh, cam_from_object, windows), hull_silhouettes, windows);
  std::vector<double> iou(agreement.size());
  for (size_t i = 0; i < agreement.size(); ++i) iou[i] = agreement[i].iou;
  const double iou_s = Seconds(ti) + hull_silhouettes_s;
  const auto te = std::chrono::steady_clock::now();
  for (auto [name, st] :
       {std::pair{layout::kMeshPly,
                  SaveMeshPly(hull->mesh, ResultsPath(sample_dir, layout::kMeshPly), &*colors)},
        std::pair{layout::kMeshObj,
                  SaveMeshObj(hull->mesh, ResultsPath(sample_dir, layout::kMeshObj), &*colors)},
        std::pair{layout::kMeshStl,
                  SaveMeshStl(hull->mesh, ResultsPath(sample_dir, layout::kMeshStl))}}) {
    if (!st) return st.error();
  }
  std::vector<records::ViewIoU> jiou;
  for (size_t i = 0; i < used_views.size(); ++i)
    jiou.push_back({used_views[i].side, used_views[i].view, iou[i], agreement[i].outline_loss});
  // A mask far larger than the model's silhouette in it (a leak, a pose that
  // does not fit) does not carve the model, but it disagrees: named.
  std::vector<records::ViewNote> disagreeing;
  {
    std::vector<double> neg;
    neg.reserve(iou.size());
    for (double x : iou) neg.push_back(-x);
    for (size_t k : HighOutliers(neg, -kIouFloor)) {
      char why[200];
      std::snprintf(why, sizeof why,
                    "its mask's IoU with the model's silhouette is %.3f, the views' median %.3f: "
                    "the mask or the "
                    "view's pose disagrees with the others; check its photo and mask",
                    iou[k], Median(iou));
      disagreeing.push_back({used_views[k].side, used_views[k].view, why, {{"iou", iou[k]}}});
    }
  }
  records::SurfaceRecord j;
  j.method = opts.photo_refine ? "visual-hull+photo" : "visual-hull";
  j.method_detail =
      std::string(
          "silhouette signed-distance field over all views of all sides in the object "
          "frame (side 1's turntable frame), each side's turntable top as a floor; "
          "marching tetrahedra") +
      (opts.photo_refine
           ? "; vertices moved inward to the depth of best multi-view NCC of tangent-plane "
             "patches, confident moves only, smoothed, folds undone"
           : "");
  j.photo_refine = photo;
  j.voxel_mm = hull->voxel_mm;
  j.vertices = static_cast<int>(hull->mesh.vertices.size());
  j.faces = static_cast<int>(hull->mesh.faces.size());
  j.views = static_cast<int>(used_views.size());
  j.silhouette_iou = std::move(jiou);
  j.views_left_out = std::move(left_out);
  j.consistency = consistency;
  j.views_disagreeing = std::move(disagreeing);
  j.files = {{"ply", layout::kMeshPly}, {"obj", layout::kMeshObj}, {"stl", layout::kMeshStl}};
  j.timings_s = {{"carve", carve_s},
                 {"photo_refine", photo_s},
                 {"colour", colour_s},
                 {"silhouette_check", iou_s},
                 {"export", Seconds(te)}};
  j.stage_seconds = Seconds(t0);
  if (Status s = records::Write(out, j); !s) return s.error();
  StageLog(LogLevel::kInfo, kCat, sample_id,
           "surface: " + std::to_string(hull->mesh.faces.size()) + " faces at " +
               std::to_string(hull->voxel_mm) + " mm in " + std::to_string(Seconds(t0)) + " s");
  return j;
}

// --- stage: morphology ---------------------------------------------------

std::string Sha256Hex(const std::string& text) {
  unsigned char digest[EVP_MAX_MD_SIZE];
  unsigned int len = 0;
  if (EVP_Digest(text.data(), text.size(), digest, &len, EVP_sha256(), nullptr) != 1) return "";
  std::string hex;
  hex.reserve(size_t{2} * len);
  static const char* const kHex = "0123456789abcdef";
  for (unsigned int i = 0; i < len; ++i) {
    hex += kHex[digest[i] >> 4];
    hex += kHex[digest[i] & 15];
  }
  return hex;
}

json StatsJson(const std::vector<double>& v) { return records::StatsToJson(ComputeStats(v)); }

// The rock's row in the state directory's library, with its description
// (sample.json's "meta": operator, lot, material and the mass from it).
Status AppendLibraryRow(const std::string& state_dir, const std::string& sample_dir,
                        const records::Morphology& morphology) {
  if (state_dir.empty()) return OkStatus();
  json meta = json::object();
  const std::string rec_path = sample_dir + "/" + layout::kSampleRecord;
  if (PathExists(rec_path)) {
    // A record that does not read leaves the description columns empty; the
    // figures are still the rock's.
    if (auto rec = jsonio::ReadFile(rec_path, "sample record"); rec && rec->is_object())
      meta = rec->value("meta", json::object());
  }
  return library_csv::Upsert(state_dir, morphology.sample_id,
                             library_csv::Row(morphology.ToJson(), meta));
}

}  // namespace

bool ParsePosesPath(const std::string& name, PosesPath* out) {
  for (PosesPath p : {PosesPath::kAuto, PosesPath::kTurntable, PosesPath::kSfm}) {
    if (name == PosesPathName(p)) {
      *out = p;
      return true;
    }
  }
  return false;
}

const char* PosesPathName(PosesPath p) {
  switch (p) {
    case PosesPath::kAuto:
      return "auto";
    case PosesPath::kTurntable:
      return "turntable";
    case PosesPath::kSfm:
      return "sfm";
  }
  return "?";
}

Result<records::Morphology> ReadMorphologyRecord(const std::string& sample_dir) {
  const std::string path = ResultsPath(sample_dir, layout::kMorphology);
  if (!PathExists(path)) {
    return MakeError(ErrorClass::kNotFound,
                     "no results yet for " + layout::SampleIdOfDir(sample_dir) +
                         " (the worker has not finished it; see its state and the worker log)");
  }
  return records::Read<records::Morphology>(
      path, "results",
      "run the reconstruction again from the morphology (aggscan reconstruct --from morphology)");
}

Result<json> ReadMorphology(const std::string& sample_dir) {
  auto m = ReadMorphologyRecord(sample_dir);
  if (!m) return m.error();
  return m->ToJson();
}

namespace {

// What the stages of one run of the sample job share: the setup read before
// the first stage and what each stage hands on (loaded from its record when
// the stage was kept).
struct SampleRun {
  SampleRun(const std::string& d, const ReconstructOptions& o) : dir(d), opts(o) {}
  std::string dir, id;
  const ReconstructOptions& opts;
  std::chrono::steady_clock::time_point t_all = std::chrono::steady_clock::now();
  std::string morph_path;
  std::vector<int> sides;
  std::optional<Config> sample_cfg;  // the config the sample was armed with
  RigConfig rig;
  bool use_sfm = false;
  cv::Size image_size;
  std::string mask_method = "classical";  // what the side jobs ran
  double masks_s = 0;
  json timings = json::object();
  std::optional<RigCalibration> cal;
  SfmPosesInput sfm_setup;
  std::map<int, std::vector<SampleView>> side_views;
  std::map<int, std::string> poses_methods;
  std::vector<SampleView> all_views;
  records::StitchRecord stitch;
  records::SurfaceRecord surface;
  std::optional<ViewEvidenceCache> evidence;  // once the calibration is known
};

// The sample's view evidence, kept from the first decode of each photo for
// the stages after it; null until the calibration is known.
ViewEvidenceCache* EvidenceOf(SampleRun& r) {
  if (!r.cal) return nullptr;
  if (!r.evidence) {
    StitchStageInput sin;
    sin.calibration = &*r.cal;
    sin.rig = r.rig;
    r.evidence.emplace(StitchEvidenceOptions(sin, WindowMarginPx(*r.cal)));
  }
  return &*r.evidence;
}

// The image size of the sample's photos, from the first readable mask.
Status ReadImageSize(SampleRun& r) {
  auto side1 = ReadSideResult(r.dir, r.sides[0]);
  if (!side1) return side1.error();
  r.mask_method = side1->mask_method;
  for (const records::View2D& v : side1->views) {
    if (!v.ok) continue;
    auto m = LoadImage(ResultsPath(r.dir, v.mask), ImageMode::kGray, r.opts.worker.image_limits);
    if (m) {
      r.image_size = m->size();
      return OkStatus();
    }
  }
  return MakeError(ErrorClass::kCorrupt,
                   "sample " + r.id + ": no readable mask in " + layout::SideDirName(r.sides[0]));
}

// The SfM setup (camera held or estimated) once the calibration is known.
void SetUpSfm(SampleRun& r) {
  r.sfm_setup.rig = r.rig;
  if (r.cal) {
    r.sfm_setup.fixed_camera = r.cal->camera;
    r.sfm_setup.camera_source =
        r.cal->method == "sfm" ? "sfm (" + r.cal->source + ")" : "calibration";
    r.sfm_setup.calibration = &*r.cal;
    return;
  }
  r.sfm_setup.camera_source = "sfm (estimated)";
  // The lens's nominal focal as the hint, held while COLMAP poses the ring
  // (the config's lens, or the sim's). Without one COLMAP starts from its
  // default, refines it, and the ring checks judge.
  if (r.sample_cfg) {
    if (auto hint = FocalHintFromConfig(*r.sample_cfg, r.image_size.width)) {
      r.sfm_setup.expected_focal_px = hint->focal_px;
      r.sfm_setup.focal_hint_source = hint->source;
      r.sfm_setup.camera_source = "sfm (focal hint held)";
    }
  }
}

Status PosesOfSide(SampleRun& r, int side) {
  if (r.use_sfm && !r.cal && side != r.sides[0]) {
    // Every side in one camera model (the surface stage has one): the first
    // side's SfM camera, held fixed.
    auto first = SfmCalibrationOfSide(r.dir, r.sides[0]);
    if (!first) return first.error();
    r.sfm_setup.fixed_camera = first->camera;
    r.sfm_setup.camera_source = "sfm " + layout::SideDirName(r.sides[0]);
  }
  std::string method;
  auto v = PosesStage(r.dir, side, r.cal ? &*r.cal : nullptr, r.use_sfm ? &r.sfm_setup : nullptr,
                      r.opts, &r.timings, &method, EvidenceOf(r));
  r.poses_methods[side] = method;
  if (!v) return v.error();
  r.side_views[side] = *v;
  r.all_views.insert(r.all_views.end(), v->begin(), v->end());
  return OkStatus();
}

// SfM without a rig calibration: the first side's camera is the sample's.
Status CalibrationFromSfm(SampleRun& r) {
  const std::string out = ResultsPath(r.dir, layout::kCalibrationUsed);
  if (!PathExists(out)) {
    auto c = SfmCalibrationOfSide(r.dir, r.sides[0]);
    if (!c) return c.error();
    json j = CalibrationToJson(*c);
    j["origin"] = ResultsPath(r.dir, layout::PosesName(r.sides[0]));
    j["stage_seconds"] = 0.0;
    if (Status s = WriteJson(out, j); !s) return s;
  }
  auto j = ReadJson(out, "calibration record");
  if (!j) return j.error();
  auto cal = CalibrationFromJson(*j, out);
  if (!cal) return cal.error();
  r.timings["calibration_s"] = 0.0;
  r.cal = std::move(*cal);
  return OkStatus();
}

Status StitchSides(SampleRun& r) {
  StitchStageInput sin;
  sin.sample_dir = r.dir;
  sin.calibration = &*r.cal;
  // The background labels are the ones configured when the sample was armed.
  sin.rig = r.rig;
  sin.evidence = EvidenceOf(r);
  sin.views = r.side_views;
  const std::string stitch_path = ResultsPath(r.dir, layout::kStitch);
  if (!PathExists(stitch_path)) {
    auto st = RunStitchStage(sin);
    if (!st) return st.error();
    if (Status s = records::Write(stitch_path, *st); !s) return s;
  }
  auto stitch = records::Read<records::StitchRecord>(
      stitch_path, "stitch record",
      "run the reconstruction again from the stitch (aggscan reconstruct --from stitch)");
  if (!stitch) return stitch.error();
  r.stitch = std::move(*stitch);
  for (int side : r.sides) {
    if (!r.stitch.table_from_object.count(side)) {
      return MakeError(ErrorClass::kCorrupt, stitch_path + " has no transform for " +
                                                 layout::SideDirName(side) +
                                                 "; run the reconstruction again from the stitch "
                                                 "(aggscan reconstruct --from stitch)");
    }
  }
  r.timings["stitch_s"] = r.stitch.stage_seconds;
  return OkStatus();
}

Status SurfaceOfSample(SampleRun& r) {
  auto surface = SurfaceStage(r.dir, r.all_views, r.stitch.table_from_object, *r.cal, r.opts, r.id,
                              EvidenceOf(r));
  if (!surface) return surface.error();
  r.surface = std::move(*surface);
  r.timings["surface_s"] = r.surface.stage_seconds;
  r.timings["surface_detail_s"] = r.surface.timings_s;
  return OkStatus();
}

Status MorphologyStage(SampleRun& r) {
  if (PathExists(r.morph_path)) return OkStatus();  // kept: the library row is added by the job
  // The masks' and 2D figures' time: their stages' own (the side jobs ran
  // most of them, in other processes).
  auto ledger = ReadStageLedger(r.dir);
  if (!ledger) return ledger.error();
  for (const auto& [name, e] : (*ledger)["stages"].items()) {
    if (name == "2d" || name.rfind("masks ", 0) == 0) r.masks_s += e.value("seconds", 0.0);
  }
  const auto t_m = std::chrono::steady_clock::now();
  auto mesh = LoadMesh(ResultsPath(r.dir, layout::kMeshPly), "mm");
  if (!mesh) return mesh.error();
  const Status watertight = CheckClosedManifold(*mesh, "reconstructed mesh");
  const MeshProps p = ComputeMeshProps(*mesh);
  for (double v : {p.volume_mm3, p.surface_area_mm2, p.a_mm, p.b_mm, p.c_mm, p.sphericity}) {
    if (!std::isfinite(v)) {
      return MakeError(ErrorClass::kInternal,
                       "morphology stage: the reconstructed mesh's figures are not finite "
                       "numbers; delete results/ to reconstruct again and report it");
    }
  }
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  for (const auto& v : mesh->vertices) centroid += Eigen::Vector3d(v.data());
  centroid /= std::max<size_t>(1, mesh->vertices.size());

  // Every view's 2D figures, in mm at the rock's depth in that view.
  std::map<std::pair<int, int>, const SampleView*> by_view;
  for (const SampleView& v : r.all_views) by_view[{v.side, v.view}] = &v;
  records::Morphology out;
  std::map<int, records::SideResult> side_results;
  std::map<int, std::map<std::string, std::vector<double>>> per_side;
  std::map<std::string, std::vector<double>> overall;
  for (int side : r.sides) {
    auto sr = ReadSideResult(r.dir, side);
    if (!sr) return sr.error();
    for (const records::View2D& v : sr->views) {
      if (!v.ok) continue;
      records::MorphView2D jv;
      jv.side = side;
      jv.view = v.view;
      auto it = by_view.find({side, v.view});
      if (it != by_view.end()) {
        const Eigen::Vector3d pc =
            it->second->cam_from_table * r.stitch.table_from_object.at(side) * centroid;
        jv.mm_per_px_at_rock = pc.z() / std::sqrt(r.cal->camera.fx * r.cal->camera.fy);
        jv.angle_deg = it->second->angle_deg;
      }
      jv.fer_2d = v.fer_2d;
      jv.circularity = v.circularity;
      jv.l_max_px = v.l_max_px;
      jv.l_min_px = v.l_min_px;
      jv.area_px = v.area_px;
      jv.perimeter_px = v.perimeter_px;
      jv.l_max_mm = v.l_max_px * jv.mm_per_px_at_rock;
      jv.l_min_mm = v.l_min_px * jv.mm_per_px_at_rock;
      for (const auto& [k, x] : {std::pair<const char*, double>{"fer_2d", jv.fer_2d},
                                 {"circularity", jv.circularity},
                                 {"l_max_mm", jv.l_max_mm},
                                 {"l_min_mm", jv.l_min_mm}}) {
        per_side[side][k].push_back(x);
        overall[k].push_back(x);
      }
      out.views_2d.push_back(jv);
    }
    side_results[side] = std::move(*sr);
  }
  json stats = json::object();
  auto block = [&](std::map<std::string, std::vector<double>>& vals) {
    json b = json::object();
    for (const char* k : {"fer_2d", "circularity", "l_max_mm", "l_min_mm"})
      b[k] = StatsJson(vals[k]);
    return b;
  };
  for (int side : r.sides) stats[layout::SideDirName(side)] = block(per_side[side]);
  stats["overall"] = block(overall);
  stats["std_kind"] = "sample";
  const double fer2d_mean = ComputeStats(overall["fer_2d"]).mean;
  const double circ_mean = ComputeStats(overall["circularity"]).mean;
  const double lo = std::min(p.c_over_b, p.b_over_a), hi = std::max(p.c_over_b, p.b_over_a);

  std::vector<double> ious, losses;
  for (const records::ViewIoU& e : r.surface.silhouette_iou) {
    ious.push_back(e.iou);
    if (e.outline_loss) losses.push_back(*e.outline_loss);
  }
  const json iou_json = r.surface.SilhouetteIoUJson();
  const Stats iou = ComputeStats(ious);
  const Stats loss = ComputeStats(losses);
  auto opt = [](const auto& o) { return o ? json(*o) : json(); };
  json quality = {
      {"silhouette_iou_mean", iou.mean},
      {"silhouette_iou_min", iou.min},
      {"silhouette_iou_note",
       "IoU of each mask with the reconstructed surface's silhouette: an estimate of mask and pose "
       "consistency (1 = every mask agrees with all the others)"},
      {"outline_loss_mean", losses.empty() ? json() : json(loss.mean)},
      {"outline_loss_max", losses.empty() ? json() : json(loss.max)},
      {"outline_loss_note",
       "fraction of the carved hull's silhouette, per view, that the surface no longer covers: "
       "how far the photo refinement moved the outline the masks agree on inward (0 = not at "
       "all)"},
      {"calibration_reprojection_rms_px", r.cal->reprojection_rms_px},
      {"stitch_rms_mm", opt(r.stitch.rms_mm)},
      {"stitch_max_mm", opt(r.stitch.max_mm)},
      {"stitch_silhouette_deficit", opt(r.stitch.silhouette_deficit)},
      {"scale_residual_mm", opt(r.stitch.scale_residual_mm)},
      {"scale_reference", opt(r.stitch.scale_reference)},
      {"watertight", watertight.ok()}};
  // What the figures cannot be trusted for, with the reason: never a
  // confident number from poor masks or an unconfirmed stitch.
  quality["flags"] = QualityFlags(quality, r.stitch.ToJson(), iou_json);
  out.confident = quality["flags"].empty();
  for (const json& f : quality["flags"]) {
    StageLog(LogLevel::kWarning, kCat, r.id, "not confident: " + f.value("reason", ""));
  }
  r.timings["masks_and_2d_s"] = r.masks_s;
  r.timings["morphology_s"] = Seconds(t_m);
  double total = r.masks_s;
  for (const char* k : {"calibration_s", "stitch_s", "surface_s", "morphology_s"})
    total += r.timings.value(k, 0.0);
  for (int side : r.sides)
    total += r.timings.value("poses_" + layout::SideDirName(side) + "_s", 0.0);
  r.timings["total"] = total;
  r.timings["this_run_wall"] = Seconds(r.t_all);

  // One method when every side agrees, else each side's.
  std::string poses_method;
  for (const auto& [side, m] : r.poses_methods) {
    if (poses_method.empty()) poses_method = m;
    if (m != r.poses_methods.begin()->second) {
      poses_method.clear();
      for (const auto& [s2, m2] : r.poses_methods) {
        poses_method += (poses_method.empty() ? "" : ", ") + layout::SideDirName(s2) + ": " + m2;
      }
      break;
    }
  }
  // Each side's poses figures (the method's own: SfM's registration and
  // scale, or the bundle adjustment's).
  for (int side : r.sides) {
    auto pj = ReadPoses(r.dir, side);
    if (!pj) return pj.error();
    records::PosesSummary ps;
    ps.side = side;
    ps.method = pj->method;
    json& e = ps.figures;
    if (pj->sfm.is_object()) {
      const json& s = pj->sfm;
      const json& sc = pj->scale.is_object() ? pj->scale : json::object();
      e.update({{"registered_views", s.value("registered_views", 0)},
                {"input_views", s.value("input_views", 0)},
                {"mean_reprojection_px", s.value("mean_reprojection_px", 0.0)},
                {"checks_passed", s.value("checks_passed", false)},
                {"camera_source", s.value("camera_source", "")},
                {"scale_reference", sc.value("reference", "")},
                {"scale_residual_mm", sc.value("residual_mm", 0.0)},
                {"colmap_s", s.value("colmap_s", 0.0)},
                {"model_dir", s.value("model_dir", "")}});
    } else if (pj->bundle_adjustment.is_object()) {
      const json& ba = pj->bundle_adjustment;
      e.update({{"ba_refined", ba.value("refined", false)},
                {"ba_final_rms_px", ba.value("final_rms_px", 0.0)}});
    }
    out.poses.push_back(std::move(ps));
  }
  // Everything left out or doubtful, with what to do: a figure computed
  // without some views is still a figure, but the operator must know.
  std::vector<std::string>& warnings = out.warnings;
  for (const auto& [side, sr] : side_results) {
    for (const std::string* w : {&sr.image_problems, &sr.mask_problems}) {
      if (!w->empty()) warnings.push_back(layout::SideDirName(side) + ": " + *w);
    }
  }
  for (const int side : r.sides) {
    auto pj = ReadPoses(r.dir, side);
    if (!pj) continue;
    const json left = pj->extra.value("views_left_out", json::array());
    for (const json& l : left) {
      warnings.push_back(layout::SideDirName(side) + " view " + std::to_string(l.value("view", 0)) +
                         " left out of the poses: " + l.value("reason", ""));
    }
  }
  for (const records::ViewNote& v : r.surface.views_left_out) {
    warnings.push_back(layout::SideDirName(v.side) + " view " + std::to_string(v.view) +
                       " left out of the model: " + v.reason);
  }
  for (const records::ViewNote& v : r.surface.views_disagreeing) {
    warnings.push_back(layout::SideDirName(v.side) + " view " + std::to_string(v.view) +
                       " disagrees with the model: " + v.reason);
  }
  out.morphology_3d = MeshPropsJson(p);
  out.morphology_3d["watertight"] = watertight.ok();
  if (!watertight) out.morphology_3d["watertight_problem"] = watertight.error().message;
  const jsonio::Source self{"morphology", r.morph_path, ""};
  if (Status s = out.Read3D(self); !s) return s;
  out.sample_id = r.id;
  out.created_utc = NowUtcString();
  out.units =
      "mm, mm2, mm3, degrees; ratios dimensionless; 2D lengths in px and in mm at the rock's depth";
  out.methods = {{"calibration", r.cal->method},
                 {"poses", poses_method},
                 {"stitch", r.stitch.method},
                 {"surface", r.surface.method},
                 {"masks", r.mask_method}};
  out.stats_2d = stats;
  out.comparison_2d_3d = {{"fer_3d", p.fer_3d},
                          {"fer_2d_mean", fer2d_mean},
                          {"fer_2d_mean_over_fer_3d", p.fer_3d > 0 ? fer2d_mean / p.fer_3d : 0.0},
                          {"ratio_c_b", p.c_over_b},
                          {"ratio_b_a", p.b_over_a},
                          {"fer_2d_mean_between_c_b_and_b_a", fer2d_mean >= lo && fer2d_mean <= hi},
                          {"sphericity", p.sphericity},
                          {"circularity_mean", circ_mean},
                          {"circularity_mean_minus_sphericity", circ_mean - p.sphericity}};
  out.quality = quality;
  out.timings_s = r.timings;
  out.software = {{"version", SoftwareVersion()}};
  // The config in effect, defaults included, as one text: two results with
  // the same hash were computed with the same settings. A sample without its
  // config.toml (made by hand) was computed with the defaults.
  out.software["config_sha256"] = Sha256Hex(ConfigToToml(r.sample_cfg ? *r.sample_cfg : Config{}));
  out.software["config_source"] =
      r.sample_cfg ? std::string("sample ") + layout::kConfigCopy : std::string("defaults");
  out.files = {{"mesh_ply", layout::kMeshPly},
               {"mesh_obj", layout::kMeshObj},
               {"mesh_stl", layout::kMeshStl},
               {"stitch", layout::kStitch},
               {"surface", layout::kSurface}};
  if (Status s = records::Write(r.morph_path, out); !s) return s;
  StageLog(LogLevel::kNotice, kCat, r.id,
           "reconstructed: V " + std::to_string(static_cast<long>(p.volume_mm3)) + " mm3, a/b/c " +
               std::to_string(p.a_mm) + "/" + std::to_string(p.b_mm) + "/" +
               std::to_string(p.c_mm) + " mm");
  return AppendLibraryRow(r.opts.state_dir, r.dir, out);
}

// The fingerprints of the stages (pipeline/core/stage_runner.h): each stage's
// options and inputs, the stages it reads by their own fingerprints.
struct SampleFingerprints {
  std::map<int, std::string> masks;  // per side
  std::string two_d, calibration;
  std::map<int, std::string> poses;
  std::string stitch, surface, morphology;
};

Result<std::string> CalibrationFingerprint(const SampleRun& r) {
  Fingerprint f;
  f.Add("stage", std::string_view("calibration"));
  // Which calibration (the sample's own copy or the rig's), not where the
  // sample lies: a sample moved or copied elsewhere keeps its stages.
  std::string path = r.dir + "/" + layout::kCalibrationCopy;
  std::string source = "sample";
  if (!PathExists(path) && !r.opts.state_dir.empty()) {
    path = CalibrationPath(r.opts.state_dir);
    source = "state_dir";
  }
  f.Add("source", std::string_view(source));
  if (Status s = f.AddFile("calibration", path); !s) return s.error();
  return f.Hex();
}

// `masks`: every side's masks and the 2D figures (AddMasksAndTwoDStages).
Result<SampleFingerprints> SampleJobFingerprints(const SampleRun& r,
                                                 const SampleFingerprints& masks) {
  SampleFingerprints fp;
  fp.masks = masks.masks;
  fp.two_d = masks.two_d;
  Fingerprint config;  // the armed config: labels and markers (poses, stitch), camera
  if (Status s = config.AddFile("config", r.dir + "/" + layout::kConfigCopy); !s) return s.error();
  if (!r.use_sfm || HasCalibration(r.dir, r.opts)) {
    auto c = CalibrationFingerprint(r);
    if (!c) return c.error();
    fp.calibration = *c;
  }
  Fingerprint stitch;
  stitch.Add("stage", std::string_view("stitch")).Add("config", std::string_view(config.Hex()));
  for (int side : r.sides) {
    Fingerprint f;
    f.Add("stage", std::string_view("poses"))
        .Add("side", std::string_view(std::to_string(side)))
        .Add("masks", std::string_view(fp.masks[side]))
        .Add("config", std::string_view(config.Hex()))
        .Add("path", std::string_view(r.use_sfm ? "sfm" : "turntable"));
    if (r.use_sfm) {
      f.Add("sfm", OptionsJson(r.opts.sfm));
      // Without a rig calibration every later side is posed with the first
      // side's SfM camera.
      if (fp.calibration.empty() && side != r.sides[0])
        f.Add("first side", std::string_view(fp.poses[r.sides[0]]));
    } else {
      f.Add("bundle_adjust", json(r.opts.bundle_adjust));
      if (r.opts.bundle_adjust) f.Add("ba", OptionsJson(r.opts.ba));
      // A hand-turned side's angles come from these.
      f.Add("hand", json{{"min_references", r.opts.hand.min_references},
                         {"max_rms_px", r.opts.hand.max_rms_px},
                         {"grid_step_deg", r.opts.hand.grid_step_deg},
                         {"min_sharpness_ratio", r.opts.hand_min_sharpness_ratio}});
    }
    f.Add("calibration", std::string_view(fp.calibration));
    fp.poses[side] = f.Hex();
    stitch.Add("poses", std::string_view(fp.poses[side]));
  }
  if (fp.calibration.empty()) {
    fp.calibration = Fingerprint()
                         .Add("stage", std::string_view("calibration from sfm"))
                         .Add("poses", std::string_view(fp.poses[r.sides[0]]))
                         .Hex();
    stitch.Add("calibration", std::string_view(fp.calibration));
  }
  fp.stitch = stitch.Hex();
  fp.surface = Fingerprint()
                   .Add("stage", std::string_view("surface"))
                   .Add("stitch", std::string_view(fp.stitch))
                   .Add("hull", OptionsJson(r.opts.hull))
                   .Add("photo_refine", json(r.opts.photo_refine))
                   .Add("photo", r.opts.photo_refine ? OptionsJson(r.opts.photo) : json())
                   .Add("photo_max_width", json(r.opts.photo_max_width))
                   .Add("surface_smooth_iterations", json(r.opts.surface_smooth_iterations))
                   .Hex();
  fp.morphology = Fingerprint()
                      .Add("stage", std::string_view("morphology"))
                      .Add("surface", std::string_view(fp.surface))
                      .Add("2d", std::string_view(fp.two_d))
                      .Hex();
  return fp;
}

// The masks stages of every side and the 2D figures over them ("2d", which
// then runs `then`, if given); their fingerprints.
Result<SampleFingerprints> AddMasksAndTwoDStages(const std::string& sample_dir,
                                                 const std::vector<int>& sides,
                                                 const WorkerOptions& wo,
                                                 const std::function<Status()>& then,
                                                 std::vector<StageDecl>* stages) {
  SampleFingerprints fp;
  Fingerprint two_d;
  two_d.Add("stage", std::string_view("2d"));
  for (int side : sides) {
    auto d = MasksStage(sample_dir, side, wo);
    if (!d) return d.error();
    fp.masks[side] = d->fingerprint;
    two_d.Add("masks", std::string_view(d->fingerprint));
    stages->push_back(std::move(*d));
  }
  fp.two_d = two_d.Hex();
  stages->push_back({"2d",
                     "",
                     fp.two_d,
                     {"results/morph2d.json"},
                     {},
                     [sample_dir, wo, then](StageContext&) -> Status {
                       if (Status s = ProcessSample(sample_dir, wo); !s) return s;
                       return then ? then() : OkStatus();
                     }});
  return fp;
}

Status TwoDFiguresStages(const std::string& sample_dir, const WorkerOptions& wo) {
  auto sides = CapturedSides(sample_dir);
  if (!sides) return sides.error();
  std::vector<StageDecl> stages;
  if (auto fp = AddMasksAndTwoDStages(sample_dir, *sides, wo, nullptr, &stages); !fp) {
    return fp.error();
  }
  StageRunOptions ro;
  ro.cancel = wo.cancel;
  auto run = RunStages(sample_dir, stages, ro);
  return run ? OkStatus() : Status(run.error());
}

Status ReconstructSampleStages(const std::string& sample_dir, const ReconstructOptions& opts) {
  SampleRun r(sample_dir, opts);
  r.id = layout::SampleIdOfDir(sample_dir);
  r.morph_path = ResultsPath(sample_dir, layout::kMorphology);
  auto sides = CapturedSides(sample_dir);
  if (!sides) return sides.error();
  r.sides = *sides;
  // The config the sample was armed with: its background labels (the SfM
  // path's scale, the stitch stage's check) and its camera.
  if (const std::string cfg_path = sample_dir + "/" + layout::kConfigCopy; PathExists(cfg_path)) {
    std::vector<ConfigProblem> problems;
    auto c = LoadConfigFile(cfg_path, &problems);
    if (!c) {
      return MakeError(ErrorClass::kInvalidConfig,
                       "sample " + r.id + ": its " + cfg_path + " does not load (" +
                           c.error().message +
                           "); it is written at arm time and must not be edited");
    }
    r.sample_cfg = std::move(*c);
    r.rig = r.sample_cfg->rig;
  }
  const bool moving_camera = r.sample_cfg && r.sample_cfg->capture.mode == "moving_camera";
  r.sfm_setup.moving_camera = moving_camera;
  auto use_sfm = ChoosePosesPath(sample_dir, opts, moving_camera);
  if (!use_sfm) return use_sfm.error();
  r.use_sfm = *use_sfm;
  WorkerOptions wo = opts.worker;
  if (!wo.cancel) wo.cancel = opts.cancel;
  std::vector<StageDecl> stages;
  auto masks = AddMasksAndTwoDStages(
      sample_dir, r.sides, wo, [&] { return ReadImageSize(r); }, &stages);
  if (!masks) return masks.error();
  auto fp = SampleJobFingerprints(r, *masks);
  if (!fp) return fp.error();
  const bool cal_first = !r.use_sfm || HasCalibration(sample_dir, opts);
  auto calibration_stage = [&](bool from_sfm) {
    return StageDecl{"calibration",
                     "",
                     fp->calibration,
                     {std::string("results/") + layout::kCalibrationUsed},
                     {},
                     [&, from_sfm](StageContext&) -> Status {
                       if (from_sfm) return CalibrationFromSfm(r);
                       auto c = CalibrationStage(sample_dir, opts, r.image_size, &r.timings);
                       if (!c) return c.error();
                       r.cal = std::move(*c);
                       if (r.use_sfm) SetUpSfm(r);
                       return OkStatus();
                     }};
  };
  if (cal_first) stages.push_back(calibration_stage(false));
  for (int side : r.sides) {
    stages.push_back({"poses side " + std::to_string(side),
                      "poses",
                      fp->poses[side],
                      {"results/" + layout::PosesName(side)},
                      // COLMAP's workspace (work/side<N>/sfm) stays: each of its
                      // steps is kept or redone by its own fingerprint.
                      {"results/" + SfmModelDirName(side)},
                      [&, side](StageContext&) -> Status {
                        if (r.use_sfm && !r.cal && side == r.sides[0]) SetUpSfm(r);
                        return PosesOfSide(r, side);
                      }});
  }
  if (!cal_first) stages.push_back(calibration_stage(true));
  stages.push_back({"stitch",
                    "",
                    fp->stitch,
                    {std::string("results/") + layout::kStitch},
                    {},
                    [&](StageContext&) { return StitchSides(r); }});
  stages.push_back(
      {"surface",
       "",
       fp->surface,
       {std::string("results/") + layout::kSurface, std::string("results/") + layout::kMeshPly,
        std::string("results/") + layout::kMeshObj, std::string("results/") + layout::kMeshStl},
       {},
       [&](StageContext&) { return SurfaceOfSample(r); }});
  stages.push_back({"morphology",
                    "",
                    fp->morphology,
                    {std::string("results/") + layout::kMorphology},
                    {},
                    [&](StageContext&) { return MorphologyStage(r); }});

  StageRunOptions ro;
  ro.from = opts.from_stage;
  ro.cancel = opts.cancel;
  // The masks' time for the record: the side jobs' (and this run's) seconds.
  auto run = RunStages(sample_dir, stages, ro);
  if (!run) return run.error();
  auto m = ReadMorphologyRecord(sample_dir);
  if (!m) return m.error();
  return AppendLibraryRow(opts.state_dir, sample_dir, *m);
}

}  // namespace

Status ReconstructSample(const std::string& sample_dir, const ReconstructOptions& opts) {
  return RunStage("reconstruction", [&] { return ReconstructSampleStages(sample_dir, opts); });
}

Status TwoDFigures(const std::string& sample_dir, const WorkerOptions& opts) {
  return RunStage("2D figures", [&] { return TwoDFiguresStages(sample_dir, opts); });
}

}  // namespace aggscan
