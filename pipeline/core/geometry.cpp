#include "pipeline/core/geometry.h"

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

namespace aggscan::geom {

namespace {

constexpr double kPi = 3.14159265358979323846;

// splitmix64: the same samples on every platform for a seed.
uint64_t NextRandom(uint64_t* s) {
  uint64_t z = (*s += 0x9E3779B97F4A7C15ull);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

// Camera centre and the inverse of the left 3x3 of P, for ray directions.
struct RayFrame {
  Eigen::Vector3d centre;
  Eigen::Matrix3d M_inv;
  Eigen::Vector3d Direction(const Eigen::Vector2d& uv) const {
    return (M_inv * Eigen::Vector3d(uv.x(), uv.y(), 1.0)).normalized();
  }
};

RayFrame MakeRayFrame(const Eigen::Matrix<double, 3, 4>& P) {
  RayFrame f;
  const Eigen::Matrix3d M = P.leftCols<3>();
  f.M_inv = M.inverse();
  f.centre = -(f.M_inv * P.col(3));
  return f;
}

double AngleDeg(const Eigen::Vector3d& a, const Eigen::Vector3d& b) {
  return std::atan2(a.cross(b).norm(), a.dot(b)) * 180.0 / kPi;
}

// Reprojection residual (undistorted px); infinity behind the camera.
double Residual(const Sighting& s, const Eigen::Vector3d& X) {
  const Eigen::Vector3d h = s.P * X.homogeneous();
  if (!(h.z() > 1e-9)) return std::numeric_limits<double>::infinity();
  return (h.head<2>() / h.z() - s.uv).norm();
}

// Linear triangulation from the listed sightings (each row normalised so every
// view weighs the same): the null vector of A, via the 4x4 normal matrix.
std::optional<Eigen::Vector3d> Dlt(const std::vector<Sighting>& s, const std::vector<int>& idx) {
  Eigen::Matrix4d AtA = Eigen::Matrix4d::Zero();
  for (int i : idx) {
    const Sighting& o = s[i];
    for (int r = 0; r < 2; ++r) {
      Eigen::RowVector4d row = o.uv(r) * o.P.row(2) - o.P.row(r);
      row /= std::max(row.norm(), 1e-300);
      AtA += row.transpose() * row;
    }
  }
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix4d> es(AtA);
  const Eigen::Vector4d x = es.eigenvectors().col(0);  // smallest eigenvalue first
  if (std::abs(x(3)) < 1e-12) return std::nullopt;     // point at infinity
  return Eigen::Vector3d(x.head<3>() / x(3));
}

// Gauss-Newton on the summed squared pixel residuals of the listed sightings.
Eigen::Vector3d Refine(const std::vector<Sighting>& s, const std::vector<int>& idx,
                       Eigen::Vector3d X, int iterations) {
  for (int it = 0; it < iterations; ++it) {
    Eigen::Matrix3d JtJ = Eigen::Matrix3d::Zero();
    Eigen::Vector3d Jtr = Eigen::Vector3d::Zero();
    for (int i : idx) {
      const Sighting& o = s[i];
      const Eigen::Vector3d h = o.P * X.homogeneous();
      if (!(h.z() > 1e-9)) continue;
      const double u = h.x() / h.z(), v = h.y() / h.z();
      Eigen::Matrix<double, 2, 3> J;
      J.row(0) = (o.P.block<1, 3>(0, 0) - u * o.P.block<1, 3>(2, 0)) / h.z();
      J.row(1) = (o.P.block<1, 3>(1, 0) - v * o.P.block<1, 3>(2, 0)) / h.z();
      const Eigen::Vector2d r(u - o.uv.x(), v - o.uv.y());
      JtJ += J.transpose() * J;
      Jtr += J.transpose() * r;
    }
    const Eigen::Vector3d dx = JtJ.ldlt().solve(-Jtr);
    if (!dx.allFinite()) break;
    X += dx;
    if (dx.norm() < 1e-9) break;
  }
  return X;
}

}  // namespace

Rigid3 Rigid3::FromRowMajor4(const std::array<double, 16>& m) {
  Rigid3 r;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) r.R(i, j) = m[4 * i + j];
    r.t(i) = m[4 * i + 3];
  }
  return r;
}

Rigid3 Rigid3::RotZ(double deg) {
  Rigid3 r;
  r.R = Eigen::AngleAxisd(deg * kPi / 180.0, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  return r;
}

double RotationAngleDeg(const Eigen::Matrix3d& R) {
  const double c = std::clamp((R.trace() - 1.0) / 2.0, -1.0, 1.0);
  // acos loses precision near 0; use the skew part there.
  const Eigen::Vector3d w(R(2, 1) - R(1, 2), R(0, 2) - R(2, 0), R(1, 0) - R(0, 1));
  return std::atan2(0.5 * w.norm(), c) * 180.0 / kPi;
}

Rigid3 CamFromTable(const RigCalibration& cal, double angle_deg) {
  Rigid3 c0;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) c0.R(i, j) = cal.R_cam_table0[3 * i + j];
    c0.t(i) = cal.t_cam_table0[i];
  }
  return c0 * Rigid3::RotZ(angle_deg);
}

Eigen::Matrix3d CameraMatrix(const CameraModel& cam) {
  Eigen::Matrix3d K;
  K << cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1;
  return K;
}

Eigen::Vector2d UndistortPixel(const CameraModel& cam, const Eigen::Vector2d& pixel) {
  const double xd = (pixel.x() - cam.cx) / cam.fx, yd = (pixel.y() - cam.cy) / cam.fy;
  double x = xd, y = yd;
  // Fixed point x = (x_d - tangential(x)) / radial(x): the distortion is a small
  // perturbation of the identity on the rig's lenses, so this contracts fast.
  for (int it = 0; it < 50; ++it) {
    const double r2 = x * x + y * y;
    const double radial = 1 + r2 * (cam.k1 + r2 * (cam.k2 + r2 * cam.k3));
    const double dx = 2 * cam.p1 * x * y + cam.p2 * (r2 + 2 * x * x);
    const double dy = cam.p1 * (r2 + 2 * y * y) + 2 * cam.p2 * x * y;
    const double nx = (xd - dx) / radial, ny = (yd - dy) / radial;
    const double step = std::abs(nx - x) + std::abs(ny - y);
    x = nx, y = ny;
    if (step < 1e-12) break;
  }
  return {cam.fx * x + cam.cx, cam.fy * y + cam.cy};
}

std::optional<Eigen::Vector2d> ProjectPoint(const CameraModel& cam, const Rigid3& cam_from_frame,
                                            const Eigen::Vector3d& p) {
  const Eigen::Vector3d c = cam_from_frame.Apply(p);
  double u = 0, v = 0;
  if (!cam.Project({c.x(), c.y(), c.z()}, &u, &v)) return std::nullopt;
  return Eigen::Vector2d(u, v);
}

Sighting MakeSighting(const CameraModel& cam, const Rigid3& cam_from_frame,
                      const Eigen::Vector2d& pixel, int view) {
  Sighting s;
  Eigen::Matrix<double, 3, 4> Rt;
  Rt.leftCols<3>() = cam_from_frame.R;
  Rt.col(3) = cam_from_frame.t;
  s.P = CameraMatrix(cam) * Rt;
  s.uv = UndistortPixel(cam, pixel);
  s.view = view;
  return s;
}

std::string TriangulationOptions::Check() const {
  if (!(inlier_px > 0)) return "inlier_px must be > 0";
  if (min_views < 2) return "min_views must be >= 2";
  if (!(min_angle_deg >= 0 && min_angle_deg < 90)) return "min_angle_deg must be in [0, 90)";
  if (refine_iterations < 0) return "refine_iterations must be >= 0";
  return {};
}

Result<TriangulatedPoint> TriangulatePoint(const std::vector<Sighting>& s,
                                           const TriangulationOptions& opts) {
  if (std::string bad = opts.Check(); !bad.empty()) {
    return MakeError(ErrorClass::kInvalidArgument, "triangulation options: " + bad);
  }
  const int n = static_cast<int>(s.size());
  if (n < opts.min_views) {
    return MakeError(
        ErrorClass::kInvalidArgument,
        "seen in " + std::to_string(n) + " views, need " + std::to_string(opts.min_views));
  }
  std::vector<Eigen::Vector3d> dirs(n);
  for (int i = 0; i < n; ++i) dirs[i] = MakeRayFrame(s[i].P).Direction(s[i].uv);

  auto inliers_of = [&](const Eigen::Vector3d& X, double* cost) {
    std::vector<int> in;
    double c = 0;
    for (int i = 0; i < n; ++i) {
      const double r = Residual(s[i], X);
      if (r <= opts.inlier_px) in.push_back(i);
      c += std::min(r, opts.inlier_px);  // truncated: ranks seeds with equal counts
    }
    if (cost) *cost = c;
    return in;
  };

  std::vector<int> inliers;
  if (opts.robust && n > 2) {
    double best_cost = std::numeric_limits<double>::infinity();
    for (int i = 0; i < n; ++i) {
      for (int j = i + 1; j < n; ++j) {
        if (AngleDeg(dirs[i], dirs[j]) < opts.min_angle_deg) continue;
        const std::optional<Eigen::Vector3d> X = Dlt(s, {i, j});
        if (!X) continue;
        double cost = 0;
        std::vector<int> in = inliers_of(*X, &cost);
        if (in.size() > inliers.size() || (in.size() == inliers.size() && cost < best_cost)) {
          inliers = std::move(in), best_cost = cost;
        }
      }
    }
  } else {
    for (int i = 0; i < n; ++i) inliers.push_back(i);
  }
  if (static_cast<int>(inliers.size()) < opts.min_views) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "no " + std::to_string(opts.min_views) + " of the " + std::to_string(n) +
                         " sightings agree within " + std::to_string(opts.inlier_px) +
                         " px (or their rays are nearly parallel)");
  }

  TriangulatedPoint out;
  for (int round = 0; round < 3; ++round) {
    const std::optional<Eigen::Vector3d> X0 = Dlt(s, inliers);
    if (!X0) return MakeError(ErrorClass::kInvalidArgument, "point at infinity");
    out.X = Refine(s, inliers, *X0, opts.refine_iterations);
    std::vector<int> next = opts.robust ? inliers_of(out.X, nullptr) : inliers;
    if (next == inliers) break;
    if (static_cast<int>(next.size()) < opts.min_views) break;  // keep the last good set
    inliers = std::move(next);
  }
  out.inliers = inliers;
  out.residual_px.resize(n);
  for (int i = 0; i < n; ++i) out.residual_px[i] = Residual(s[i], out.X);
  double ss = 0;
  for (int i : inliers) {
    ss += out.residual_px[i] * out.residual_px[i];
    out.max_px = std::max(out.max_px, out.residual_px[i]);
    for (int j : inliers)
      out.max_angle_deg = std::max(out.max_angle_deg, AngleDeg(dirs[i], dirs[j]));
  }
  out.rms_px = std::sqrt(ss / static_cast<double>(inliers.size()));
  if (out.max_angle_deg < opts.min_angle_deg) {
    return MakeError(ErrorClass::kInvalidArgument, "rays of the agreeing views meet at only " +
                                                       std::to_string(out.max_angle_deg) +
                                                       " deg (need " +
                                                       std::to_string(opts.min_angle_deg) + ")");
  }
  return out;
}

std::optional<Similarity3> AlignPoints(const std::vector<Eigen::Vector3d>& src,
                                       const std::vector<Eigen::Vector3d>& dst, bool with_scale) {
  const int n = static_cast<int>(src.size());
  if (n < 3 || dst.size() != src.size()) return std::nullopt;
  Eigen::Matrix3Xd a(3, n), b(3, n);
  for (int i = 0; i < n; ++i) a.col(i) = src[i], b.col(i) = dst[i];
  // Collinear (or coincident) sources leave the rotation about their line free.
  const Eigen::Matrix3Xd ac = a.colwise() - a.rowwise().mean();
  const Eigen::Vector3d sv = Eigen::JacobiSVD<Eigen::Matrix3Xd>(ac).singularValues();
  if (!(sv(1) > 1e-9 * std::max(sv(0), 1e-300))) return std::nullopt;
  const Eigen::Matrix4d T = Eigen::umeyama(a, b, with_scale);
  Similarity3 out;
  const Eigen::Matrix3d sR = T.topLeftCorner<3, 3>();
  out.scale = with_scale ? std::cbrt(sR.determinant()) : 1.0;
  out.R = sR / out.scale;
  out.t = T.topRightCorner<3, 1>();
  if (!out.R.allFinite() || !(out.scale > 0)) return std::nullopt;
  return out;
}

void AlignmentResidual(const Similarity3& T, const std::vector<Eigen::Vector3d>& src,
                       const std::vector<Eigen::Vector3d>& dst, double* rms, double* max) {
  double ss = 0, mx = 0;
  for (size_t i = 0; i < src.size(); ++i) {
    const double e = (T.Apply(src[i]) - dst[i]).norm();
    ss += e * e, mx = std::max(mx, e);
  }
  if (rms) *rms = src.empty() ? 0 : std::sqrt(ss / static_cast<double>(src.size()));
  if (max) *max = mx;
}

std::optional<RansacRigidResult> RansacRigid(const std::vector<Eigen::Vector3d>& src,
                                             const std::vector<Eigen::Vector3d>& dst,
                                             const RansacRigidOptions& opts) {
  const int n = static_cast<int>(src.size());
  if (n < 3 || dst.size() != src.size()) return std::nullopt;
  auto inliers_of = [&](const Similarity3& T, double* cost) {
    std::vector<int> in;
    double c = 0;
    for (int i = 0; i < n; ++i) {
      const double e = (T.Apply(src[i]) - dst[i]).norm();
      if (e <= opts.inlier_mm) in.push_back(i);
      c += std::min(e, opts.inlier_mm);
    }
    *cost = c;
    return in;
  };
  uint64_t rng = opts.seed * 0x2545F4914F6CDD1Dull + 1;
  std::vector<int> best;
  double best_cost = std::numeric_limits<double>::infinity();
  const double spread2 = opts.min_spread_mm * opts.min_spread_mm;
  int needed = opts.iterations;
  for (int it = 0; it < needed; ++it) {
    const int i = static_cast<int>(NextRandom(&rng) % n);
    const int j = static_cast<int>(NextRandom(&rng) % n);
    const int k = static_cast<int>(NextRandom(&rng) % n);
    if (i == j || j == k || i == k) continue;
    // A rigid motion keeps distances: reject samples whose pairs disagree.
    bool bad = false;
    for (auto [a, b] : {std::pair{i, j}, {j, k}, {i, k}}) {
      const double ds = (src[a] - src[b]).squaredNorm(), dd = (dst[a] - dst[b]).squaredNorm();
      if (ds < spread2 || std::abs(std::sqrt(ds) - std::sqrt(dd)) > 2 * opts.inlier_mm) bad = true;
    }
    if (bad) continue;
    const std::optional<Similarity3> T =
        AlignPoints({src[i], src[j], src[k]}, {dst[i], dst[j], dst[k]}, false);
    if (!T) continue;
    double cost = 0;
    std::vector<int> in = inliers_of(*T, &cost);
    if (in.size() > best.size() || (in.size() == best.size() && cost < best_cost)) {
      best = std::move(in), best_cost = cost;
      // Enough samples that an all-inlier triple was drawn with 99.99 %
      // probability at the inlier ratio seen so far.
      const double w = static_cast<double>(best.size()) / n;
      const double p_miss = 1.0 - w * w * w;
      if (p_miss <= 0) {
        needed = it + 1;
      } else if (p_miss < 1) {
        needed = std::min(opts.iterations,
                          static_cast<int>(std::ceil(std::log(1e-4) / std::log(p_miss))) + 1);
      }
    }
  }
  if (best.size() < 3) return std::nullopt;
  RansacRigidResult out;
  Similarity3 T;
  for (int round = 0; round < 3; ++round) {
    std::vector<Eigen::Vector3d> a, b;
    for (int i : best) a.push_back(src[i]), b.push_back(dst[i]);
    const std::optional<Similarity3> fit = AlignPoints(a, b, false);
    if (!fit) return std::nullopt;
    T = *fit;
    double cost = 0;
    std::vector<int> next = inliers_of(T, &cost);
    if (next == best || next.size() < 3) break;
    best = std::move(next);
  }
  out.T.R = T.R;
  out.T.t = T.t;
  out.inliers = best;
  std::vector<Eigen::Vector3d> a, b;
  for (int i : best) a.push_back(src[i]), b.push_back(dst[i]);
  AlignmentResidual(T, a, b, &out.rms_mm, &out.max_mm);
  return out;
}

LengthScaleFit LengthResiduals(double scale, const std::vector<LengthPair>& lengths) {
  LengthScaleFit f;
  f.scale = scale;
  double ss = 0;
  for (const auto& [r, c] : lengths) {
    const double e = scale * r - c;
    ss += e * e;
    f.max_mm = std::max(f.max_mm, std::abs(e));
  }
  f.rms_mm = lengths.empty() ? 0.0 : std::sqrt(ss / static_cast<double>(lengths.size()));
  return f;
}

LengthScaleFit FitLengthScale(const std::vector<LengthPair>& lengths) {
  double num = 0, den = 0;
  for (const auto& [r, c] : lengths) num += r * c, den += r * r;
  return LengthResiduals(den > 0 ? num / den : 1.0, lengths);
}

Eigen::Isometry3d IsoFromRowMajor(const std::array<double, 16>& m) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) T.linear()(r, c) = m[r * 4 + c];
    T.translation()(r) = m[r * 4 + 3];
  }
  return T;
}

}  // namespace aggscan::geom
