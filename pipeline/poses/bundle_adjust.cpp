#include "pipeline/poses/bundle_adjust.h"

#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <numeric>
#include <set>

#include "pipeline/core/geometry.h"

namespace aggscan {

namespace {

constexpr double kPi = 3.14159265358979323846;

double Seconds(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

std::string Fmt(const char* f, double v) {
  char buf[64];
  std::snprintf(buf, sizeof buf, f, v);
  return buf;
}

// Lens parameters that may be refined, in this order.
enum Lens { kFx, kFy, kCx, kCy, kK1, kK2, kLensParams };

// Distorted pixel of table point X seen at turntable angle `angle_deg`:
// cam = Exp(rig[0..2]) * (R0 * Rz(angle) * X + t0) + rig[3..5], then the
// OpenCV lens model (rig_calibration.h) with the refinable fx, fy, cx, cy, k1,
// k2 and the calibration's fixed p1, p2, k3.
struct ReprojectionCost {
  ReprojectionCost(const Eigen::Vector2d& observed, const Eigen::Matrix3d& R0,
                   const Eigen::Vector3d& t0, const CameraModel& cam)
      : obs(observed), R0(R0), t0(t0), p1(cam.p1), p2(cam.p2), k3(cam.k3) {}

  template <typename T>
  bool operator()(const T* angle_deg, const T* rig, const T* lens, const T* X, T* residual) const {
    using std::cos, std::sin;
    const T a = angle_deg[0] * T(kPi / 180.0);
    const T c = cos(a), s = sin(a);
    const T q[3] = {c * X[0] - s * X[1], s * X[0] + c * X[1], X[2]};
    T p[3];
    for (int r = 0; r < 3; ++r)
      p[r] = T(R0(r, 0)) * q[0] + T(R0(r, 1)) * q[1] + T(R0(r, 2)) * q[2] + T(t0(r));
    T pc[3];
    ceres::AngleAxisRotatePoint(rig, p, pc);
    for (int r = 0; r < 3; ++r) pc[r] += rig[3 + r];
    if (pc[2] <= T(1e-6)) return false;
    const T x = pc[0] / pc[2], y = pc[1] / pc[2];
    const T r2 = x * x + y * y;
    const T radial = T(1) + lens[kK1] * r2 + lens[kK2] * r2 * r2 + T(k3) * r2 * r2 * r2;
    const T xd = x * radial + T(2 * p1) * x * y + T(p2) * (r2 + T(2) * x * x);
    const T yd = y * radial + T(p1) * (r2 + T(2) * y * y) + T(2 * p2) * x * y;
    residual[0] = lens[kFx] * xd + lens[kCx] - T(obs.x());
    residual[1] = lens[kFy] * yd + lens[kCy] - T(obs.y());
    return true;
  }

  Eigen::Vector2d obs;
  Eigen::Matrix3d R0;
  Eigen::Vector3d t0;
  double p1, p2, k3;
};

// (angle - measured) / sigma: the turntable's own reading as a weak prior.
struct AnglePrior {
  double measured, sigma;
  template <typename T>
  bool operator()(const T* angle, T* residual) const {
    residual[0] = (angle[0] - T(measured)) / T(sigma);
    return true;
  }
};

// The rig delta over its prior sigmas (rotation in radians, translation in mm).
struct RigPrior {
  double sigma_rad, sigma_mm;
  template <typename T>
  bool operator()(const T* rig, T* residual) const {
    for (int i = 0; i < 3; ++i) residual[i] = rig[i] / T(sigma_rad);
    for (int i = 3; i < 6; ++i) residual[i] = rig[i] / T(sigma_mm);
    return true;
  }
};

struct Observation {
  int view = 0;        // input view index
  int point = 0;       // index into the points
  Eigen::Vector2d uv;  // observed distorted pixel
};

}  // namespace

std::string BundleAdjustOptions::Check() const {
  std::string e;
  auto bad = [&](bool cond, const std::string& what) {
    if (cond) e += (e.empty() ? "" : "; ") + what;
  };
  bad(!(angle_prior_deg > 0), "angle_prior_deg must be > 0 (the turntable's 1-sigma accuracy)");
  bad(!(rig_prior_deg > 0) || !(rig_prior_mm > 0), "rig_prior_deg and rig_prior_mm must be > 0");
  bad(!(huber_px > 0), "huber_px must be > 0");
  bad(!(outlier_px > huber_px), "outlier_px must exceed huber_px");
  bad(min_tracks < 1 || min_views < 2, "min_tracks must be >= 1 and min_views >= 2");
  bad(max_iterations < 1 || num_threads < 1 || threads < 1,
      "max_iterations, num_threads and threads must be >= 1");
  bad(!(features.image_scale > 0 && features.image_scale <= 1),
      "features.image_scale must be in (0, 1]");
  bad(sift_max_width < 64, "sift_max_width must be >= 64 px");
  bad(!(max_correction_deg > 0), "max_correction_deg must be > 0");
  if (std::string t = features.triangulation.Check(); !t.empty())
    bad(true, "features.triangulation: " + t);
  return e;
}

BundleAdjustResult BundleAdjustSide(const std::vector<ViewFeatures>& views,
                                    const std::vector<double>& measured_deg,
                                    const RigCalibration& cal, const BundleAdjustOptions& opts) {
  BundleAdjustResult res;
  const int nv = static_cast<int>(measured_deg.size());
  res.angle_deg = measured_deg;
  res.correction_deg.assign(nv, 0.0);
  res.adjusted.assign(nv, false);
  res.calibration = cal;
  if (std::string e = opts.Check(); !e.empty()) {
    res.reason = "invalid bundle adjustment options: " + e;
    return res;
  }
  if (static_cast<int>(views.size()) != nv) {
    res.reason = "got " + std::to_string(views.size()) + " feature sets for " + std::to_string(nv) +
                 " measured angles; pass one per view";
    return res;
  }

  // Tracks and their initial points from the measured poses.
  const auto t_match = std::chrono::steady_clock::now();
  std::vector<geom::Rigid3> poses;
  poses.reserve(measured_deg.size());
  for (double a : measured_deg) poses.push_back(geom::CamFromTable(cal, a));
  const FeatureCloud cloud = BuildFeatureCloud(views, poses, cal.camera, opts.features);
  res.matching_s = Seconds(t_match);

  std::vector<std::array<double, 3>> points;
  std::vector<Observation> obs;
  for (size_t p = 0; p < cloud.points.size(); ++p) {
    points.push_back({cloud.points[p].x(), cloud.points[p].y(), cloud.points[p].z()});
    for (const auto& [v, k] : cloud.tracks[p]) {
      const cv::Point2f& pt = views[v].keypoints[k].pt;
      obs.push_back({v, static_cast<int>(p), Eigen::Vector2d(pt.x, pt.y)});
    }
  }
  auto count = [&](const std::vector<Observation>& o, int* n_views, int* n_tracks) {
    std::set<int> vs, ps;
    for (const Observation& x : o) vs.insert(x.view), ps.insert(x.point);
    *n_views = static_cast<int>(vs.size());
    *n_tracks = static_cast<int>(ps.size());
  };
  count(obs, &res.views_used, &res.tracks);
  res.observations = static_cast<int>(obs.size());
  auto too_little = [&]() -> bool {
    if (res.tracks < opts.min_tracks) {
      res.reason = "only " + std::to_string(res.tracks) +
                   " feature tracks inside the rock masks (need " +
                   std::to_string(opts.min_tracks) +
                   "): the rock shows too little texture or the masks are too small; the measured "
                   "turntable angles are used as they are";
      return true;
    }
    if (res.views_used < opts.min_views) {
      res.reason = "only " + std::to_string(res.views_used) +
                   " views have tracked features (need " + std::to_string(opts.min_views) +
                   "); the measured turntable angles are used as they are";
      return true;
    }
    return false;
  };
  if (too_little()) return res;

  // Unknowns.
  Eigen::Matrix3d R0;
  Eigen::Vector3d t0;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) R0(i, j) = cal.R_cam_table0[3 * i + j];
    t0(i) = cal.t_cam_table0[i];
  }
  std::vector<double> angle = measured_deg;
  std::array<double, 6> rig{};  // angle-axis and translation delta on cam_from_table0
  const CameraModel& cam = cal.camera;
  std::array<double, kLensParams> lens{cam.fx, cam.fy, cam.cx, cam.cy, cam.k1, cam.k2};

  auto residual_px = [&](const Observation& o, const std::vector<double>& ang,
                         const std::array<double, 6>& rg, const std::array<double, kLensParams>& ln,
                         const std::vector<std::array<double, 3>>& pts) {
    const ReprojectionCost f(o.uv, R0, t0, cam);
    double r[2];
    if (!f(&ang[o.view], rg.data(), ln.data(), pts[o.point].data(), r)) return 1e9;
    return std::hypot(r[0], r[1]);
  };
  auto rms = [&](const std::vector<Observation>& o, const std::vector<double>& ang,
                 const std::array<double, 6>& rg, const std::array<double, kLensParams>& ln,
                 const std::vector<std::array<double, 3>>& pts) {
    double ss = 0;
    for (const Observation& x : o) ss += std::pow(residual_px(x, ang, rg, ln, pts), 2);
    return o.empty() ? 0.0 : std::sqrt(ss / static_cast<double>(o.size()));
  };
  const std::vector<std::array<double, 3>> initial_points = points;
  const std::array<double, 6> initial_rig = rig;
  const std::array<double, kLensParams> initial_lens = lens;

  // Gauge: the first view with observations keeps its measured angle.
  std::set<int> used_views;
  for (const Observation& o : obs) used_views.insert(o.view);
  res.fixed_view = *used_views.begin();

  const auto t_solve = std::chrono::steady_clock::now();
  auto solve = [&](const std::vector<Observation>& o) -> ceres::Solver::Summary {
    ceres::Problem problem;
    // One loss for every block: the problem owns it and deletes it once.
    ceres::LossFunction* loss = new ceres::HuberLoss(opts.huber_px);
    for (const Observation& x : o) {
      auto* cost = new ceres::AutoDiffCostFunction<ReprojectionCost, 2, 1, 6, kLensParams, 3>(
          new ReprojectionCost(x.uv, R0, t0, cam));
      problem.AddResidualBlock(cost, loss, &angle[x.view], rig.data(), lens.data(),
                               points[x.point].data());
    }
    std::set<int> vs;
    for (const Observation& x : o) vs.insert(x.view);
    for (int v : vs) {
      if (v == res.fixed_view) {
        problem.SetParameterBlockConstant(&angle[v]);
      } else {
        problem.AddResidualBlock(new ceres::AutoDiffCostFunction<AnglePrior, 1, 1>(
                                     new AnglePrior{measured_deg[v], opts.angle_prior_deg}),
                                 nullptr, &angle[v]);
      }
    }
    if (opts.refine_rig) {
      problem.AddResidualBlock(new ceres::AutoDiffCostFunction<RigPrior, 6, 6>(new RigPrior{
                                   opts.rig_prior_deg * kPi / 180.0, opts.rig_prior_mm}),
                               nullptr, rig.data());
    } else {
      problem.SetParameterBlockConstant(rig.data());
    }
    if (!opts.refine_lens) problem.SetParameterBlockConstant(lens.data());
    ceres::Solver::Options so;
    so.linear_solver_type = ceres::DENSE_SCHUR;
    so.max_num_iterations = opts.max_iterations;
    so.num_threads = opts.num_threads;
    so.function_tolerance = 1e-8;
    so.logging_type = ceres::SILENT;
    ceres::Solver::Summary summary;
    ceres::Solve(so, &problem, &summary);
    return summary;
  };
  ceres::Solver::Summary s1 = solve(obs);
  res.iterations = static_cast<int>(s1.iterations.size());
  if (!s1.IsSolutionUsable()) {
    res.reason = "the bundle adjustment did not converge (" + s1.message +
                 "); the measured turntable angles are used as they are";
    return res;
  }
  // Drop the observations the solution does not explain, and tracks left with
  // fewer than two, then solve again from here.
  std::vector<Observation> kept;
  for (const Observation& x : obs) {
    if (residual_px(x, angle, rig, lens, points) <= opts.outlier_px) kept.push_back(x);
  }
  std::vector<int> per_point(points.size(), 0);
  for (const Observation& x : kept) ++per_point[x.point];
  std::erase_if(kept, [&](const Observation& x) { return per_point[x.point] < 2; });
  res.outliers_dropped = static_cast<int>(obs.size() - kept.size());
  obs = std::move(kept);
  count(obs, &res.views_used, &res.tracks);
  res.observations = static_cast<int>(obs.size());
  if (too_little()) return res;
  if (std::none_of(obs.begin(), obs.end(),
                   [&](const Observation& x) { return x.view == res.fixed_view; })) {
    // Without its observations the gauge view no longer ties the others down.
    res.reason = "the gauge view " + std::to_string(res.fixed_view) +
                 " lost all its observations as outliers; the measured turntable angles are used "
                 "as they are";
    return res;
  }
  ceres::Solver::Summary s2 = solve(obs);
  res.iterations += static_cast<int>(s2.iterations.size());
  res.solve_s = Seconds(t_solve);
  if (!s2.IsSolutionUsable()) {
    res.reason = "the bundle adjustment did not converge (" + s2.message +
                 "); the measured turntable angles are used as they are";
    return res;
  }
  res.initial_rms_px = rms(obs, measured_deg, initial_rig, initial_lens, initial_points);
  res.final_rms_px = rms(obs, angle, rig, lens, points);
  if (!(res.final_rms_px <= res.initial_rms_px)) {
    res.reason = "the adjustment raised the reprojection RMS (" + Fmt("%.3f", res.initial_rms_px) +
                 " -> " + Fmt("%.3f px", res.final_rms_px) +
                 "); the measured turntable angles are used as they are";
    return res;
  }

  std::set<int> final_views;
  for (const Observation& x : obs) final_views.insert(x.view);
  for (int v : final_views) {
    if (std::abs(angle[v] - measured_deg[v]) > opts.max_correction_deg) {
      res.reason =
          "view " + std::to_string(v) + "'s angle would move by " +
          Fmt("%.2f deg", angle[v] - measured_deg[v]) + ", more than the " +
          Fmt("%.2f deg", opts.max_correction_deg) +
          " a working turntable can be off: the features or the calibration are wrong (recalibrate "
          "the rig if this repeats); the measured turntable angles are used as they are";
      return res;
    }
  }
  for (int v : final_views) {
    res.adjusted[v] = true;
    res.angle_deg[v] = angle[v];
    res.correction_deg[v] = angle[v] - measured_deg[v];
  }
  if (opts.refine_rig) {
    double Rd[9];
    ceres::AngleAxisToRotationMatrix(rig.data(), Rd);  // column-major
    const Eigen::Matrix3d D = Eigen::Map<const Eigen::Matrix3d>(Rd);
    const Eigen::Matrix3d R = D * R0;
    const Eigen::Vector3d t = D * t0 + Eigen::Vector3d(rig[3], rig[4], rig[5]);
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) res.calibration.R_cam_table0[3 * i + j] = R(i, j);
      res.calibration.t_cam_table0[i] = t(i);
    }
  }
  if (opts.refine_lens) {
    CameraModel& c = res.calibration.camera;
    c.fx = lens[kFx], c.fy = lens[kFy], c.cx = lens[kCx], c.cy = lens[kCy], c.k1 = lens[kK1],
    c.k2 = lens[kK2];
  }
  res.refined = true;
  return res;
}

BundleAdjustResult BundleAdjustSideImages(int views, const BundleAdjustViewLoader& load,
                                          const std::vector<double>& measured_deg,
                                          const RigCalibration& cal,
                                          const BundleAdjustOptions& opts) {
  const auto t0 = std::chrono::steady_clock::now();
  std::vector<ViewFeatures> vf(std::max(0, views));
  std::vector<int> take(vf.size());
  std::iota(take.begin(), take.end(), 0);
  if (opts.features.distinct_viewpoints_only && static_cast<int>(measured_deg.size()) == views) {
    std::vector<geom::Rigid3> poses;
    poses.reserve(measured_deg.size());
    for (double a : measured_deg) poses.push_back(geom::CamFromTable(cal, a));
    take = DistinctViewpoints(poses);
  }
  // One photo per thread at a time: the loader decodes it, SIFT runs on the
  // rock's box, and the photo is dropped before the next.
  ParallelFor(take.size(), opts.threads, [&](size_t k) {
    const int i = take[k];
    cv::Mat bgr, mask;
    if (!load(i, &bgr, &mask) || bgr.empty() || mask.empty()) return;
    FeatureCloudOptions fo = opts.features;
    fo.image_scale = std::min(1.0, static_cast<double>(opts.sift_max_width) / bgr.cols);
    vf[static_cast<size_t>(i)] = ExtractRockFeatures(bgr, mask, fo);
  });
  const double features_s = Seconds(t0);
  BundleAdjustResult r = BundleAdjustSide(vf, measured_deg, cal, opts);
  r.features_s = features_s;
  return r;
}

}  // namespace aggscan
