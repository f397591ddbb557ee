#include "pipeline/stitch/stitch.h"

#include <Eigen/Eigenvalues>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <numeric>
#include <opencv2/features2d.hpp>
#include <opencv2/imgproc.hpp>
#include <unordered_map>

namespace aggscan {

namespace {

using Eigen::Vector2d;
using Eigen::Vector3d;

std::string Mm(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.2f mm", v);
  return buf;
}

Eigen::Matrix3d Skew(const Vector3d& v) {
  Eigen::Matrix3d m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

// Fundamental matrix between undistorted pixels of view a and view b.
Eigen::Matrix3d Fundamental(const geom::Rigid3& a, const geom::Rigid3& b,
                            const Eigen::Matrix3d& K) {
  const geom::Rigid3 ba = b * a.Inverse();  // camera a -> camera b
  const Eigen::Matrix3d E = Skew(ba.t) * ba.R;
  const Eigen::Matrix3d Ki = K.inverse();
  return Ki.transpose() * E * Ki;
}

double Sampson(const Eigen::Matrix3d& F, const Vector2d& x1, const Vector2d& x2) {
  const Vector3d p(x1.x(), x1.y(), 1), q(x2.x(), x2.y(), 1);
  const Vector3d Fp = F * p, Ftq = F.transpose() * q;
  const double e = q.dot(Fp);
  const double den = Fp.x() * Fp.x() + Fp.y() * Fp.y() + Ftq.x() * Ftq.x() + Ftq.y() * Ftq.y();
  return den > 0 ? std::abs(e) / std::sqrt(den) : 1e300;
}

// k nearest rows of `train` for every row of `query` (approximate: KD-trees;
// 10-20x faster than brute force on a few thousand SIFT descriptors), with
// exact L2 distances (FLANN's own are squared for L2).
std::vector<std::vector<cv::DMatch>> KnnL2(const cv::Mat& query, const cv::Mat& train, int k) {
  std::vector<std::vector<cv::DMatch>> knn;
  if (query.empty() || train.empty()) return knn;
  cv::FlannBasedMatcher matcher(cv::makePtr<cv::flann::KDTreeIndexParams>(4),
                                cv::makePtr<cv::flann::SearchParams>(64));
  matcher.knnMatch(query, train, knn, std::min(k, train.rows));
  for (auto& ms : knn) {
    for (cv::DMatch& m : ms) {
      m.distance =
          static_cast<float>(cv::norm(query.row(m.queryIdx), train.row(m.trainIdx), cv::NORM_L2));
    }
    std::sort(ms.begin(), ms.end(),
              [](const cv::DMatch& a, const cv::DMatch& b) { return a.distance < b.distance; });
  }
  return knn;
}

struct UnionFind {
  std::vector<int> parent;
  explicit UnionFind(int n) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  int Find(int x) {
    while (parent[x] != x) x = parent[x] = parent[parent[x]];
    return x;
  }
  void Unite(int a, int b) { parent[Find(a)] = Find(b); }
};

// Displacement difference of two motions over points of the moving side (RMS).
double DisplacementRms(const geom::Rigid3& a, const geom::Rigid3& b,
                       const std::vector<Vector3d>& pts) {
  if (pts.empty()) return (a.t - b.t).norm();
  double ss = 0;
  for (const Vector3d& p : pts) ss += (a.Apply(p) - b.Apply(p)).squaredNorm();
  return std::sqrt(ss / static_cast<double>(pts.size()));
}

// 1-sigma rotation uncertainty (deg) about the weakest axis of a rigid fit to
// `pts` with isotropic point errors sigma: the rotation's information matrix
// is sum(|q|^2 I - q q^T) / sigma^2 over the centred points q.
double RotationSigmaDeg(const std::vector<Vector3d>& pts, double sigma) {
  if (pts.size() < 3) return 180.0;
  Vector3d c = Vector3d::Zero();
  for (const Vector3d& p : pts) c += p;
  c /= static_cast<double>(pts.size());
  Eigen::Matrix3d info = Eigen::Matrix3d::Zero();
  for (const Vector3d& p : pts) {
    const Vector3d q = p - c;
    info += q.squaredNorm() * Eigen::Matrix3d::Identity() - q * q.transpose();
  }
  const double lmin = Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(info).eigenvalues()(0);
  return lmin > 0 ? sigma / std::sqrt(lmin) * 180.0 / 3.14159265358979323846 : 180.0;
}

// The RANSAC rigid fit of one-to-one matches (reference point -> (moving
// point, descriptor distance)); `pairs` gets their number.
std::optional<geom::RansacRigidResult> FitMatches(const std::map<int, std::pair<int, double>>& m,
                                                  const FeatureCloud& ref, const FeatureCloud& mov,
                                                  const StitchOptions& opts, int* pairs) {
  std::vector<Vector3d> a, b;
  for (const auto& [p_ref, md] : m) {
    a.push_back(mov.points[md.first]);
    b.push_back(ref.points[p_ref]);
  }
  *pairs = static_cast<int>(a.size());
  return geom::RansacRigid(a, b, opts.ransac);
}

}  // namespace

// --- features ---

ViewFeatures ExtractRockFeatures(const cv::Mat& bgr, const cv::Mat& rock_mask,
                                 const FeatureCloudOptions& opts, cv::Point origin) {
  ViewFeatures out;
  if (bgr.empty() || rock_mask.size() != bgr.size()) return out;
  cv::Mat mask;
  cv::compare(rock_mask, 0, mask, cv::CMP_GT);
  if (opts.mask_erode_px > 0) {
    const int k = 2 * opts.mask_erode_px + 1;
    cv::erode(mask, mask, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(k, k)));
  }
  const cv::Rect box = cv::boundingRect(mask);
  if (box.area() == 0) return out;
  // SIFT on the rock's box only (plus a margin for the pyramid's blur): the
  // rock covers a few percent of the frame.
  const int margin = 16;
  const cv::Rect roi = (box + cv::Size(2 * margin, 2 * margin) - cv::Point(margin, margin)) &
                       cv::Rect(0, 0, bgr.cols, bgr.rows);
  cv::Mat gray, m = mask(roi);
  cv::cvtColor(bgr(roi), gray, cv::COLOR_BGR2GRAY);
  const double s = opts.image_scale;
  if (s != 1.0) {
    cv::resize(gray, gray, cv::Size(), s, s, cv::INTER_AREA);
    cv::resize(m, m, gray.size(), 0, 0, cv::INTER_NEAREST);
  }
  cv::Ptr<cv::SIFT> sift = cv::SIFT::create(opts.max_features);
  sift->detectAndCompute(gray, m, out.keypoints, out.descriptors);
  for (cv::KeyPoint& k : out.keypoints) {
    // Back to full-resolution pixel centres.
    k.pt.x = static_cast<float>((k.pt.x + 0.5) / s - 0.5 + (roi.x + origin.x));
    k.pt.y = static_cast<float>((k.pt.y + 0.5) / s - 0.5 + (roi.y + origin.y));
    k.size = static_cast<float>(k.size / s);
  }
  return out;
}

std::vector<int> DistinctViewpoints(const std::vector<geom::Rigid3>& poses) {
  std::vector<int> reps;
  for (int i = 0; i < static_cast<int>(poses.size()); ++i) {
    const Vector3d ci = -(poses[i].R.transpose() * poses[i].t);
    bool dup = false;
    for (int r : reps) {
      const Vector3d cr = -(poses[r].R.transpose() * poses[r].t);
      if (geom::RotationAngleDeg(poses[i].R * poses[r].R.transpose()) < 1.0 &&
          (ci - cr).norm() < 2.0) {
        dup = true;
        break;
      }
    }
    if (!dup) reps.push_back(i);
  }
  return reps;
}

FeatureCloud BuildFeatureCloud(const std::vector<ViewFeatures>& views,
                               const std::vector<geom::Rigid3>& poses, const CameraModel& camera,
                               const FeatureCloudOptions& opts) {
  FeatureCloud out;
  const int nv = static_cast<int>(std::min(views.size(), poses.size()));
  std::vector<int> used;
  std::vector<int> candidates(nv);
  std::iota(candidates.begin(), candidates.end(), 0);
  if (opts.distinct_viewpoints_only) {
    candidates = DistinctViewpoints(std::vector<geom::Rigid3>(poses.begin(), poses.begin() + nv));
  }
  for (int i : candidates) {
    if (!views[i].keypoints.empty() && !views[i].descriptors.empty()) used.push_back(i);
  }
  out.views = static_cast<int>(used.size());
  // Undistorted keypoints and a global id per (view, keypoint).
  std::vector<std::vector<Vector2d>> uv(nv);
  std::vector<int> offset(nv + 1, 0);
  for (int i = 0; i < nv; ++i) {
    offset[i + 1] = offset[i] + static_cast<int>(views[i].keypoints.size());
  }
  for (int i : used) {
    for (const cv::KeyPoint& k : views[i].keypoints) {
      uv[i].push_back(geom::UndistortPixel(camera, Vector2d(k.pt.x, k.pt.y)));
    }
  }
  const Eigen::Matrix3d K = geom::CameraMatrix(camera);
  UnionFind uf(offset[nv]);
  for (size_t a = 0; a < used.size(); ++a) {
    for (size_t b = a + 1; b < used.size(); ++b) {
      const int i = used[a], j = used[b];
      const double ang = geom::RotationAngleDeg(poses[j].R * poses[i].R.transpose());
      if (ang < opts.min_pair_deg || ang > opts.max_pair_deg) continue;
      ++out.view_pairs;
      const Eigen::Matrix3d F = Fundamental(poses[i], poses[j], K);
      const std::vector<std::vector<cv::DMatch>> knn =
          KnnL2(views[i].descriptors, views[j].descriptors, 2);
      for (const auto& m : knn) {
        if (m.size() < 2 || m[0].distance >= opts.ratio * m[1].distance) continue;
        const int qi = m[0].queryIdx, ti = m[0].trainIdx;
        if (Sampson(F, uv[i][qi], uv[j][ti]) > opts.epipolar_px) continue;
        uf.Unite(offset[i] + qi, offset[j] + ti);
      }
    }
  }
  // Tracks: the union-find classes with at least two members.
  std::unordered_map<int, std::vector<std::pair<int, int>>> tracks;  // root -> (view, kp)
  for (int i : used) {
    for (int k = 0; k < static_cast<int>(views[i].keypoints.size()); ++k) {
      tracks[uf.Find(offset[i] + k)].push_back({i, k});
    }
  }
  std::vector<cv::Mat> rows;
  for (auto& [root, members] : tracks) {
    if (members.size() < 2) continue;
    std::sort(members.begin(), members.end());
    // Two keypoints of one view in a track: a bad merge; drop the track.
    bool dup = false;
    for (size_t m = 1; m < members.size(); ++m)
      dup = dup || members[m].first == members[m - 1].first;
    if (dup) continue;
    std::vector<geom::Sighting> s;
    for (const auto& [v, k] : members) {
      geom::Sighting g;
      Eigen::Matrix<double, 3, 4> Rt;
      Rt.leftCols<3>() = poses[v].R;
      Rt.col(3) = poses[v].t;
      g.P = K * Rt;
      g.uv = uv[v][k];
      g.view = v;
      s.push_back(g);
    }
    Result<geom::TriangulatedPoint> tp = geom::TriangulatePoint(s, opts.triangulation);
    if (!tp.ok()) continue;
    const int pid = static_cast<int>(out.points.size());
    out.points.push_back(tp->X);
    out.rms_px.push_back(tp->rms_px);
    out.tracks.emplace_back();
    for (int in : tp->inliers) {
      const auto& [v, k] = members[in];
      out.tracks.back().push_back({v, k});
      rows.push_back(views[v].descriptors.row(k));
      out.point_of_row.push_back(pid);
    }
  }
  if (!rows.empty()) cv::vconcat(rows, out.descriptors);
  return out;
}

// --- stitching ---

StitchEstimate StitchFromMarkers(const SideMarkers& ref, const SideMarkers& mov,
                                 const StitchOptions& opts) {
  StitchEstimate e;
  std::vector<Vector3d> a, b;  // moving, reference
  std::vector<std::string> names;
  for (const MarkerPoint& p : mov.points) {
    const MarkerPoint* q = ref.Find(p.color, p.segment);
    if (p.located && q && q->located) {
      a.push_back(p.position), b.push_back(q->position), names.push_back(p.Name());
    }
  }
  e.pairs = static_cast<int>(a.size());
  if (a.size() < 3) {
    e.note = "only " + std::to_string(a.size()) + " marker points located on both sides (need 3)";
    return e;
  }
  auto fit = [&](const std::vector<int>& idx, geom::Similarity3* T, double* rms, double* mx) {
    std::vector<Vector3d> sa, sb;
    for (int i : idx) sa.push_back(a[i]), sb.push_back(b[i]);
    const std::optional<geom::Similarity3> t = geom::AlignPoints(sa, sb, false);
    if (!t) return false;
    *T = *t;
    geom::AlignmentResidual(*T, sa, sb, rms, mx);
    return true;
  };
  auto ok = [&](double rms, double mx) {
    return rms <= opts.marker_max_rms_mm && mx <= opts.marker_max_mm;
  };
  std::vector<int> all(a.size());
  std::iota(all.begin(), all.end(), 0);
  geom::Similarity3 T;
  double rms = 0, mx = 0;
  if (!fit(all, &T, &rms, &mx)) {
    e.note = "the marker points are collinear";
    return e;
  }
  std::vector<int> chosen = all;
  if (!ok(rms, mx) && a.size() >= 4) {
    // One bad point spoils the fit: drop the one whose removal fits best.
    double best = 1e300;
    int drop = -1;
    geom::Similarity3 Tb;
    double rb = 0, mb = 0;
    for (size_t d = 0; d < a.size(); ++d) {
      std::vector<int> idx;
      for (int i : all) {
        if (i != static_cast<int>(d)) idx.push_back(i);
      }
      geom::Similarity3 t;
      double r = 0, m = 0;
      if (fit(idx, &t, &r, &m) && ok(r, m) && r < best)
        best = r, drop = static_cast<int>(d), Tb = t, rb = r, mb = m;
    }
    if (drop >= 0) {
      e.note = "dropped " + names[drop] + " (" + Mm((T.Apply(a[drop]) - b[drop]).norm()) +
               " off in the 4-point fit, " + Mm((Tb.Apply(a[drop]) - b[drop]).norm()) +
               " from the others' fit)";
      chosen.erase(chosen.begin() + drop);
      T = Tb, rms = rb, mx = mb;
    }
  }
  e.T.R = T.R;
  e.T.t = T.t;
  e.inliers = static_cast<int>(chosen.size());
  {
    std::vector<Vector3d> used;
    used.reserve(chosen.size());
    for (int i : chosen) used.push_back(a[i]);
    e.rotation_sigma_deg = RotationSigmaDeg(used, opts.marker_sigma_mm);
  }
  e.rms_mm = rms;
  e.max_mm = mx;
  for (int i : chosen) e.points.push_back(names[i]);
  if (!ok(rms, mx)) {
    e.note = "the marker points do not fit one rigid motion: residual RMS " + Mm(rms) + ", max " +
             Mm(mx) + " over " + std::to_string(chosen.size()) + " points";
    return e;
  }
  e.valid = true;
  if (chosen.size() == 3 && e.note.empty())
    e.note = "3 points: no redundancy beyond their distances";
  return e;
}

StitchEstimate StitchFromFeatures(const FeatureCloud& ref, const FeatureCloud& mov,
                                  const StitchOptions& opts) {
  StitchEstimate e;
  if (ref.points.empty() || mov.points.empty() || ref.descriptors.empty() ||
      mov.descriptors.empty()) {
    e.note = "no triangulated features on " +
             std::string(ref.points.empty() ? "side " + std::to_string(opts.reference_side)
                                            : "side " + std::to_string(opts.moving_side));
    return e;
  }
  // Nearest reference descriptors of every moving descriptor; the ratio test
  // compares the best with the best of another point (a point's own
  // descriptors from other views are not rivals).
  const std::vector<std::vector<cv::DMatch>> knn = KnnL2(mov.descriptors, ref.descriptors, 6);
  std::map<int, std::pair<int, float>> best_of_mov;  // moving point -> (ref point, distance)
  for (const auto& m : knn) {
    if (m.empty()) continue;
    const int p_ref = ref.point_of_row[m[0].trainIdx];
    float second = -1;
    for (size_t k = 1; k < m.size(); ++k) {
      if (ref.point_of_row[m[k].trainIdx] != p_ref) {
        second = m[k].distance;
        break;
      }
    }
    if (second >= 0 && m[0].distance >= opts.feature_ratio * second) continue;
    const int p_mov = mov.point_of_row[m[0].queryIdx];
    auto it = best_of_mov.find(p_mov);
    if (it == best_of_mov.end() || m[0].distance < it->second.second) {
      best_of_mov[p_mov] = {p_ref, m[0].distance};
    }
  }
  // One moving point per reference point: the closest in descriptor space.
  std::map<int, std::pair<int, double>> best_of_ref;
  for (const auto& [p_mov, rd] : best_of_mov) {
    auto it = best_of_ref.find(rd.first);
    if (it == best_of_ref.end() || rd.second < it->second.second)
      best_of_ref[rd.first] = {p_mov, rd.second};
  }
  const std::optional<geom::RansacRigidResult> r =
      FitMatches(best_of_ref, ref, mov, opts, &e.pairs);
  if (!r) {
    e.note = std::to_string(e.pairs) + " putative matches, no consistent triple";
    return e;
  }
  e.T = r->T;
  e.inliers = static_cast<int>(r->inliers.size());
  e.unguided_inliers = e.inliers;
  e.rms_mm = r->rms_mm;
  e.max_mm = r->max_mm;
  if (e.inliers < opts.min_feature_inliers) {
    // Too few: the fit from the global matches guides a second matching,
    // which finds the true matches the global ratio test lost to
    // look-alikes. A fit with enough inliers is kept as it is: the guided
    // one takes looser matches in, and on the sim's renders it came out no
    // closer to the truth.
    StitchEstimate g = GuidedFeatureFit(ref, mov, r->T, opts);
    if (g.valid) {
      g.unguided_inliers = e.inliers;
      g.guided_from = "features";
      return g;
    }
    e.note = "only " + std::to_string(e.inliers) + " of " + std::to_string(e.pairs) +
             " feature matches consistent (need " + std::to_string(opts.min_feature_inliers) +
             "); guided by that fit: " + g.note;
    return e;
  }
  e.valid = true;
  return e;
}

StitchEstimate GuidedFeatureFit(const FeatureCloud& ref, const FeatureCloud& mov,
                                const geom::Rigid3& start, const StitchOptions& opts) {
  StitchEstimate e;
  e.T = start;
  if (ref.points.empty() || mov.points.empty() || ref.descriptors.empty() ||
      mov.descriptors.empty()) {
    e.note = "no triangulated features on one side";
    return e;
  }
  std::vector<std::vector<int>> rows_mov(mov.points.size()), rows_ref(ref.points.size());
  for (int i = 0; i < mov.descriptors.rows; ++i) rows_mov[mov.point_of_row[i]].push_back(i);
  for (int j = 0; j < ref.descriptors.rows; ++j) rows_ref[ref.point_of_row[j]].push_back(j);
  // Two points' descriptor distance: the closest of their sightings (a
  // point seen from a similar angle on both sides matches best there).
  auto distance = [&](size_t p_mov, size_t p_ref) {
    double d = std::numeric_limits<double>::infinity();
    for (int i : rows_mov[p_mov]) {
      for (int j : rows_ref[p_ref]) {
        d = std::min(d, cv::norm(mov.descriptors.row(i), ref.descriptors.row(j), cv::NORM_L2));
      }
    }
    return d;
  };
  const double r2 = opts.guided_radius_mm * opts.guided_radius_mm;
  for (int round = 0; round < std::max(1, opts.guided_rounds); ++round) {
    std::map<int, std::pair<int, double>> best_of_ref;  // ref point -> (moving, distance)
    for (size_t pm = 0; pm < mov.points.size(); ++pm) {
      const Vector3d x = e.T.Apply(mov.points[pm]);
      double d1 = std::numeric_limits<double>::infinity(), d2 = d1;
      size_t best = ref.points.size();
      for (size_t pr = 0; pr < ref.points.size(); ++pr) {
        if ((ref.points[pr] - x).squaredNorm() > r2) continue;
        const double d = distance(pm, pr);
        if (d < d1) {
          d2 = d1, d1 = d, best = pr;
        } else if (d < d2) {
          d2 = d;
        }
      }
      // A lone candidate has no rival to be told from: its descriptor is
      // untested, and taking it would turn the matching into a nearest-point
      // search that a wrong start can settle on.
      if (best == ref.points.size() || std::isinf(d2) || !(d1 < opts.feature_ratio * d2)) continue;
      const int pr = static_cast<int>(best);
      auto it = best_of_ref.find(pr);
      if (it == best_of_ref.end() || d1 < it->second.second)
        best_of_ref[pr] = {static_cast<int>(pm), d1};
    }
    const std::optional<geom::RansacRigidResult> r =
        FitMatches(best_of_ref, ref, mov, opts, &e.pairs);
    if (!r) {
      e.inliers = 0;
      e.note = std::to_string(e.pairs) + " guided matches, no consistent triple";
      return e;
    }
    const bool same = static_cast<int>(r->inliers.size()) == e.inliers &&
                      geom::RotationAngleDeg(r->T.R * e.T.R.transpose()) < 1e-3;
    e.T = r->T;
    e.inliers = static_cast<int>(r->inliers.size());
    e.rms_mm = r->rms_mm;
    e.max_mm = r->max_mm;
    if (same) break;
  }
  if (e.inliers < opts.min_feature_inliers) {
    e.note = "only " + std::to_string(e.inliers) + " of " + std::to_string(e.pairs) +
             " guided feature matches consistent (need " +
             std::to_string(opts.min_feature_inliers) + ")";
    return e;
  }
  if (e.rms_mm > opts.guided_max_rms_mm) {
    e.note = std::to_string(e.inliers) + " of " + std::to_string(e.pairs) +
             " guided feature matches consistent, but spread over the whole gate (RMS " +
             Mm(e.rms_mm) + ", a true fit's is under " + Mm(opts.guided_max_rms_mm) +
             "): a chance alignment";
    return e;
  }
  e.valid = true;
  return e;
}

Result<StitchResult> StitchSides(const SideMarkers& ref, const SideMarkers& mov,
                                 const FeatureCloud* ref_features, const FeatureCloud* mov_features,
                                 const StitchOptions& opts, const SilhouetteStitcher* silhouettes) {
  StitchResult out;
  const bool clouds = ref_features && mov_features;
  out.markers = StitchFromMarkers(ref, mov, opts);
  if (clouds) {
    out.features = StitchFromFeatures(*ref_features, *mov_features, opts);
    // No feature fit of its own: the marker fit, even one that failed its
    // residual test, may be close enough to guide the matching.
    if (!out.features.valid && out.markers.pairs >= 3 && out.markers.inliers >= 3) {
      StitchEstimate g = GuidedFeatureFit(*ref_features, *mov_features, out.markers.T, opts);
      if (g.valid) {
        g.unguided_inliers = out.features.unguided_inliers;
        g.guided_from = "markers";
        out.features = g;
      } else {
        out.features.note += "; guided by the marker fit: " + g.note;
      }
    }
  } else {
    out.features.note = "no feature clouds given";
  }
  const StitchEstimate &m = out.markers, &f = out.features;
  // Displacements are compared over the rock (the moving side's points), where they matter.
  std::vector<Vector3d> rock;
  for (const MarkerPoint& p : mov.points) {
    if (p.located) rock.push_back(p.position);
  }
  if (mov_features)
    rock.insert(rock.end(), mov_features->points.begin(), mov_features->points.end());
  if (m.valid && f.valid) {
    out.cross_checked = true;
    out.disagreement_deg = geom::RotationAngleDeg(m.T.R * f.T.R.transpose());
    out.disagreement_mm = DisplacementRms(m.T, f.T, rock);
    out.consistent = out.disagreement_deg <= opts.agree_deg + 3 * m.rotation_sigma_deg &&
                     out.disagreement_mm <= opts.agree_mm;
  }
  if (m.valid && f.valid) {
    // Both: the features are the more precise (hundreds of points spread
    // over the rock against 3-4 points ~20 mm apart per marker), the markers
    // the check. When they disagree, 4 marker points that fit are trusted
    // over a feature fit, 3 only against a weak feature fit.
    const bool markers_win =
        !out.consistent && (m.inliers >= 4 || f.inliers < 2 * opts.min_feature_inliers);
    out.T = markers_win ? m.T : f.T;
    out.source = markers_win ? "markers" : "features";
  } else if (m.valid) {
    out.T = m.T;
    out.source = "markers";
  } else if (f.valid) {
    out.T = f.T;
    out.source = "features";
  }
  if (silhouettes) {
    SilhouetteRefinement& sr = out.silhouettes;
    // A motion is judged by what it leaves uncovered beyond what each side's
    // own masks disagree on.
    sr.own_deficit = silhouettes->OwnDeficit();
    const double accept = sr.own_deficit + opts.silhouette_accept;
    auto refine = [&](const geom::Rigid3& start, double step_deg) {
      SilhouetteFit fit = silhouettes->Refine(start, step_deg, step_deg);
      sr.evaluations += fit.evaluations;
      sr.seconds += fit.seconds;
      return fit;
    };
    auto record = [&](const std::string& start, const geom::Rigid3& T0, const SilhouetteFit& fit) {
      sr.tried = true;
      sr.start = start;
      sr.deficit_start = fit.deficit_start;
      sr.deficit = fit.deficit;
      sr.moved_deg = geom::RotationAngleDeg(fit.T.R * T0.R.transpose());
      sr.moved_mm = DisplacementRms(fit.T, T0, rock);
    };
    if (out.source == "markers") {
      // The markers' weak axis: refine by the silhouettes, keep it when they confirm.
      const SilhouetteFit fit = refine(m.T, std::max(2.0, 2 * m.rotation_sigma_deg));
      record("markers", m.T, fit);
      if (fit.deficit <= accept) {
        sr.used = true;
        out.T = fit.T;
        out.source = "markers+silhouettes";
      } else {
        sr.note = "the silhouettes do not confirm the marker estimate (deficit " +
                  std::to_string(fit.deficit) + " after refinement); the marker estimate is kept";
        // Marker points misnamed (a head taken for its tail) can still fit one
        // rigid motion, a wrong one. A partial feature fit the silhouettes
        // confirm is then taken instead, and the two are reported as
        // disagreeing.
        if (!f.valid && f.inliers >= 3) {
          const SilhouetteFit ff = refine(f.T, 3.0);
          if (ff.deficit <= accept) {
            const double marker_deficit = fit.deficit;
            record("features (" + std::to_string(f.inliers) + " consistent matches)", f.T, ff);
            sr.used = true;
            out.T = ff.T;
            out.source = "silhouettes";
            out.cross_checked = true;
            out.consistent = false;
            out.disagreement_deg = geom::RotationAngleDeg(m.T.R * ff.T.R.transpose());
            out.disagreement_mm = DisplacementRms(m.T, ff.T, rock);
            sr.note = "the marker estimate leaves " + std::to_string(marker_deficit) +
                      " of the silhouettes uncovered after refinement (accepted up to " +
                      std::to_string(accept) + "); " + std::to_string(f.inliers) +
                      " consistent feature matches, refined by the silhouettes, are taken";
          }
        }
      }
    } else if (out.source == "features") {
      // The feature fit is the more precise when its inliers are many and
      // spread; the silhouettes check it (one deficit evaluation).
      const double d0 = silhouettes->Deficit(f.T);
      ++sr.evaluations;
      // A feature fit the silhouettes contradict (more uncovered than
      // silhouette_accept: few or clustered inliers) is replaced by its
      // refinement when that is coherent; a coherent one is refined too
      // (refine_features) and replaced only by a clearly more coherent
      // motion close to it.
      const bool contradicted = d0 > accept;
      if (contradicted || opts.refine_features) {
        const SilhouetteFit fit = refine(f.T, 2.0);
        record("features", f.T, fit);
        const bool small_move = sr.moved_deg <= opts.agree_deg && sr.moved_mm <= opts.agree_mm;
        if ((contradicted || small_move) && fit.deficit <= accept &&
            fit.deficit < 0.9 * fit.deficit_start) {
          sr.used = true;
          out.T = fit.T;
          out.source = "features+silhouettes";
        } else {
          // The feature estimate is kept: the record's deficit is its own,
          // which the quality flags judge, not the refinement's.
          if (contradicted) {
            sr.note = "the feature estimate leaves " + std::to_string(d0) +
                      " of the silhouettes uncovered (more than " + std::to_string(accept) +
                      ") and its refinement is no better; the feature estimate is kept";
          } else {
            sr.note = "the refinement (" + std::to_string(fit.deficit) + " uncovered, " +
                      std::to_string(sr.moved_deg) +
                      " deg away) is not clearly better; the feature estimate is kept";
          }
          sr.deficit = d0;
        }
      } else {
        sr.tried = true;
        sr.start = "features (check only)";
        sr.deficit_start = sr.deficit = d0;
      }
    } else {
      // Neither estimate alone: refine whatever partial evidence there is.
      struct Start {
        std::string what;
        geom::Rigid3 T;
        double step_deg;
      };
      std::vector<Start> starts;
      if (m.inliers >= 3) starts.push_back({"markers (" + m.note + ")", m.T, 3.0});
      if (f.inliers >= 3) {
        starts.push_back(
            {"features (" + std::to_string(f.inliers) + " consistent matches)", f.T, 3.0});
      }
      // Two marker points fix the motion but for a rotation about the line
      // through them: try rotations about it, keep the most coherent two.
      std::vector<Vector3d> pa, pb;
      std::vector<std::string> pn;
      for (const MarkerPoint& p : mov.points) {
        const MarkerPoint* q = ref.Find(p.color, p.segment);
        if (p.located && q && q->located)
          pa.push_back(p.position), pb.push_back(q->position), pn.push_back(p.Name());
      }
      if (pa.size() == 2 && (pa[1] - pa[0]).norm() > 5.0) {
        const Vector3d da = (pa[1] - pa[0]).normalized(), db = (pb[1] - pb[0]).normalized();
        const Eigen::Matrix3d R0 = Eigen::Quaterniond::FromTwoVectors(da, db).toRotationMatrix();
        const Vector3d ma = 0.5 * (pa[0] + pa[1]), mb = 0.5 * (pb[0] + pb[1]);
        std::vector<std::pair<double, geom::Rigid3>> trials;
        for (double a = 0; a < 360 - 1e-9; a += opts.sweep_deg) {
          geom::Rigid3 T;
          T.R = Eigen::AngleAxisd(a * 3.14159265358979323846 / 180, db).toRotationMatrix() * R0;
          T.t = mb - T.R * ma;
          trials.push_back({silhouettes->Deficit(T), T});
          ++sr.evaluations;
        }
        std::sort(trials.begin(), trials.end(),
                  [](const auto& x, const auto& y) { return x.first < y.first; });
        for (size_t i = 0; i < std::min<size_t>(2, trials.size()); ++i) {
          starts.push_back({pn[0] + " and " + pn[1] + ", swept about their axis", trials[i].second,
                            opts.sweep_deg / 2});
        }
      }
      double best = 2;
      for (const Start& st : starts) {
        const SilhouetteFit fit = refine(st.T, st.step_deg);
        if (fit.deficit < best) {
          best = fit.deficit;
          const int evals = sr.evaluations;
          const double secs = sr.seconds;
          record(st.what, st.T, fit);
          sr.evaluations = evals, sr.seconds = secs;
          out.T = fit.T;
        }
      }
      bool ambiguous = false;
      if (!(sr.tried && sr.deficit <= accept) && opts.search) {
        // Nothing to start from that the silhouettes accept: search every
        // orientation.
        const SilhouetteSearch search = silhouettes->Search(opts.search_options);
        sr.searched = true;
        sr.search_fits = static_cast<int>(search.fits.size());
        sr.search_seconds = search.seconds;
        sr.evaluations += search.evaluations;
        sr.seconds += search.seconds;
        if (!search.fits.empty() && (!sr.tried || search.fits[0].deficit < best)) {
          const SilhouetteFit& b = search.fits[0];
          sr.tried = true;
          sr.start = "search over every orientation";
          sr.deficit_start = b.deficit_start;
          sr.deficit = b.deficit;
          sr.moved_deg = sr.moved_mm = 0;
          out.T = b.T;
          bool unique = true;
          if (search.fits.size() > 1) {
            const SilhouetteFit& r = search.fits[1];
            sr.search_runner_up = r.deficit;
            sr.search_runner_up_deg = geom::RotationAngleDeg(r.T.R * b.T.R.transpose());
            const double eb = b.deficit - sr.own_deficit, er = r.deficit - sr.own_deficit;
            unique = er >= opts.search_unique_ratio * eb && er >= eb + opts.search_unique_margin;
          }
          if (!unique) {
            ambiguous = true;
            sr.note = "the silhouettes fit two motions " + std::to_string(sr.search_runner_up_deg) +
                      " deg apart almost alike (" + std::to_string(b.deficit) + " and " +
                      std::to_string(sr.search_runner_up) + " uncovered, own " +
                      std::to_string(sr.own_deficit) +
                      "): the rock's outline cannot tell them apart";
          }
        }
      }
      if (sr.tried && sr.deficit <= accept && !ambiguous) {
        sr.used = true;
        out.source = "silhouettes";
      } else if (sr.tried && !ambiguous) {
        sr.note = "best silhouette-refined start (" + sr.start + ") leaves " +
                  std::to_string(sr.deficit) + " of the silhouettes uncovered (accepted up to " +
                  std::to_string(accept) + ")";
      } else if (!sr.tried) {
        sr.note =
            "no partial estimate to start from (fewer than 2 marker points on both sides and fewer "
            "than 3 "
            "consistent feature matches)";
      }
    }
  }
  if (out.source.empty()) {
    std::string seen;
    for (const MarkerPoint& p : mov.points) {
      const MarkerPoint* q = ref.Find(p.color, p.segment);
      const bool both = p.located && q && q->located;
      seen += (seen.empty() ? "" : "; ") + p.Name() + (both ? ": located on both" : "");
      if (!both) {
        if (q && !q->located) {
          seen += ": side " + std::to_string(opts.reference_side) + " " + q->problem;
        }
        if (!p.located) seen += ": side " + std::to_string(opts.moving_side) + " " + p.problem;
      }
    }
    return MakeError(
        ErrorClass::kInvalidArgument,
        "stitch: only " + std::to_string(m.pairs) + " marker points located on both sides " +
            std::to_string(opts.reference_side) + " and " + std::to_string(opts.moving_side) +
            (m.pairs >= 3 ? " (" + m.note + ")" : "") + " and " + std::to_string(f.inliers) +
            " consistent feature matches (need 4 marker points, or 3 that agree, or " +
            std::to_string(opts.min_feature_inliers) + " feature matches" +
            (silhouettes ? ", or a partial estimate the silhouettes confirm" : std::string()) +
            "). Re-shoot side " + std::to_string(opts.moving_side) +
            " with the rock placed so that both object markers (purple and red, head and "
            "tail) face the camera in some views, or repaint them where both sides show "
            "them",
        "markers: " + seen + "; features: " + f.note +
            (silhouettes ? "; silhouettes: " + out.silhouettes.note : std::string()));
  }
  if (out.cross_checked && !out.consistent) {
    out.warning = "the marker and feature estimates disagree by " +
                  std::to_string(out.disagreement_deg) + " deg, " + Mm(out.disagreement_mm) +
                  " over the rock; using the " + out.source + " estimate (" +
                  std::to_string(m.inliers) + " marker points, " + Mm(m.rms_mm) + " RMS; " +
                  std::to_string(f.inliers) + " feature pairs, " + Mm(f.rms_mm) + " RMS)";
  }
  return out;
}

}  // namespace aggscan
