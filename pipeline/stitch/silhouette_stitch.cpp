#include "pipeline/stitch/silhouette_stitch.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/optim.hpp>
#include <opencv2/imgproc.hpp>

#include "pipeline/stitch/stitch.h"
#include "pipeline/surface/visual_hull.h"

namespace aggscan {

namespace {

using Eigen::Vector3d;

constexpr double kPi = 3.14159265358979323846;
constexpr double kOutside = -1e9;

struct WorkView {
  cv::Mat mask;  // CV_8U, 0/1, undistorted, working scale
  cv::Mat sd;    // signed distance to the silhouette boundary, px
  cv::Rect roi;  // the mask's bounding box with a margin
  int pixels = 0;
  geom::Rigid3 pose;  // cam_from_table
  int input = 0;      // index into the side's input views
};

struct P3 {
  double x, y, z;
};

// A pose as 12 plain doubles: the hot loops avoid Eigen expression templates,
// whose out-of-line pieces may link to a copy from an unoptimised translation
// unit in Debug builds (10x slower).
struct Pose {
  double m[12];
  explicit Pose(const geom::Rigid3& T) {
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) m[4 * r + c] = T.R(r, c);
      m[4 * r + 3] = T.t(r);
    }
  }
  void Apply(const double* p, double* out) const {
    for (size_t r = 0; r < 3; ++r)
      out[r] = m[4 * r] * p[0] + m[4 * r + 1] * p[1] + m[4 * r + 2] * p[2] + m[4 * r + 3];
  }
};

// Pinhole (undistorted) working camera.
struct Pinhole {
  double fx = 0, fy = 0, cx = 0, cy = 0;
  int width = 0, height = 0;
};

struct Grid {
  Vector3d origin = Vector3d::Zero();
  double h = 1;
  int nx = 0, ny = 0, nz = 0;
  std::vector<float> f;

  size_t Index(int i, int j, int k) const {
    return (static_cast<size_t>(k) * ny + j) * static_cast<size_t>(nx) + i;
  }
  Vector3d Node(int i, int j, int k) const { return origin + h * Vector3d(i, j, k); }
  double Interp(const double* p) const {
    const double gx = (p[0] - origin.x()) / h, gy = (p[1] - origin.y()) / h,
                 gz = (p[2] - origin.z()) / h;
    if (!(gx >= 0 && gy >= 0 && gz >= 0 && gx <= nx - 1 && gy <= ny - 1 && gz <= nz - 1))
      return kOutside;
    const int i = std::min(static_cast<int>(gx), nx - 2),
              j = std::min(static_cast<int>(gy), ny - 2),
              k = std::min(static_cast<int>(gz), nz - 2);
    const double ax = gx - i, ay = gy - j, az = gz - k;
    auto at = [&](int di, int dj, int dk) {
      return static_cast<double>(f[Index(i + di, j + dj, k + dk)]);
    };
    const double c00 = at(0, 0, 0) * (1 - ax) + at(1, 0, 0) * ax;
    const double c10 = at(0, 1, 0) * (1 - ax) + at(1, 1, 0) * ax;
    const double c01 = at(0, 0, 1) * (1 - ax) + at(1, 0, 1) * ax;
    const double c11 = at(0, 1, 1) * (1 - ax) + at(1, 1, 1) * ax;
    return (c00 * (1 - ay) + c10 * ay) * (1 - az) + (c01 * (1 - ay) + c11 * ay) * az;
  }
};

struct Side {
  std::vector<WorkView> views;
  Grid grid;
};

Pinhole WorkingCamera(const CameraModel& cam, double s) {
  const CameraModel r = cam.Resized(std::max(8, static_cast<int>(std::lround(cam.width * s))),
                                    std::max(8, static_cast<int>(std::lround(cam.height * s))));
  return {r.fx, r.fy, r.cx, r.cy, r.width, r.height};
}

// The side's masks at scale s, undistorted, with their signed distances.
std::vector<WorkView> PrepareViews(const SilhouetteSideInput& in, const std::vector<int>& use,
                                   const CameraModel& cam, const Pinhole& pc) {
  const cv::Size size(pc.width, pc.height);
  const cv::Matx33d K(pc.fx, 0, pc.cx, 0, pc.fy, pc.cy, 0, 0, 1);
  const std::vector<double> dist{cam.k1, cam.k2, cam.p1, cam.p2, cam.k3};
  cv::Mat map1, map2;
  cv::initUndistortRectifyMap(K, dist, cv::Matx33d::eye(), K, size, CV_32FC1, map1, map2);
  std::vector<WorkView> out;
  for (int i : use) {
    WorkView w;
    cv::Mat small, und;
    cv::resize(in.masks[i], small, size, 0, 0, cv::INTER_AREA);
    cv::remap(small, und, map1, map2, cv::INTER_LINEAR, cv::BORDER_CONSTANT, 0);
    cv::threshold(und, w.mask, 127, 1, cv::THRESH_BINARY);
    w.pixels = cv::countNonZero(w.mask);
    if (w.pixels < 16) continue;
    cv::Mat m255;
    w.mask.convertTo(m255, CV_8U, 255);
    w.sd = SilhouetteSignedDistance(m255);
    const int margin = 4;
    w.roi =
        (cv::boundingRect(w.mask) + cv::Size(2 * margin, 2 * margin) - cv::Point(margin, margin)) &
        cv::Rect(0, 0, pc.width, pc.height);
    w.pose = in.cam_from_table[i];
    w.input = i;
    out.push_back(std::move(w));
  }
  return out;
}

// The side's hull field at p (mm, positive inside): the floor z >= 0 and every
// view's silhouette distance at the point's depth. Stops early below stop_below.
double Field(const std::vector<WorkView>& views, const Pinhole& pc, const Vector3d& p,
             double stop_below) {
  double f = p.z();
  if (f < stop_below) return f;
  const double q[3] = {p.x(), p.y(), p.z()};
  for (const WorkView& w : views) {
    double c[3];
    Pose(w.pose).Apply(q, c);
    if (c[2] <= 1) return kOutside;
    const double u = pc.fx * c[0] / c[2] + pc.cx, v = pc.fy * c[1] / c[2] + pc.cy;
    f = std::min(f, SampleSignedDistance(w.sd, u, v) * c[2] / pc.fx);
    if (f < stop_below) return f;
  }
  return f;
}

Grid SampleGrid(const std::vector<WorkView>& views, const Pinhole& pc,
                const Eigen::AlignedBox3d& box, double h, double stop_below) {
  Grid g;
  g.origin = box.min();
  g.h = h;
  const Vector3d n = (box.max() - box.min()) / h;
  g.nx = static_cast<int>(std::ceil(n.x())) + 1;
  g.ny = static_cast<int>(std::ceil(n.y())) + 1;
  g.nz = static_cast<int>(std::ceil(n.z())) + 1;
  g.f.resize(static_cast<size_t>(g.nx) * g.ny * g.nz);
  for (int k = 0; k < g.nz; ++k) {
    for (int j = 0; j < g.ny; ++j) {
      for (int i = 0; i < g.nx; ++i) {
        g.f[g.Index(i, j, k)] =
            static_cast<float>(std::max(Field(views, pc, g.Node(i, j, k), stop_below), -1e6));
      }
    }
  }
  return g;
}

struct Occupied {
  Eigen::AlignedBox3d box;
  Vector3d centre = Vector3d::Zero();
  double volume = 0;
};

Occupied OccupiedRegion(const Grid& g) {
  Occupied o;
  int n = 0;
  for (int k = 0; k < g.nz; ++k) {
    for (int j = 0; j < g.ny; ++j) {
      for (int i = 0; i < g.nx; ++i) {
        if (g.f[g.Index(i, j, k)] > 0) {
          const Vector3d p = g.Node(i, j, k);
          o.box.extend(p);
          o.centre += p;
          ++n;
        }
      }
    }
  }
  if (n > 0) o.centre /= n;
  o.volume = n * g.h * g.h * g.h;
  return o;
}

// Up to max_views of the side's distinct viewpoints, spread evenly.
std::vector<int> PickViews(const SilhouetteSideInput& in, int max_views) {
  std::vector<int> distinct = DistinctViewpoints(in.cam_from_table);
  std::vector<int> use;
  const int n = static_cast<int>(distinct.size());
  const int k = std::min(n, std::max(1, max_views));
  use.reserve(static_cast<size_t>(k));
  for (int i = 0; i < k; ++i) use.push_back(distinct[static_cast<size_t>(i * n / k)]);
  return use;
}

// Per view of a side, the grid nodes above the floor that its mask alone
// projects outside its silhouette, and the nodes every view holds inside:
// the views whose masks lost part of the rock (DisagreeingViews). Such a
// part is cut out of the side's hull, and in the stitch the other side's
// views then miss it whatever the motion.
std::vector<size_t> SoleCarvingOutliers(const std::vector<WorkView>& views, const Pinhole& pc,
                                        const Grid& g) {
  std::vector<double> sole(views.size(), 0.0);
  double agreed = 0;
  std::vector<Pose> poses;
  poses.reserve(views.size());
  for (const WorkView& w : views) poses.emplace_back(w.pose);
  for (int k = 0; k < g.nz; ++k) {
    for (int j = 0; j < g.ny; ++j) {
      for (int i = 0; i < g.nx; ++i) {
        const Vector3d p = g.Node(i, j, k);
        if (p.z() < 0) continue;
        const double q[3] = {p.x(), p.y(), p.z()};
        int outside = 0;
        size_t first = 0;
        for (size_t v = 0; v < views.size() && outside < 2; ++v) {
          double c[3];
          poses[v].Apply(q, c);
          const bool out =
              c[2] <= 1 || SampleSignedDistance(views[v].sd, pc.fx * c[0] / c[2] + pc.cx,
                                                pc.fy * c[1] / c[2] + pc.cy) < 0;
          if (out && outside++ == 0) first = v;
        }
        if (outside == 0) agreed += 1;
        if (outside == 1) sole[first] += 1;
      }
    }
  }
  return DisagreeingViews(sole, agreed);
}

}  // namespace

struct SilhouetteStitcher::Impl {
  Pinhole cam;
  double scale = 1;
  double h = 1;
  int splat = 1;  // half-width of a voxel's footprint, px
  Side ref, mov;
  std::vector<P3> ref_points;  // reference grid nodes that may be inside
  std::vector<float> ref_values;
  Vector3d centre = Vector3d::Zero();
  Vector3d moving_centre = Vector3d::Zero();
  std::vector<int> left_out_ref, left_out_mov;  // input views left out (SoleCarvingOutliers)
  double own_deficit = 0;                       // each side's hull in its own views (OwnDeficit)
};

namespace {

// Grid nodes of a side's hull field that may be inside, with their values.
void NodesInside(const Grid& g, double h, std::vector<P3>* points, std::vector<float>* values) {
  for (int k = 0; k < g.nz; ++k) {
    for (int j = 0; j < g.ny; ++j) {
      for (int i = 0; i < g.nx; ++i) {
        const float f = g.f[g.Index(i, j, k)];
        if (f > -0.5 * h) {
          const Vector3d p = g.Node(i, j, k);
          points->push_back({p.x(), p.y(), p.z()});
          values->push_back(f);
        }
      }
    }
  }
}

// Soft voxel occupancy of a field value: 0.5 on the surface, 1 half a voxel inside.
float Occupancy(double f, double h) {
  return static_cast<float>(std::clamp(0.5 + f / h, 0.0, 1.0));
}

// The fraction of one view's rock pixels that voxels `pts` (occupancies
// `occ`, in the frame `pose` maps into the camera) leave uncovered.
// `splat`: half-width of a voxel's footprint in the working camera `cam`, px.
double ViewDeficit(const Pinhole& cam, int splat, const WorkView& w, const Pose& pose,
                   const std::vector<P3>& pts, const std::vector<float>& occ, cv::Mat* cov) {
  cov->create(w.roi.height, w.roi.width, CV_32F);
  cov->setTo(0);
  const int r = splat;
  const double fx = cam.fx, fy = cam.fy, cx = cam.cx - w.roi.x, cy = cam.cy - w.roi.y;
  const int W = w.roi.width, H = w.roi.height;
  for (size_t i = 0; i < pts.size(); ++i) {
    double c[3];
    pose.Apply(&pts[i].x, c);
    if (c[2] <= 1) continue;
    const int u = static_cast<int>(std::floor(fx * c[0] / c[2] + cx + 0.5));
    const int v = static_cast<int>(std::floor(fy * c[1] / c[2] + cy + 0.5));
    if (u < -r || v < -r || u >= W + r || v >= H + r) continue;
    const float o = occ[i];
    for (int y = std::max(0, v - r); y <= std::min(H - 1, v + r); ++y) {
      float* row = cov->ptr<float>(y);
      for (int x = std::max(0, u - r); x <= std::min(W - 1, u + r); ++x)
        row[x] = std::max(row[x], o);
    }
  }
  double miss = 0;
  for (int y = 0; y < H; ++y) {
    const uchar* mk = w.mask.ptr<uchar>(y + w.roi.y) + w.roi.x;
    const float* row = cov->ptr<float>(y);
    for (int x = 0; x < W; ++x) {
      if (mk[x]) miss += 1.0 - row[x];
    }
  }
  return miss / w.pixels;
}

}  // namespace

Result<SilhouetteStitcher> SilhouetteStitcher::Create(const SilhouetteSideInput& reference,
                                                      const SilhouetteSideInput& moving,
                                                      const CameraModel& camera,
                                                      const SilhouetteStitchOptions& opts) {
  for (const SilhouetteSideInput* s : {&reference, &moving}) {
    if (s->masks.size() != s->cam_from_table.size() || s->masks.empty()) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "silhouette stitch: a side has no views or masks and poses "
                       "that do not pair up");
    }
    for (const cv::Mat& m : s->masks) {
      if (m.type() != CV_8UC1 || m.cols != camera.width || m.rows != camera.height) {
        return MakeError(ErrorClass::kInvalidArgument,
                         "silhouette stitch: a mask is not an 8-bit image at the "
                         "calibrated resolution");
      }
    }
  }
  auto impl = std::make_shared<Impl>();
  const std::vector<int> use_ref = PickViews(reference, opts.max_views);
  const std::vector<int> use_mov = PickViews(moving, opts.max_views);
  // Coarse pass (working width ~500 px, 4 mm grid over the disc) for each
  // side's extent, the rock's size and its distance from the camera.
  const double s0 = std::min(1.0, 504.0 / camera.width);
  const Pinhole p0 = WorkingCamera(camera, s0);
  const Eigen::AlignedBox3d search(Vector3d(-200, -200, 0), Vector3d(200, 200, 320));
  const double coarse = 4.0;
  std::array<Occupied, 2> occ;
  for (int si = 0; si < 2; ++si) {
    const SilhouetteSideInput& in = si == 0 ? reference : moving;
    const std::vector<WorkView> views = PrepareViews(in, si == 0 ? use_ref : use_mov, camera, p0);
    if (views.size() < 3) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "silhouette stitch: side " + std::string(si == 0 ? "1" : "2") +
                           " has fewer than 3 views with a rock mask");
    }
    occ[si] = OccupiedRegion(SampleGrid(views, p0, search, coarse, -2 * coarse));
    if (occ[si].volume <= 0) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "silhouette stitch: the silhouettes of side " +
                           std::string(si == 0 ? "1" : "2") +
                           " do not intersect (masks or poses are wrong)");
    }
  }
  double depth = 0;
  for (int i : use_ref) depth += reference.cam_from_table[i].Apply(occ[0].centre).z();
  depth /= static_cast<double>(use_ref.size());
  impl->h = std::clamp(std::cbrt(occ[0].volume / std::max(1000, opts.target_points)), 0.3, 8.0);
  impl->scale = std::clamp(opts.voxel_px * depth / (impl->h * camera.fx), 0.05, 1.0);
  impl->cam = WorkingCamera(camera, impl->scale);
  impl->splat = std::max(1, static_cast<int>(std::lround(0.5 * impl->h * impl->cam.fx / depth)));
  impl->centre = occ[0].centre;
  impl->moving_centre = occ[1].centre;
  for (int si = 0; si < 2; ++si) {
    const SilhouetteSideInput& in = si == 0 ? reference : moving;
    Side& side = si == 0 ? impl->ref : impl->mov;
    side.views = PrepareViews(in, si == 0 ? use_ref : use_mov, camera, impl->cam);
    // The grid reaches a quarter of the hull's size beyond it (rock that one
    // view's mask lost lies outside the hull of all the views), in whole
    // voxels beyond a margin of two coarse cells: the nodes near the rock lie
    // where they would with that margin alone.
    Eigen::AlignedBox3d box = occ[si].box;
    Vector3d grow;
    for (int a = 0; a < 3; ++a) {
      const double extra = std::max(0.0, 0.25 * box.sizes()(a) - 2 * coarse);
      grow(a) = 2 * coarse + std::ceil(extra / impl->h) * impl->h;
    }
    box.min() -= grow;
    box.max() += grow;
    box.min().z() = std::max(box.min().z(), -impl->h);
    side.grid = SampleGrid(side.views, impl->cam, box, impl->h, -2 * impl->h);
    const std::vector<size_t> bad = opts.leave_out_disagreeing
                                        ? SoleCarvingOutliers(side.views, impl->cam, side.grid)
                                        : std::vector<size_t>{};
    // Left out only while two thirds of the views stay: beyond that the masks
    // as a whole are in doubt, and the deficits say so.
    if (!bad.empty() && 3 * bad.size() <= side.views.size()) {
      std::vector<WorkView> kept;
      for (size_t v = 0; v < side.views.size(); ++v) {
        if (std::find(bad.begin(), bad.end(), v) == bad.end()) {
          kept.push_back(std::move(side.views[v]));
        } else {
          (si == 0 ? impl->left_out_ref : impl->left_out_mov).push_back(side.views[v].input);
        }
      }
      side.views = std::move(kept);
      side.grid = SampleGrid(side.views, impl->cam, box, impl->h, -2 * impl->h);
    }
  }
  NodesInside(impl->ref.grid, impl->h, &impl->ref_points, &impl->ref_values);
  {
    // What the masks leave uncovered before the sides meet: each side's
    // own hull in its own views (shadows and backdrop the side's other views
    // carve away, a mask's missing rock).
    std::vector<P3> mov_points;
    std::vector<float> mov_values;
    NodesInside(impl->mov.grid, impl->h, &mov_points, &mov_values);
    cv::Mat cov;
    double sum = 0;
    int n = 0;
    for (int si = 0; si < 2; ++si) {
      const std::vector<P3>& pts = si == 0 ? impl->ref_points : mov_points;
      const std::vector<float>& vals = si == 0 ? impl->ref_values : mov_values;
      std::vector<float> occ(vals.size());
      for (size_t i = 0; i < vals.size(); ++i) occ[i] = Occupancy(vals[i], impl->h);
      for (const WorkView& w : (si == 0 ? impl->ref : impl->mov).views) {
        sum += ViewDeficit(impl->cam, impl->splat, w, Pose(w.pose), pts, occ, &cov);
        ++n;
      }
    }
    impl->own_deficit = n > 0 ? sum / n : 0.0;
  }
  SilhouetteStitcher s;
  s.impl_ = std::move(impl);
  return s;
}

double SilhouetteStitcher::OwnDeficit() const { return impl_->own_deficit; }

double SilhouetteStitcher::Deficit(const geom::Rigid3& T) const {
  const Impl& m = *impl_;
  const geom::Rigid3 Ti = T.Inverse();
  const Pose ti(Ti);
  // The intersection of the two hulls, as soft voxel occupancies on the
  // reference grid (0.5 on the surface, 1 half a voxel inside).
  std::vector<P3> pts;
  std::vector<float> occ;
  pts.reserve(m.ref_points.size());
  occ.reserve(m.ref_points.size());
  for (size_t i = 0; i < m.ref_points.size(); ++i) {
    double q[3];
    ti.Apply(&m.ref_points[i].x, q);
    const double f = std::min<double>(m.ref_values[i], m.mov.grid.Interp(q));
    const float o = Occupancy(f, m.h);
    if (o > 0) {
      pts.push_back(m.ref_points[i]);
      occ.push_back(o);
    }
  }
  if (pts.empty()) return 1.0;
  double sum = 0;
  int n = 0;
  cv::Mat cov;
  for (const WorkView& w : m.ref.views)
    sum += ViewDeficit(m.cam, m.splat, w, Pose(w.pose), pts, occ, &cov), ++n;
  for (const WorkView& w : m.mov.views)
    sum += ViewDeficit(m.cam, m.splat, w, Pose(w.pose * Ti), pts, occ, &cov), ++n;
  return sum / n;
}

namespace {

// T(x) = A(x) * T0, A rotating by the rotation vector x[0..2] (deg) about c
// and translating by x[3..5] (mm).
geom::Rigid3 Perturbed(const geom::Rigid3& T0, const Vector3d& c, const double* x) {
  const Vector3d w(x[0], x[1], x[2]);
  const double ang = w.norm() * kPi / 180.0;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  if (ang > 0) R = Eigen::AngleAxisd(ang, w.normalized()).toRotationMatrix();
  geom::Rigid3 A;
  A.R = R;
  A.t = c - R * c + Vector3d(x[3], x[4], x[5]);
  return A * T0;
}

class DeficitFunction : public cv::MinProblemSolver::Function {
 public:
  DeficitFunction(const SilhouetteStitcher& s, const geom::Rigid3& T0, const Vector3d& c,
                  int* evals)
      : s_(s), T0_(T0), c_(c), evals_(evals) {}
  int getDims() const override { return 6; }
  double calc(const double* x) const override {
    ++*evals_;
    return s_.Deficit(Perturbed(T0_, c_, x));
  }

 private:
  const SilhouetteStitcher& s_;
  geom::Rigid3 T0_;
  Vector3d c_;
  int* evals_;
};

}  // namespace

SilhouetteFit SilhouetteStitcher::Refine(const geom::Rigid3& start, double step_deg,
                                         double step_mm) const {
  const auto t0 = std::chrono::steady_clock::now();
  SilhouetteFit fit;
  fit.T = start;
  fit.deficit_start = fit.deficit = Deficit(start);
  fit.evaluations = 1;
  // Coarse-to-fine restarts: Nelder-Mead on a piecewise-smooth objective
  // settles early; restarting with smaller steps from the best point
  // continues where a single run would stall.
  const int budget = 400;
  for (double f : {1.0, 0.4, 0.15}) {
    int evals = 0;
    cv::Ptr<DeficitFunction> fn = cv::makePtr<DeficitFunction>(*this, fit.T, impl_->centre, &evals);
    cv::Mat step = (cv::Mat_<double>(1, 6) << step_deg * f, step_deg * f, step_deg * f, step_mm * f,
                    step_mm * f, step_mm * f);
    cv::Ptr<cv::DownhillSolver> solver = cv::DownhillSolver::create(
        fn, step,
        cv::TermCriteria(cv::TermCriteria::MAX_ITER + cv::TermCriteria::EPS, budget / 3, 1e-5));
    cv::Mat x = cv::Mat::zeros(1, 6, CV_64F);
    const double val = solver->minimize(x);
    fit.evaluations += evals;
    if (val < fit.deficit) {
      fit.deficit = val;
      fit.T = Perturbed(fit.T, impl_->centre, x.ptr<double>());
    }
  }
  fit.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return fit;
}

SilhouetteSearch SilhouetteStitcher::Search(const SilhouetteSearchOptions& opts) const {
  const auto t0 = std::chrono::steady_clock::now();
  const Vector3d c1 = impl_->centre, c2 = impl_->moving_centre;
  std::vector<std::pair<double, geom::Rigid3>> coarse;
  const int nd = std::max(1, opts.directions), nt = std::max(1, opts.turns);
  coarse.reserve(static_cast<size_t>(nd) * nt);
  const double golden = kPi * (3 - std::sqrt(5.0));  // Fibonacci sphere: even spread
  for (int i = 0; i < nd; ++i) {
    const double z = 1 - 2 * (i + 0.5) / nd, r = std::sqrt(std::max(0.0, 1 - z * z));
    const Vector3d up(r * std::cos(golden * i), r * std::sin(golden * i), z);
    const Eigen::Matrix3d R0 =
        Eigen::Quaterniond::FromTwoVectors(Vector3d::UnitZ(), up).toRotationMatrix();
    for (int k = 0; k < nt; ++k) {
      geom::Rigid3 T;
      T.R = Eigen::AngleAxisd(2 * kPi * k / nt, up).toRotationMatrix() * R0;
      T.t = c1 - T.R * c2;
      coarse.emplace_back(Deficit(T), T);
    }
  }
  std::sort(coarse.begin(), coarse.end(),
            [](const auto& a, const auto& b) { return a.first < b.first; });
  SilhouetteSearch out;
  std::vector<SilhouetteFit>& fits = out.fits;
  out.evaluations = static_cast<int>(coarse.size());
  // The most coherent candidates, each at least distinct_deg from the ones
  // already refined and from where they went; refined until `refine` have
  // been and two motions stand apart (the runner-up tells how unique the
  // best is), or twice that many.
  std::vector<geom::Rigid3> starts;
  auto far_from = [&](const geom::Rigid3& T, double deg) {
    for (const geom::Rigid3& S : starts) {
      if (geom::RotationAngleDeg(S.R * T.R.transpose()) < deg) return false;
    }
    for (const SilhouetteFit& f : fits) {
      if (geom::RotationAngleDeg(f.T.R * T.R.transpose()) < deg) return false;
    }
    return true;
  };
  for (const auto& [d, T] : coarse) {
    const int n = static_cast<int>(starts.size());
    if ((n >= opts.refine && fits.size() >= 2) || n >= 2 * opts.refine) break;
    if (!far_from(T, opts.distinct_deg)) continue;
    starts.push_back(T);
    SilhouetteFit f = Refine(T, opts.step_deg, opts.step_deg);
    out.evaluations += f.evaluations;
    bool merged = false;
    for (SilhouetteFit& g : fits) {
      if (geom::RotationAngleDeg(g.T.R * f.T.R.transpose()) < opts.distinct_deg / 4) {
        if (f.deficit < g.deficit) g = f;
        merged = true;
      }
    }
    if (!merged) fits.push_back(f);
  }
  std::sort(fits.begin(), fits.end(),
            [](const SilhouetteFit& a, const SilhouetteFit& b) { return a.deficit < b.deficit; });
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return out;
}

double SilhouetteStitcher::voxel_mm() const { return impl_->h; }
Eigen::Vector3d SilhouetteStitcher::reference_centre() const { return impl_->centre; }
const std::vector<int>& SilhouetteStitcher::left_out(int side) const {
  return side == 0 ? impl_->left_out_ref : impl_->left_out_mov;
}
int SilhouetteStitcher::views_used() const { return static_cast<int>(impl_->ref.views.size()); }
double SilhouetteStitcher::image_scale() const { return impl_->scale; }

SilhouettePolish PolishSilhouetteStitch(const SilhouetteStitcher& coarse,
                                        const SilhouetteSideInput& reference,
                                        const SilhouetteSideInput& moving,
                                        const CameraModel& camera, const geom::Rigid3& start,
                                        const SilhouetteStitchOptions& coarse_opts) {
  const auto t0 = std::chrono::steady_clock::now();
  SilhouettePolish out;
  out.T = start;
  // Half the voxel needs twice the working scale: at or over the full photo,
  // the finer voxel spans under voxel_px pixels and the photos cannot resolve
  // it (sim seed 6 at 1008x756: 0.61 -> 0.69 deg).
  if (2 * coarse.image_scale() >= 1.0) {
    out.voxel_mm = coarse.voxel_mm() / 2;
    out.problem =
        "the photos do not resolve a grid of " + std::to_string(out.voxel_mm) + " mm; not polished";
    out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    return out;
  }
  SilhouetteStitchOptions fine = coarse_opts;
  fine.target_points = 8 * coarse_opts.target_points;  // half the voxel
  fine.max_evaluations = 150;
  // The views the coarse stitcher left out, judged on its grid, stay out.
  fine.leave_out_disagreeing = false;
  auto without = [](const SilhouetteSideInput& in, const std::vector<int>& out) {
    SilhouetteSideInput kept;
    for (size_t i = 0; i < in.masks.size(); ++i) {
      if (std::find(out.begin(), out.end(), static_cast<int>(i)) != out.end()) continue;
      kept.masks.push_back(in.masks[i]);
      kept.cam_from_table.push_back(in.cam_from_table[i]);
    }
    return kept;
  };
  auto st = SilhouetteStitcher::Create(without(reference, coarse.left_out(0)),
                                       without(moving, coarse.left_out(1)), camera, fine);
  if (!st) {
    out.problem = st.error().message;
  } else {
    out.voxel_mm = st->voxel_mm();
    out.deficit_start = st->Deficit(start);
    const SilhouetteFit fit = st->Refine(start, 0.5, 0.5);
    out.evaluations = fit.evaluations + 1;
    out.deficit = out.deficit_start;
    if (fit.deficit < out.deficit_start) {
      out.done = true;
      out.T = fit.T;
      out.deficit = fit.deficit;
      out.moved_deg = geom::RotationAngleDeg(fit.T.R * start.R.transpose());
    }
  }
  out.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return out;
}

}  // namespace aggscan
