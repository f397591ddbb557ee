#include "pipeline/surface/photo_refine.h"

#include <Eigen/Cholesky>
#include <Eigen/LU>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <functional>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <string>
#include <utility>

#include "pipeline/core/parallel_for.h"
#include "pipeline/surface/photo_refine_steps.h"

namespace aggscan {

std::vector<std::string> PhotoRefineOptions::Check() const {
  std::vector<std::string> p;
  if (!(max_depth_mm > 0)) p.push_back("max_depth_mm must be > 0");
  if (!(step_mm > 0) || step_mm > max_depth_mm) p.push_back("step_mm must be in (0, max_depth_mm]");
  if (depth_search_stride < 1) p.push_back("depth_search_stride must be >= 1");
  if (views_per_vertex < 2)
    p.push_back("views_per_vertex must be >= 2 (a reference and one to compare)");
  if (!(min_baseline_deg >= 0 && min_baseline_deg < 90))
    p.push_back("min_baseline_deg must be in [0, 90)");
  if (!(min_cos > 0 && min_cos < 1)) p.push_back("min_cos must be in (0, 1)");
  if (patch_radius < 1 || patch_radius > 10) p.push_back("patch_radius must be in 1..10");
  if (!(patch_spacing_px > 0)) p.push_back("patch_spacing_px must be > 0");
  if (!(image_scale > 0 && image_scale <= 1)) p.push_back("image_scale must be in (0, 1]");
  if (blur_sigma_px < 0) p.push_back("blur_sigma_px must be >= 0");
  if (depth_map_downscale < 1) p.push_back("depth_map_downscale must be >= 1");
  if (!(depth_tolerance_mm > 0)) p.push_back("depth_tolerance_mm must be > 0");
  if (!(min_ncc > -1 && min_ncc < 1)) p.push_back("min_ncc must be in (-1, 1)");
  if (min_gain < 0) p.push_back("min_gain must be >= 0");
  if (!(near_hull_mm >= 0 && near_hull_mm <= max_depth_mm))
    p.push_back("near_hull_mm must be in [0, max_depth_mm]");
  if (!(outside_mm >= 0 && outside_mm <= 5)) p.push_back("outside_mm must be in [0, 5]");
  if (!(highlight_depth_ratio >= 0 && highlight_depth_ratio <= 2))
    p.push_back("highlight_depth_ratio must be in [0, 2] (0: off)");
  if (!(highlight_reach_mm > 0 && highlight_reach_mm <= 50))
    p.push_back("highlight_reach_mm must be in (0, 50]");
  if (!(move_reach >= 0 && move_reach <= 4)) p.push_back("move_reach must be in [0, 4]");
  if (!(min_on_rock > 0 && min_on_rock <= 1)) p.push_back("min_on_rock must be in (0, 1]");
  if (untangle_passes < 0) p.push_back("untangle_passes must be >= 0");
  if (sample_rings < 0 || sample_rings > 3) p.push_back("sample_rings must be in 0..3");
  if (smooth_iterations < 0) p.push_back("smooth_iterations must be >= 0");
  if (!(smooth_lambda > 0)) p.push_back("smooth_lambda must be > 0");
  if (!(outlier_mm > 0)) p.push_back("outlier_mm must be > 0");
  if (!(max_face_turn_deg > 0 && max_face_turn_deg < 180))
    p.push_back("max_face_turn_deg must be in (0, 180)");
  if (surface_smooth_iterations < 0) p.push_back("surface_smooth_iterations must be >= 0");
  if (threads < 1) p.push_back("threads must be >= 1");
  return p;
}

namespace photo_refine {
namespace {

// OpenCV's lens model (see rig_calibration.h), inline: this is the hot loop.
inline bool ProjectCam(const CameraModel& c, const Vec3& p, double* u, double* v) {
  if (!(p.z() > 1e-6)) return false;
  const double x = p.x() / p.z(), y = p.y() / p.z();
  const double r2 = x * x + y * y;
  const double radial = 1 + r2 * (c.k1 + r2 * (c.k2 + r2 * c.k3));
  const double xd = x * radial + 2 * c.p1 * x * y + c.p2 * (r2 + 2 * x * x);
  const double yd = y * radial + c.p1 * (r2 + 2 * y * y) + 2 * c.p2 * x * y;
  *u = c.fx * xd + c.cx;
  *v = c.fy * yd + c.cy;
  return true;
}

inline bool Bilinear(const cv::Mat& img, double u, double v, float* out) {
  if (!(u >= 0 && v >= 0 && u < img.cols - 1 && v < img.rows - 1)) return false;
  const int x = static_cast<int>(u), y = static_cast<int>(v);
  const float fx = static_cast<float>(u - x), fy = static_cast<float>(v - y);
  const float* r0 = img.ptr<float>(y) + x;
  const float* r1 = img.ptr<float>(y + 1) + x;
  *out = (1 - fy) * ((1 - fx) * r0[0] + fx * r0[1]) + fy * ((1 - fx) * r1[0] + fx * r1[1]);
  return true;
}

// Normalised cross-correlation of two equally long sample vectors over the
// samples whose on-rock flags are both set; false when fewer than min_count
// are, or either side is flat (no texture to compare).
inline bool NccOnRock(const float* a, const float* b, const uint8_t* ma, const uint8_t* mb, int n,
                      int min_count, double min_var, double* out) {
  double sa = 0, sb = 0, saa = 0, sbb = 0, sab = 0;
  int c = 0;
  for (int i = 0; i < n; ++i) {
    if (!ma[i] || !mb[i]) continue;
    ++c;
    sa += a[i];
    sb += b[i];
    saa += a[i] * a[i];
    sbb += b[i] * b[i];
    sab += a[i] * b[i];
  }
  if (c < min_count) return false;
  const double va = saa - sa * sa / c, vb = sbb - sb * sb / c;
  if (va < min_var * c || vb < min_var * c) return false;
  *out = (sab - sa * sb / c) / std::sqrt(va * vb);
  return true;
}

std::vector<Vec3> VertexNormals(const std::vector<Vec3>& V, const Faces& F) {
  std::vector<Vec3> n(V.size(), Vec3::Zero());
  for (const auto& f : F) {
    const Vec3 fn = (V[f[1]] - V[f[0]]).cross(V[f[2]] - V[f[0]]);  // area-weighted
    for (int k = 0; k < 3; ++k) n[f[k]] += fn;
  }
  for (auto& x : n) {
    const double l = x.norm();
    x = l > 0 ? Vec3(x / l) : Vec3::UnitZ();
  }
  return n;
}

Rings Neighbours(size_t nv, const Faces& F) {
  Rings nb(nv);
  for (const auto& f : F) {
    for (int k = 0; k < 3; ++k) {
      nb[f[k]].push_back(f[(k + 1) % 3]);
      nb[f[k]].push_back(f[(k + 2) % 3]);
    }
  }
  for (auto& l : nb) {
    std::sort(l.begin(), l.end());
    l.erase(std::unique(l.begin(), l.end()), l.end());
  }
  return nb;
}

// Data-weighted Laplacian smoothing: x_i <- (w_i d_i + lambda mean_j x_j) /
// (w_i + lambda); vertices without data (w = 0) take their neighbours' mean.
std::vector<double> SmoothField(std::vector<double> x, const std::vector<double>& data,
                                const std::vector<double>& w, const Rings& nb, int iterations,
                                double lambda) {
  std::vector<double> next(x.size());
  for (int it = 0; it < iterations; ++it) {
    for (size_t i = 0; i < x.size(); ++i) {
      if (nb[i].empty()) {
        next[i] = x[i];
        continue;
      }
      double s = 0;
      for (int j : nb[i]) s += x[j];
      next[i] = (w[i] * data[i] + lambda * s / nb[i].size()) / (w[i] + lambda);
    }
    x.swap(next);
  }
  return x;
}

// The surface's local quadric at V[i] in the tangent basis (t1, t2) of the
// normal n: heights above the tangent plane h = -(A x^2 + 2 B x y + C y^2) / 2
// (A, C > 0 where the surface is convex), least squares over the mesh
// vertices within `reach` of V[i] that are connected to it within that reach.
// Curvatures are clamped to 1/reach; zero when fewer than 8 vertices fit.
Eigen::Vector3d LocalQuadric(const std::vector<Vec3>& V, const Rings& nb, size_t i, const Vec3& n,
                             const Vec3& t1, const Vec3& t2, double reach) {
  const Vec3& p = V[i];
  std::vector<int> seen{static_cast<int>(i)}, front{static_cast<int>(i)}, next;
  Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
  Eigen::Vector3d rhs = Eigen::Vector3d::Zero();
  int used = 0;
  while (!front.empty() && seen.size() < 400) {
    next.clear();
    for (int a : front) {
      for (int b : nb[a]) {
        if (std::find(seen.begin(), seen.end(), b) != seen.end()) continue;
        seen.push_back(b);
        const Vec3 d = V[b] - p;
        if (d.norm() > reach) continue;
        next.push_back(b);
        const double x = d.dot(t1), y = d.dot(t2);
        const Eigen::Vector3d row(-0.5 * x * x, -x * y, -0.5 * y * y);
        M += row * row.transpose();
        rhs += row * d.dot(n);
        ++used;
      }
    }
    front.swap(next);
  }
  if (used < 8) return Eigen::Vector3d::Zero();
  Eigen::LDLT<Eigen::Matrix3d> ldlt(M);
  if (ldlt.info() != Eigen::Success || !(std::abs(M.determinant()) > 1e-12))
    return Eigen::Vector3d::Zero();
  const Eigen::Vector3d k = ldlt.solve(rhs);
  const double lim = 1.0 / reach;
  return k.cwiseMax(-lim).cwiseMin(lim);
}

}  // namespace

Status CheckInputs(const std::vector<PhotoView>& views, const PhotoRefineOptions& opts) {
  if (auto problems = opts.Check(); !problems.empty()) {
    std::string m = "photo refinement options:";
    for (const auto& p : problems) m += " " + p + ";";
    return MakeError(ErrorClass::kInvalidArgument, m);
  }
  if (views.size() < 2) {
    return MakeError(
        ErrorClass::kInvalidArgument,
        "photo refinement needs at least two views, got " + std::to_string(views.size()));
  }
  for (size_t i = 0; i < views.size(); ++i) {
    const PhotoView& v = views[i];
    if (v.image.empty() || v.image.cols != v.camera.width || v.image.rows != v.camera.height ||
        (v.image.type() != CV_8UC1 && v.image.type() != CV_8UC3)) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "photo refinement: image of view " + std::to_string(i) + " is " +
                           std::to_string(v.image.cols) + "x" + std::to_string(v.image.rows) +
                           " (type " + std::to_string(v.image.type()) + "), the camera is " +
                           std::to_string(v.camera.width) + "x" + std::to_string(v.camera.height) +
                           "; give an 8-bit grey or BGR image at the camera's size");
    }
    if (!v.mask.empty() && (v.mask.type() != CV_8UC1 || v.mask.cols < v.image.cols ||
                            static_cast<int64_t>(v.mask.cols) * v.image.rows !=
                                static_cast<int64_t>(v.mask.rows) * v.image.cols)) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "photo refinement: mask of view " + std::to_string(i) +
                           " is not an 8-bit single-channel image " + "of the photo's shape (" +
                           std::to_string(v.mask.cols) + "x" + std::to_string(v.mask.rows) +
                           " for a " + std::to_string(v.image.cols) + "x" +
                           std::to_string(v.image.rows) + " photo); give the view's rock mask");
    }
  }
  return OkStatus();
}

Surface MakeSurface(const Mesh& hull) {
  Surface s;
  const size_t nv = hull.vertices.size();
  s.V.resize(nv);
  for (size_t i = 0; i < nv; ++i)
    s.V[i] = Vec3(hull.vertices[i][0], hull.vertices[i][1], hull.vertices[i][2]);
  s.F = hull.faces;
  s.nb = Neighbours(nv, s.F);
  s.N = VertexNormals(s.V, s.F);
  for (int it = 0; it < 3; ++it) {
    std::vector<Vec3> next(nv);
    for (size_t i = 0; i < nv; ++i) {
      Vec3 sum = s.N[i];
      for (int j : s.nb[i]) sum += s.N[j];
      next[i] = sum.normalized();
    }
    s.N.swap(next);
  }
  return s;
}

PreparedView PrepareView(const PhotoView& v, const PhotoRefineOptions& opts) {
  PreparedView p;
  cv::Mat g;
  if (v.image.channels() == 3) {
    cv::cvtColor(v.image, g, cv::COLOR_BGR2GRAY);
  } else {
    g = v.image;
  }
  p.cam = v.camera;
  if (opts.image_scale < 1) {
    const int w = static_cast<int>(std::lround(v.camera.width * opts.image_scale));
    const int h = static_cast<int>(std::lround(v.camera.height * opts.image_scale));
    cv::resize(g, g, cv::Size(w, h), 0, 0, cv::INTER_AREA);
    p.cam = v.camera.Resized(w, h);
  }
  if (opts.masked_patches && !v.mask.empty()) {
    if (v.mask.size() == g.size()) {
      p.mask = v.mask > 127;
    } else {
      cv::Mat m;
      cv::resize(v.mask, m, g.size(), 0, 0, cv::INTER_AREA);
      p.mask = m > 127;
    }
  }
  g.convertTo(p.grey, CV_32F);
  if (opts.blur_sigma_px > 0) cv::GaussianBlur(p.grey, p.grey, cv::Size(0, 0), opts.blur_sigma_px);
  p.R = v.cam_from_object.linear();
  p.t = v.cam_from_object.translation();
  p.centre = -p.R.transpose() * p.t;
  p.depth_cam = p.cam.Resized(std::max(8, p.cam.width / opts.depth_map_downscale),
                              std::max(8, p.cam.height / opts.depth_map_downscale));
  return p;
}

void RasterizeDepth(const std::vector<Vec3>& V, const Faces& F, PreparedView* pv) {
  const CameraModel& c = pv->depth_cam;
  pv->depth =
      cv::Mat(c.height, c.width, CV_32F, cv::Scalar(std::numeric_limits<float>::infinity()));
  std::vector<Eigen::Vector3d> proj(V.size());  // u, v, z; z <= 0 when behind
  for (size_t i = 0; i < V.size(); ++i) {
    const Vec3 pc = pv->R * V[i] + pv->t;
    double u = 0, v = 0;
    if (ProjectCam(c, pc, &u, &v)) {
      proj[i] = Vec3(u, v, pc.z());
    } else {
      proj[i] = Vec3(0, 0, -1);
    }
  }
  for (const auto& f : F) {
    const Vec3& a = proj[f[0]];
    const Vec3& b = proj[f[1]];
    const Vec3& d = proj[f[2]];
    if (a.z() <= 0 || b.z() <= 0 || d.z() <= 0) continue;
    const int x0 = std::max(0, static_cast<int>(std::ceil(std::min({a.x(), b.x(), d.x()}))));
    const int x1 =
        std::min(c.width - 1, static_cast<int>(std::floor(std::max({a.x(), b.x(), d.x()}))));
    const int y0 = std::max(0, static_cast<int>(std::ceil(std::min({a.y(), b.y(), d.y()}))));
    const int y1 =
        std::min(c.height - 1, static_cast<int>(std::floor(std::max({a.y(), b.y(), d.y()}))));
    if (x0 > x1 || y0 > y1) continue;
    const double area = (b.x() - a.x()) * (d.y() - a.y()) - (d.x() - a.x()) * (b.y() - a.y());
    if (std::abs(area) < 1e-12) continue;
    for (int y = y0; y <= y1; ++y) {
      float* row = pv->depth.ptr<float>(y);
      for (int x = x0; x <= x1; ++x) {
        const double w0 = ((b.x() - x) * (d.y() - y) - (d.x() - x) * (b.y() - y)) / area;
        const double w1 = ((d.x() - x) * (a.y() - y) - (a.x() - x) * (d.y() - y)) / area;
        const double w2 = 1 - w0 - w1;
        if (w0 < -1e-9 || w1 < -1e-9 || w2 < -1e-9) continue;
        const float z = static_cast<float>(w0 * a.z() + w1 * b.z() + w2 * d.z());
        if (z < row[x]) row[x] = z;
      }
    }
  }
  // Small triangles can fall between pixel centres: fill single-pixel gaps
  // with the neighbourhood minimum where the pixel is empty.
  cv::Mat eroded;
  cv::erode(pv->depth, eroded, cv::Mat::ones(3, 3, CV_8U));
  for (int y = 0; y < pv->depth.rows; ++y) {
    float* r = pv->depth.ptr<float>(y);
    const float* e = eroded.ptr<float>(y);
    for (int x = 0; x < pv->depth.cols; ++x) {
      if (std::isinf(r[x])) r[x] = e[x];
    }
  }
}

std::vector<PreparedView> PrepareViews(const std::vector<PhotoView>& views, const Surface& s,
                                       const PhotoRefineOptions& opts) {
  std::vector<PreparedView> pv(views.size());
  ParallelFor(views.size(), opts.threads, [&](size_t i) {
    pv[i] = PrepareView(views[i], opts);
    RasterizeDepth(s.V, s.F, &pv[i]);
  });
  return pv;
}

bool Unoccluded(const PreparedView& q, const Vec3& p, double depth_tolerance_mm) {
  const Vec3 pc = q.R * p + q.t;
  double u = 0, v = 0;
  if (!ProjectCam(q.depth_cam, pc, &u, &v)) return false;
  const int x = static_cast<int>(std::lround(u)), y = static_cast<int>(std::lround(v));
  if (x < 0 || y < 0 || x >= q.depth.cols || y >= q.depth.rows) return false;
  return !(pc.z() > q.depth.at<float>(y, x) + depth_tolerance_mm);
}

std::vector<char> ChooseScoredVertices(const Rings& nb, int sample_rings) {
  const size_t nv = nb.size();
  std::vector<char> scored(nv, 1);
  if (sample_rings <= 0) return scored;
  std::vector<int> blocked(nv, 0);
  std::fill(scored.begin(), scored.end(), 0);
  for (size_t i = 0; i < nv; ++i) {
    if (blocked[i]) continue;
    scored[i] = 1;
    std::vector<int> front{static_cast<int>(i)};
    blocked[i] = 1;
    for (int r = 0; r < sample_rings; ++r) {
      std::vector<int> nxt;
      for (int a : front) {
        for (int b : nb[a]) {
          if (!blocked[b]) {
            blocked[b] = 1;
            nxt.push_back(b);
          }
        }
      }
      front.swap(nxt);
    }
  }
  return scored;
}

std::vector<ViewPick> ChooseViews(const Vec3& p, const Vec3& n,
                                  const std::vector<PreparedView>& views,
                                  const PhotoRefineOptions& opts) {
  std::vector<ViewPick> cand;
  for (size_t k = 0; k < views.size(); ++k) {
    const PreparedView& q = views[k];
    const Vec3 to_cam = q.centre - p;
    const double cosang = n.dot(to_cam) / to_cam.norm();
    if (cosang < opts.min_cos) continue;
    if (!Unoccluded(q, p, opts.depth_tolerance_mm)) continue;
    cand.emplace_back(cosang, static_cast<int>(k));
  }
  if (cand.size() < 2) return cand;
  std::sort(cand.begin(), cand.end(), std::greater<>());
  // Greedy: most frontal first, skipping views that look from (nearly) the
  // same direction as one already chosen: no baseline, no depth signal.
  const double cos_baseline = std::cos(opts.min_baseline_deg * M_PI / 180);
  std::vector<ViewPick> chosen;
  std::vector<Vec3> dirs;
  for (const auto& c : cand) {
    const Vec3 dir = (views[c.second].centre - p).normalized();
    bool close = false;
    for (const Vec3& d : dirs) close = close || d.dot(dir) > cos_baseline;
    if (close) continue;
    chosen.push_back(c);
    dirs.push_back(dir);
    if (static_cast<int>(chosen.size()) == opts.views_per_vertex) break;
  }
  return chosen;
}

Patch MakePatch(const Surface& s, size_t i, const PreparedView& ref,
                const PhotoRefineOptions& opts) {
  Patch patch;
  patch.p = s.V[i];
  patch.n = s.N[i];
  patch.radius = opts.patch_radius;
  const Vec3& p = patch.p;
  const Vec3& n = patch.n;
  const int R = patch.radius;
  // Tangent basis and the patch spacing: about patch_spacing_px reference pixels.
  patch.t1 = n.unitOrthogonal();
  patch.t2 = n.cross(patch.t1);
  const double zref = (ref.R * p + ref.t).z();
  patch.spacing = opts.patch_spacing_px * zref / ref.cam.fx;
  // The patch follows the hull's local shape, not its tangent plane: a flat
  // patch on a convex tip fits best inside it, and the tips moved inward
  // (sim seed 11: the long axis 2.5 % short, its tips 0.5 and 1.0 mm inside
  // the rock's where the hull's were 0.1 and 0.3 mm; curved, 0.2 and 0.8).
  if (opts.curved_patches)
    patch.quad = LocalQuadric(s.V, s.nb, i, n, patch.t1, patch.t2, 1.2 * R * patch.spacing);
  return patch;
}

PatchScorer::PatchScorer(const std::vector<PreparedView>& views, const std::vector<ViewPick>& picks,
                         const Patch& patch, const PhotoRefineOptions& opts)
    : views_(views), picks_(picks), patch_(patch) {
  const int side = 2 * patch.radius + 1;
  ns_ = side * side;
  const int nvw = static_cast<int>(picks.size());
  samples_.resize(static_cast<size_t>(nvw) * ns_);
  on_rock_.assign(static_cast<size_t>(nvw) * ns_, 1);
  min_on_rock_ = static_cast<int>(std::ceil(opts.min_on_rock * ns_));
}

double PatchScorer::Score(double depth_mm) {
  constexpr double kMinVar = 1.0;  // grey levels^2: flat patches carry no depth information
  const int R = patch_.radius, ns = ns_;
  const double s = patch_.spacing;
  const Vec3& n = patch_.n;
  const Eigen::Vector3d& quad = patch_.quad;
  const int nvw = static_cast<int>(picks_.size());
  const Vec3 c = patch_.p - depth_mm * n;
  ok_.assign(nvw, 1);
  for (int w = 0; w < nvw; ++w) {
    const PreparedView& q = views_[picks_[w].second];
    const Vec3 base = q.R * c + q.t;
    const Vec3 A = q.R * (s * patch_.t1), B = q.R * (s * patch_.t2), Nq = q.R * n;
    float* out = samples_.data() + static_cast<size_t>(w) * ns;
    uint8_t* rock = on_rock_.data() + static_cast<size_t>(w) * ns;
    for (int b = -R; b <= R && ok_[w]; ++b) {
      for (int a = -R; a <= R; ++a) {
        double u = 0, v = 0;
        const double x = a * s, y = b * s;
        const double h = -0.5 * (quad[0] * x * x + 2 * quad[1] * x * y + quad[2] * y * y);
        if (!ProjectCam(q.cam, base + a * A + b * B + h * Nq, &u, &v) ||
            !Bilinear(q.grey, u, v, out++)) {
          ok_[w] = 0;
          break;
        }
        if (!q.mask.empty()) {
          const int mx = std::clamp(static_cast<int>(std::lround(u)), 0, q.mask.cols - 1);
          const int my = std::clamp(static_cast<int>(std::lround(v)), 0, q.mask.rows - 1);
          *rock = q.mask.at<uint8_t>(my, mx) != 0;
        }
        ++rock;
      }
    }
    if (w == 0 && !ok_[0]) return kNoScore;
  }
  double sum = 0;
  int cnt = 0;
  for (int w = 1; w < nvw; ++w) {
    double r = 0;
    if (!ok_[w] ||
        !NccOnRock(samples_.data(), samples_.data() + static_cast<size_t>(w) * ns, on_rock_.data(),
                   on_rock_.data() + static_cast<size_t>(w) * ns, ns, min_on_rock_, kMinVar, &r)) {
      continue;
    }
    sum += r;
    ++cnt;
  }
  return cnt > 0 ? sum / cnt : kNoScore;
}

DepthGrid MakeDepthGrid(const PhotoRefineOptions& opts) {
  DepthGrid g;
  const int nd = static_cast<int>(std::floor(opts.max_depth_mm / opts.step_mm)) + 1;
  g.k_out = static_cast<int>(std::lround(opts.outside_mm / opts.step_mm));
  g.count = nd + g.k_out;
  g.step_mm = opts.step_mm;
  return g;
}

std::vector<double> SearchScores(const std::function<double(double depth_mm)>& score,
                                 const DepthGrid& grid, int stride) {
  const int nk = grid.count, kOut = grid.k_out;
  std::vector<double> scores(nk, kNoScore);
  std::vector<char> done(nk, 0);
  auto score_at = [&](int k) {
    if (k < 0 || k >= nk || done[k]) return;
    done[k] = 1;
    scores[k] = score((k - kOut) * grid.step_mm);
  };
  // The NCC along the normal changes over several steps (a step moves the
  // patch ~0.2 px in the other views), so every stride-th hypothesis (the
  // hull's among them) finds the peak's neighbourhood and the steps around
  // the best one then find the peak and its neighbours.
  stride = std::max(1, stride);
  for (int k = kOut % stride; k < nk; k += stride) score_at(k);
  for (int best = -1; stride > 1;) {
    int bk = 0;
    for (int k = 1; k < nk; ++k)
      if (scores[k] > scores[bk]) bk = k;
    if (bk == best) break;
    best = bk;
    for (int k = bk - stride + 1; k < bk + stride; ++k) score_at(k);
  }
  return scores;
}

std::optional<double> PickDepth(const std::vector<double>& score, const DepthGrid& grid,
                                const PhotoRefineOptions& opts) {
  const int nk = grid.count, kOut = grid.k_out;
  int bi = 0;
  for (int k = 1; k < nk; ++k) {
    if (score[k] > score[bi]) bi = k;
  }
  if (score[bi] < opts.min_ncc) return std::nullopt;  // no clear photo-consistent depth
  double d = (bi - kOut) * grid.step_mm;
  if (bi > 0 && bi + 1 < nk && score[bi - 1] > kNoScore && score[bi + 1] > kNoScore) {
    // Parabola through the peak and its neighbours: sub-step depth.
    const double l = score[bi - 1], m = score[bi], r = score[bi + 1];
    const double den = l - 2 * m + r;
    if (den < 0) d += std::clamp(0.5 * (l - r) / den, -0.5, 0.5) * grid.step_mm;
  }
  const double hull_score = score[kOut];
  if (d > opts.near_hull_mm && score[bi] - hull_score < opts.min_gain) {
    // A deep peak hardly better than the hull: not confident that the
    // surface lies that deep. Data only if the hull itself is consistent.
    if (hull_score >= opts.min_ncc) return 0.0;
    return std::nullopt;
  }
  return opts.outside_mm > 0 ? d : std::max(0.0, d);
}

double HullConvexCurvature(const Surface& s, size_t i, double reach_mm) {
  const Vec3& n = s.N[i];
  const Vec3 t1 = n.unitOrthogonal(), t2 = n.cross(t1);
  const Eigen::Vector3d q = LocalQuadric(s.V, s.nb, i, n, t1, t2, reach_mm);
  // Largest eigenvalue of the curvature matrix [[A, B], [B, C]].
  const double mean = 0.5 * (q[0] + q[2]);
  const double k = mean + std::hypot(0.5 * (q[0] - q[2]), q[1]);
  return std::max(0.0, k);
}

bool LooksLikeHighlight(double depth_mm, const std::function<double()>& curvature,
                        const PhotoRefineOptions& opts) {
  return opts.highlight_depth_ratio > 0 && depth_mm > opts.near_hull_mm &&
         depth_mm * curvature() > opts.highlight_depth_ratio;
}

VertexDepth SearchVertexDepth(const Surface& s, size_t i, const std::vector<PreparedView>& views,
                              const PhotoRefineOptions& opts) {
  VertexDepth out;
  const std::vector<ViewPick> picks = ChooseViews(s.V[i], s.N[i], views, opts);
  if (picks.size() < 2) return out;
  out.had_views = true;
  const Patch patch = MakePatch(s, i, views[picks[0].second], opts);
  PatchScorer scorer(views, picks, patch, opts);
  const DepthGrid grid = MakeDepthGrid(opts);
  const std::vector<double> score =
      SearchScores([&](double d) { return scorer.Score(d); }, grid, opts.depth_search_stride);
  out.depth_mm = PickDepth(score, grid, opts);
  if (out.depth_mm &&
      LooksLikeHighlight(
          *out.depth_mm, [&] { return HullConvexCurvature(s, i, opts.highlight_reach_mm); },
          opts)) {
    out.depth_mm.reset();
    out.highlight = true;
  }
  return out;
}

DepthData SearchDepths(const Surface& s, const std::vector<PreparedView>& views,
                       const std::vector<char>& scored, const PhotoRefineOptions& opts) {
  const size_t nv = s.V.size();
  DepthData data;
  data.depth_mm.assign(nv, 0.0);
  data.weight.assign(nv, 0.0);
  data.had_views.assign(nv, 0);
  data.highlight.assign(nv, 0);
  ParallelFor(nv, opts.threads, [&](size_t i) {
    if (!scored[i]) return;
    const VertexDepth r = SearchVertexDepth(s, i, views, opts);
    data.had_views[i] = r.had_views ? 1 : 0;
    data.highlight[i] = r.highlight ? 1 : 0;
    if (r.depth_mm) {
      data.depth_mm[i] = *r.depth_mm;
      data.weight[i] = 1;
    }
  });
  return data;
}

std::vector<double> RegulariseField(const DepthData& data, const Rings& nb,
                                    const PhotoRefineOptions& opts) {
  const std::vector<double>& d = data.depth_mm;
  std::vector<double> weight = data.weight;
  std::vector<double> field =
      SmoothField(d, d, weight, nb, opts.smooth_iterations, opts.smooth_lambda);
  for (size_t i = 0; i < d.size(); ++i) {
    if (weight[i] > 0 && std::abs(d[i] - field[i]) > opts.outlier_mm) weight[i] = 0;
  }
  // Second pass from the first's field, without the outliers.
  field = SmoothField(field, d, weight, nb, opts.smooth_iterations, opts.smooth_lambda);
  for (double& x : field) x = std::clamp(x, 0.0, opts.max_depth_mm);
  return field;
}

MoveDirections ChooseMoveDirections(const Surface& s, const std::vector<double>& field,
                                    double move_reach) {
  // Each vertex's normal smoothed further until the smoothing reaches about
  // its move's depth. k passes of 1-ring averaging spread a normal over about
  // e sqrt(k) (e: the mean edge), so a move d takes (reach d / e)^2 passes in
  // all, the 3 of N included. A shallow move keeps N; a deep one behind a
  // convex edge moves nearly parallel to its neighbours instead of
  // converging with them.
  const size_t nv = s.V.size();
  const auto& V = s.V;
  const auto& F = s.F;
  MoveDirections m;
  m.dir = s.N;
  if (!(move_reach > 0)) return m;
  double esum = 0;
  for (const auto& f : F) esum += (V[f[1]] - V[f[0]]).norm();
  const double e = F.empty() ? 1.0 : esum / F.size();
  constexpr int kMaxPasses = 400;
  std::vector<int> passes(nv, 0);
  int most = 0;
  for (size_t i = 0; i < nv; ++i) {
    const double r = move_reach * field[i] / e;
    passes[i] = std::clamp(static_cast<int>(std::lround(r * r)) - 3, 0, kMaxPasses);
    most = std::max(most, passes[i]);
  }
  m.max_passes = most;
  std::vector<Vec3> S = s.N, next(nv);
  for (int k = 1; k <= most; ++k) {
    for (size_t i = 0; i < nv; ++i) {
      Vec3 sum = S[i];
      for (int j : s.nb[i]) sum += S[j];
      next[i] = sum.normalized();
    }
    S.swap(next);
    for (size_t i = 0; i < nv; ++i) {
      if (passes[i] == k) m.dir[i] = S[i];
    }
  }
  return m;
}

FoldTest::FoldTest(const Surface& s, double max_face_turn_deg)
    : F_(s.F), fn0_(s.F.size()), cos_turn_(std::cos(max_face_turn_deg * M_PI / 180)) {
  const auto& V = s.V;
  for (size_t f = 0; f < F_.size(); ++f) {
    fn0_[f] = (V[F_[f][1]] - V[F_[f][0]]).cross(V[F_[f][2]] - V[F_[f][0]]).normalized();
  }
}

int FoldTest::Find(const std::vector<Vec3>& X, std::vector<char>* bad) const {
  bad->assign(X.size(), 0);
  int nbad = 0;
  for (size_t f = 0; f < F_.size(); ++f) {
    const Vec3 c = (X[F_[f][1]] - X[F_[f][0]]).cross(X[F_[f][2]] - X[F_[f][0]]);
    const double l = c.norm();
    if (l > 1e-12 && c.dot(fn0_[f]) / l >= cos_turn_) continue;
    ++nbad;
    for (int k = 0; k < 3; ++k) (*bad)[F_[f][k]] = 1;
  }
  return nbad;
}

MovedVertices MoveVertices(const Surface& s, const std::vector<double>& field,
                           const std::vector<Vec3>& dirs, const FoldTest& folds,
                           int untangle_passes) {
  // Undo folds where they are: a folding vertex moves to the centroid of its
  // neighbours' moved positions (never outward of the hull), which keeps the
  // region's depth. What that cannot undo is pulled back towards the hull,
  // where no face is folded: halving, then all the way.
  const size_t nv = s.V.size();
  const auto& V = s.V;
  const auto& N = s.N;
  const auto& nb = s.nb;
  MovedVertices m;
  std::vector<Vec3>& W = m.W;
  W.resize(nv);
  for (size_t i = 0; i < nv; ++i) W[i] = V[i] - field[i] * dirs[i];
  std::vector<char> bad;
  for (int pass = 0;; ++pass) {
    const int nbad = folds.Find(W, &bad);
    if (pass == 0) m.faces_folded = nbad;
    if (nbad == 0) break;
    if (pass < untangle_passes) {
      m.untangle_passes = pass + 1;
      std::vector<Vec3> next = W;
      for (size_t i = 0; i < nv; ++i) {
        if (!bad[i] || nb[i].empty()) continue;
        Vec3 c = Vec3::Zero();
        for (int j : nb[i]) c += W[j];
        next[i] = c / nb[i].size();
        const double out = (next[i] - V[i]).dot(N[i]);
        if (out > 0) next[i] -= out * N[i];
      }
      W.swap(next);
      continue;
    }
    const int halving = pass - untangle_passes;
    m.fold_passes = halving + 1;
    for (size_t i = 0; i < nv; ++i) {
      if (bad[i]) W[i] = halving < 12 ? V[i] + 0.5 * (W[i] - V[i]) : V[i];
    }
    if (halving > 12) break;  // cannot happen: the hull itself has no folds
  }
  return m;
}

std::vector<Vec3> SmoothMovedRegion(const Surface& s, const std::vector<double>& field,
                                    std::vector<Vec3> W, const FoldTest& folds, int iterations) {
  // Taubin smoothing (lambda|mu, no shrinkage) of the moved region's
  // positions: the depth field is rough where it is deep, which inflates the
  // area. Unmoved hull vertices stay put; no vertex leaves the hull outward.
  if (iterations <= 0) return W;
  const size_t nv = s.V.size();
  const auto& V = s.V;
  const auto& N = s.N;
  const auto& nb = s.nb;
  std::vector<char> movable(nv, 0);
  for (size_t i = 0; i < nv; ++i) movable[i] = field[i] > 0.05 ? 1 : 0;
  std::vector<Vec3> X = W, next(nv);
  for (int it = 0; it < 2 * iterations; ++it) {
    const double f = (it % 2 == 0) ? 0.5 : -0.53;
    for (size_t i = 0; i < nv; ++i) {
      next[i] = X[i];
      if (!movable[i] || nb[i].empty()) continue;
      Vec3 c = Vec3::Zero();
      for (int j : nb[i]) c += X[j];
      next[i] = X[i] + f * (c / nb[i].size() - X[i]);
    }
    X.swap(next);
  }
  for (size_t i = 0; i < nv; ++i) {
    const double out = (X[i] - V[i]).dot(N[i]);
    if (out > 0) X[i] -= out * N[i];
  }
  // Keep the smoothing only where it inverts no face: vertices of folded
  // faces go back to their unsmoothed place, until the mix (which can fold
  // faces of its own at the seams) has none; all back is W, which has none.
  std::vector<char> bad;
  while (folds.Find(X, &bad) > 0) {
    for (size_t i = 0; i < nv; ++i) {
      if (bad[i]) X[i] = W[i];
    }
  }
  return X;
}

void Summarise(const Surface& s, const DepthData& data, const std::vector<Vec3>& W,
               PhotoRefineResult* res) {
  const size_t nv = s.V.size();
  res->vertices = static_cast<int64_t>(nv);
  for (size_t i = 0; i < nv; ++i) {
    res->vertices_scored += data.had_views[i] ? 1 : 0;
    res->vertices_confident += data.weight[i] > 0 ? 1 : 0;
    res->vertices_highlight += data.highlight[i];
  }
  res->mesh.faces = s.F;
  res->mesh.vertices.resize(nv);
  double sum = 0;
  for (size_t i = 0; i < nv; ++i) {
    res->mesh.vertices[i] = {W[i].x(), W[i].y(), W[i].z()};
    const double d = (W[i] - s.V[i]).norm();
    if (d > 0.05) {
      ++res->vertices_moved;
      sum += d;
      res->max_displacement_mm = std::max(res->max_displacement_mm, d);
    }
  }
  res->mean_displacement_mm = res->vertices_moved > 0 ? sum / res->vertices_moved : 0.0;
}

}  // namespace photo_refine

Result<PhotoRefineResult> RefineByPhotoConsistency(const Mesh& hull,
                                                   const std::vector<PhotoView>& views,
                                                   const PhotoRefineOptions& opts) {
  using namespace photo_refine;
  const auto t0 = std::chrono::steady_clock::now();
  if (Status st = CheckInputs(views, opts); !st) return st.error();
  const Surface s = MakeSurface(hull);
  const std::vector<PreparedView> pv = PrepareViews(views, s, opts);
  const std::vector<char> scored = ChooseScoredVertices(s.nb, opts.sample_rings);
  const DepthData data = SearchDepths(s, pv, scored, opts);
  const std::vector<double> field = RegulariseField(data, s.nb, opts);
  const MoveDirections dirs = ChooseMoveDirections(s, field, opts.move_reach);
  const FoldTest folds(s, opts.max_face_turn_deg);
  MovedVertices moved = MoveVertices(s, field, dirs.dir, folds, opts.untangle_passes);
  const std::vector<Vec3> W =
      SmoothMovedRegion(s, field, std::move(moved.W), folds, opts.surface_smooth_iterations);
  PhotoRefineResult res;
  res.max_direction_passes = dirs.max_passes;
  res.faces_folded = moved.faces_folded;
  res.untangle_passes = moved.untangle_passes;
  res.fold_passes = moved.fold_passes;
  Summarise(s, data, W, &res);
  res.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

}  // namespace aggscan
