#include "pipeline/surface/visual_hull.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <limits>
#include <opencv2/imgproc.hpp>
#include <unordered_map>

#include "pipeline/core/parallel_for.h"
#include "pipeline/core/stats.h"

namespace aggscan {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();

struct PreparedView {
  cv::Mat sd;  // CV_32F signed distance, px
  CameraModel cam;
  Eigen::Matrix3d R;
  Eigen::Vector3d t;
  double mm_per_px_per_mm = 0;  // 1 / f: px * z / f = mm at depth z
};

class Field {
 public:
  Field(std::vector<PreparedView> views, std::vector<HalfSpace> floors)
      : views_(std::move(views)), floors_(std::move(floors)) {}

  // The field at p, exact when it is >= stop_below; otherwise some value
  // below stop_below that is >= the exact field (an early exit).
  double operator()(const Eigen::Vector3d& p, double stop_below) const {
    double f = kInf;
    for (const HalfSpace& h : floors_) {
      f = std::min(f, h.normal.dot(p) + h.offset);
      if (f < stop_below) return f;
    }
    for (const PreparedView& pv : views_) {
      const Eigen::Vector3d pc = pv.R * p + pv.t;
      double d;
      if (pc.z() < 1.0) {
        d = -1e6;  // behind the camera: outside its cone
      } else {
        double u, v;
        pv.cam.Project({pc.x(), pc.y(), pc.z()}, &u, &v);
        d = SampleSignedDistance(pv.sd, u, v) * pc.z() * pv.mm_per_px_per_mm;
      }
      f = std::min(f, d);
      if (f < stop_below) return f;
    }
    return f;
  }

 private:
  std::vector<PreparedView> views_;
  std::vector<HalfSpace> floors_;
};

struct Grid {
  Eigen::Vector3d origin;
  double h = 1;
  int nx = 0, ny = 0, nz = 0;
  std::vector<float> f;

  int64_t Index(int i, int j, int k) const {
    return i + static_cast<int64_t>(nx) * (j + static_cast<int64_t>(ny) * k);
  }
  Eigen::Vector3d Node(int i, int j, int k) const { return origin + h * Eigen::Vector3d(i, j, k); }
  // Trilinear interpolation at p (clamped into the grid).
  double Interp(const Eigen::Vector3d& p) const {
    const Eigen::Vector3d g = (p - origin) / h;
    const int i = std::clamp(static_cast<int>(std::floor(g.x())), 0, nx - 2);
    const int j = std::clamp(static_cast<int>(std::floor(g.y())), 0, ny - 2);
    const int k = std::clamp(static_cast<int>(std::floor(g.z())), 0, nz - 2);
    const double ax = std::clamp(g.x() - i, 0.0, 1.0), ay = std::clamp(g.y() - j, 0.0, 1.0),
                 az = std::clamp(g.z() - k, 0.0, 1.0);
    auto at = [&](int di, int dj, int dk) {
      return static_cast<double>(f[Index(i + di, j + dj, k + dk)]);
    };
    const double c00 = at(0, 0, 0) * (1 - ax) + at(1, 0, 0) * ax;
    const double c10 = at(0, 1, 0) * (1 - ax) + at(1, 1, 0) * ax;
    const double c01 = at(0, 0, 1) * (1 - ax) + at(1, 0, 1) * ax;
    const double c11 = at(0, 1, 1) * (1 - ax) + at(1, 1, 1) * ax;
    const double c0 = c00 * (1 - ay) + c10 * ay, c1 = c01 * (1 - ay) + c11 * ay;
    return c0 * (1 - az) + c1 * az;
  }
};

Grid MakeGrid(const Eigen::AlignedBox3d& box, double h) {
  Grid g;
  g.h = h;
  const Eigen::Vector3d size = box.sizes();
  g.nx = std::max(2, static_cast<int>(std::ceil(size.x() / h)) + 1);
  g.ny = std::max(2, static_cast<int>(std::ceil(size.y() / h)) + 1);
  g.nz = std::max(2, static_cast<int>(std::ceil(size.z() / h)) + 1);
  // Centre the grid on the box.
  const Eigen::Vector3d span = h * Eigen::Vector3d(g.nx - 1, g.ny - 1, g.nz - 1);
  g.origin = box.center() - span / 2;
  g.f.assign(static_cast<size_t>(g.nx) * g.ny * g.nz, 0.0f);
  return g;
}

// Marching tetrahedra over the grid at iso 0 (inside: f >= 0). Six tetrahedra
// per cube, all around the cube's main diagonal (corner 0 to corner 7), so
// neighbouring cubes share tetrahedron faces and the surface is closed.
Mesh Contour(const Grid& g) {
  Mesh mesh;
  // Corner c = dx + 2 dy + 4 dz.
  static constexpr int kTets[6][4] = {{0, 1, 3, 7}, {0, 1, 5, 7}, {0, 2, 3, 7},
                                      {0, 2, 6, 7}, {0, 4, 5, 7}, {0, 4, 6, 7}};
  std::unordered_map<uint64_t, int> edge_vertex;
  edge_vertex.reserve(1 << 16);
  auto value = [&](int64_t idx) {
    const float v = g.f[idx];
    return v == 0.0f ? 1e-7f : v;  // never exactly on the iso level
  };
  auto node_pos = [&](int64_t idx) {
    const int i = static_cast<int>(idx % g.nx);
    const int j = static_cast<int>((idx / g.nx) % g.ny);
    const int k = static_cast<int>(idx / (static_cast<int64_t>(g.nx) * g.ny));
    return g.Node(i, j, k);
  };
  auto vertex_on = [&](int64_t a, int64_t b) {
    if (a > b) std::swap(a, b);
    const uint64_t key =
        static_cast<uint64_t>(a) * 0x9E3779B97F4A7C15ull ^ static_cast<uint64_t>(b);
    // Key collisions are impossible in practice but guard by checking the pair.
    auto [it, inserted] = edge_vertex.try_emplace(key, static_cast<int>(mesh.vertices.size()));
    if (inserted) {
      const double fa = value(a), fb = value(b);
      const double t = fa / (fa - fb);
      const Eigen::Vector3d p = node_pos(a) + t * (node_pos(b) - node_pos(a));
      mesh.vertices.push_back({p.x(), p.y(), p.z()});
    }
    return it->second;
  };
  auto emit = [&](int va, int vb, int vc, const Eigen::Vector3d& outward) {
    const auto& A = mesh.vertices[va];
    const auto& B = mesh.vertices[vb];
    const auto& C = mesh.vertices[vc];
    const Eigen::Vector3d a(A[0], A[1], A[2]), b(B[0], B[1], B[2]), c(C[0], C[1], C[2]);
    if ((b - a).cross(c - a).dot(outward) >= 0) {
      mesh.faces.push_back({va, vb, vc});
    } else {
      mesh.faces.push_back({va, vc, vb});
    }
  };
  for (int k = 0; k + 1 < g.nz; ++k) {
    for (int j = 0; j + 1 < g.ny; ++j) {
      for (int i = 0; i + 1 < g.nx; ++i) {
        int64_t corner[8];
        int inside = 0;
        for (int c = 0; c < 8; ++c) {
          corner[c] = g.Index(i + (c & 1), j + ((c >> 1) & 1), k + ((c >> 2) & 1));
          inside += value(corner[c]) >= 0;
        }
        if (inside == 0 || inside == 8) continue;
        for (const auto& tet : kTets) {
          int64_t in[4], out[4];
          int ni = 0, no = 0;
          for (int q = 0; q < 4; ++q) {
            const int64_t n = corner[tet[q]];
            if (value(n) >= 0)
              in[ni++] = n;
            else
              out[no++] = n;
          }
          if (ni == 0 || no == 0) continue;
          Eigen::Vector3d ci = Eigen::Vector3d::Zero(), co = Eigen::Vector3d::Zero();
          for (int q = 0; q < ni; ++q) ci += node_pos(in[q]);
          for (int q = 0; q < no; ++q) co += node_pos(out[q]);
          const Eigen::Vector3d outward = co / no - ci / ni;
          if (ni == 1) {
            emit(vertex_on(in[0], out[0]), vertex_on(in[0], out[1]), vertex_on(in[0], out[2]),
                 outward);
          } else if (no == 1) {
            emit(vertex_on(in[0], out[0]), vertex_on(in[1], out[0]), vertex_on(in[2], out[0]),
                 outward);
          } else {
            // Quad around the tetrahedron: (i0,o0) (i0,o1) (i1,o1) (i1,o0).
            const int q0 = vertex_on(in[0], out[0]), q1 = vertex_on(in[0], out[1]);
            const int q2 = vertex_on(in[1], out[1]), q3 = vertex_on(in[1], out[0]);
            emit(q0, q1, q2, outward);
            emit(q0, q2, q3, outward);
          }
        }
      }
    }
  }
  return mesh;
}

}  // namespace

double SampleSignedDistance(const cv::Mat& sd, double u, double v) {
  const int w = sd.cols, h = sd.rows;
  double extra = 0;
  if (u < 0) {
    extra += -u;
    u = 0;
  }
  if (v < 0) {
    extra += -v;
    v = 0;
  }
  if (u > w - 1) {
    extra += u - (w - 1);
    u = w - 1;
  }
  if (v > h - 1) {
    extra += v - (h - 1);
    v = h - 1;
  }
  const int x0 = std::min(static_cast<int>(u), w - 2), y0 = std::min(static_cast<int>(v), h - 2);
  const double ax = u - x0, ay = v - y0;
  const float* r0 = sd.ptr<float>(y0);
  const float* r1 = sd.ptr<float>(y0 + 1);
  const double top = r0[x0] * (1 - ax) + r0[x0 + 1] * ax;
  const double bot = r1[x0] * (1 - ax) + r1[x0 + 1] * ax;
  const double val = top * (1 - ay) + bot * ay;
  return extra > 0 ? std::min(val, 0.0) - extra : val;
}

cv::Mat SilhouetteSignedDistance(const cv::Mat& mask) {
  cv::Mat bin = mask > 127;
  cv::Mat din, dout;
  // Distance from each inside pixel to the nearest outside pixel centre, and
  // the reverse; the boundary lies half a pixel from both.
  cv::distanceTransform(bin, din, cv::DIST_L2, cv::DIST_MASK_PRECISE, CV_32F);
  cv::Mat inv = ~bin;
  cv::distanceTransform(inv, dout, cv::DIST_L2, cv::DIST_MASK_PRECISE, CV_32F);
  cv::Mat sd(mask.size(), CV_32F);
  for (int y = 0; y < mask.rows; ++y) {
    const uint8_t* b = bin.ptr<uint8_t>(y);
    const float* di = din.ptr<float>(y);
    const float* dn = dout.ptr<float>(y);
    float* s = sd.ptr<float>(y);
    for (int x = 0; x < mask.cols; ++x) s[x] = b[x] ? di[x] - 0.5f : -(dn[x] - 0.5f);
  }
  return sd;
}

Result<VisualHullResult> CarveVisualHull(const std::vector<SilhouetteView>& views,
                                         const std::vector<HalfSpace>& floors,
                                         const Eigen::AlignedBox3d& search_box,
                                         const VisualHullOptions& opts) {
  const auto t0 = std::chrono::steady_clock::now();
  if (views.empty()) return MakeError(ErrorClass::kInvalidArgument, "visual hull: no views given");
  if (search_box.isEmpty() || search_box.sizes().minCoeff() <= 0) {
    return MakeError(ErrorClass::kInvalidArgument, "visual hull: empty search box");
  }
  std::vector<PreparedView> prepared(views.size());
  {
    std::atomic<int> bad{-1};
    ParallelFor(views.size(), opts.threads, [&](size_t i) {
      const SilhouetteView& v = views[i];
      if (v.mask.type() != CV_8UC1 || v.mask.cols != v.camera.width ||
          v.mask.rows != v.camera.height || v.mask.cols < 2 || v.mask.rows < 2) {
        bad = static_cast<int>(i);
        return;
      }
      PreparedView& p = prepared[i];
      p.sd = SilhouetteSignedDistance(v.mask);
      p.cam = v.camera;
      p.R = v.cam_from_object.linear();
      p.t = v.cam_from_object.translation();
      p.mm_per_px_per_mm = 1.0 / std::sqrt(v.camera.fx * v.camera.fy);
    });
    if (bad >= 0) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "visual hull: mask of view " + std::to_string(bad.load()) +
                           " is not an 8-bit single-channel image of the camera's size");
    }
  }
  for (const HalfSpace& h : floors) {
    if (std::abs(h.normal.norm() - 1.0) > 1e-6) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "visual hull: a floor's normal is not a unit vector");
    }
  }
  const Field field(std::move(prepared), floors);
  VisualHullResult result;
  std::atomic<int64_t> evals{0};

  // Coarse pass.
  const double hc = opts.coarse_mm;
  Grid coarse = MakeGrid(search_box, hc);
  ParallelFor(coarse.nz, opts.threads, [&](int k) {
    int64_t n = 0;
    for (int j = 0; j < coarse.ny; ++j) {
      for (int i = 0; i < coarse.nx; ++i) {
        coarse.f[coarse.Index(i, j, k)] = static_cast<float>(field(coarse.Node(i, j, k), -3 * hc));
        ++n;
      }
    }
    evals += n;
  });
  Eigen::AlignedBox3d occupied;
  bool touches = false;
  for (int k = 0; k < coarse.nz; ++k) {
    for (int j = 0; j < coarse.ny; ++j) {
      for (int i = 0; i < coarse.nx; ++i) {
        if (coarse.f[coarse.Index(i, j, k)] < 0) continue;
        occupied.extend(coarse.Node(i, j, k));
        if (i == 0 || j == 0 || k == 0 || i == coarse.nx - 1 || j == coarse.ny - 1 ||
            k == coarse.nz - 1) {
          touches = true;
        }
      }
    }
  }
  if (occupied.isEmpty()) {
    return MakeError(
        ErrorClass::kInvalidArgument,
        "visual hull: the silhouettes have no common volume: the view poses or the masks are wrong "
        "(check the rig calibration and the masks)");
  }
  if (touches) {
    return MakeError(
        ErrorClass::kInvalidArgument,
        "visual hull: the carved volume reaches the edge of the search region: the rock is not "
        "inside it, or the masks/poses are wrong (check masks for background leaks)");
  }
  // The fine spacing from the coarse contour: faces scale with 1/h^2.
  double h = opts.voxel_mm;
  if (h <= 0) {
    Mesh m0 = Contour(coarse);
    const double faces0 = static_cast<double>(m0.faces.size());
    h = faces0 > 0 ? hc * std::sqrt(faces0 / std::max(1, opts.target_faces)) : hc / 4;
    h = std::clamp(h, opts.min_voxel_mm, hc);
  }
  Eigen::AlignedBox3d fine_box(occupied.min() - Eigen::Vector3d::Constant(1.5 * hc),
                               occupied.max() + Eigen::Vector3d::Constant(1.5 * hc));
  Grid fine = MakeGrid(fine_box, h);
  const double certain = 1.5 * hc;
  ParallelFor(fine.nz, opts.threads, [&](int k) {
    int64_t n = 0;
    for (int j = 0; j < fine.ny; ++j) {
      for (int i = 0; i < fine.nx; ++i) {
        const Eigen::Vector3d p = fine.Node(i, j, k);
        double v = coarse.Interp(p);
        if (std::abs(v) <= certain) {
          v = field(p, -2 * h);
          ++n;
        }
        fine.f[fine.Index(i, j, k)] = static_cast<float>(v);
      }
    }
    evals += n;
  });
  // The fine box's outer layer must be outside (it is 1.5 coarse cells away).
  result.mesh = Contour(fine);
  if (result.mesh.faces.empty()) {
    return MakeError(ErrorClass::kInternal, "visual hull: contouring produced no surface");
  }
  result.voxel_mm = h;
  for (const auto& v : result.mesh.vertices) result.box.extend(Eigen::Vector3d(v[0], v[1], v[2]));
  result.field_evaluations = evals;
  result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return result;
}

std::vector<std::size_t> DisagreeingViews(const std::vector<double>& sole_carving, double agreed) {
  constexpr double kMaxFraction = 0.05;
  return HighOutliers(sole_carving, kMaxFraction * agreed);
}

}  // namespace aggscan
