// Volume, area, convex hull and minimum-volume bounding box of a mesh.
#include "common/mesh_props.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numbers>
#include <optional>
#include <unordered_map>

extern "C" {
#include <libqhull_r/qhull_ra.h>
}

namespace aggscan {
namespace {

Vec3d Sub(const Vec3d& a, const Vec3d& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
Vec3d Add(const Vec3d& a, const Vec3d& b) { return {a[0] + b[0], a[1] + b[1], a[2] + b[2]}; }
Vec3d Mul(const Vec3d& a, double s) { return {a[0] * s, a[1] * s, a[2] * s}; }
double Dot(const Vec3d& a, const Vec3d& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
Vec3d Cross(const Vec3d& a, const Vec3d& b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
double Norm(const Vec3d& a) { return std::sqrt(Dot(a, a)); }
Vec3d Normalized(const Vec3d& a) {
  const double n = Norm(a);
  return n > 0 ? Mul(a, 1.0 / n) : Vec3d{0, 0, 0};
}

// Two unit vectors completing n (unit) to a right-handed orthonormal basis.
void Basis(const Vec3d& n, Vec3d* u, Vec3d* v) {
  const Vec3d helper = std::fabs(n[0]) < 0.6 ? Vec3d{1, 0, 0} : Vec3d{0, 1, 0};
  *u = Normalized(Cross(helper, n));
  *v = Cross(n, *u);
}

// ------------------------------------------------------------ 2D helpers

using Vec2d = std::array<double, 2>;

double Cross2(const Vec2d& o, const Vec2d& a, const Vec2d& b) {
  return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
}

// Andrew's monotone chain; counter-clockwise. Turns smaller than a relative
// tolerance are dropped, so near-duplicate points (a box seen exactly along an
// edge) leave no tiny edges with meaningless directions for the calipers.
std::vector<Vec2d> Hull2D(std::vector<Vec2d> pts) {
  std::sort(pts.begin(), pts.end());
  pts.erase(std::unique(pts.begin(), pts.end()), pts.end());
  if (pts.size() < 3) return pts;
  double lo0 = pts.front()[0], hi0 = pts.back()[0], lo1 = pts[0][1], hi1 = pts[0][1];
  for (const auto& p : pts) {
    lo1 = std::min(lo1, p[1]);
    hi1 = std::max(hi1, p[1]);
  }
  const double span = std::max(hi0 - lo0, hi1 - lo1);
  const double tol = 1e-12 * span * span;
  std::vector<Vec2d> h(2 * pts.size());
  size_t k = 0;
  for (size_t i = 0; i < pts.size(); ++i) {
    while (k >= 2 && Cross2(h[k - 2], h[k - 1], pts[i]) <= tol) --k;
    h[k++] = pts[i];
  }
  for (size_t i = pts.size() - 1, t = k + 1; i > 0; --i) {
    while (k >= t && Cross2(h[k - 2], h[k - 1], pts[i - 1]) <= tol) --k;
    h[k++] = pts[i - 1];
  }
  h.resize(k - 1);
  return h;
}

double MinAreaRectOfHull(const std::vector<Vec2d>& h, Vec2d* dir, double* w, double* ht,
                         Vec2d* lo) {
  const size_t n = h.size();
  if (n == 0) {
    *dir = {1, 0};
    *w = *ht = 0;
    *lo = {0, 0};
    return 0;
  }
  if (n < 3) {
    const Vec2d d = n == 2 ? Vec2d{h[1][0] - h[0][0], h[1][1] - h[0][1]} : Vec2d{1, 0};
    const double len = std::hypot(d[0], d[1]);
    *dir = len > 0 ? Vec2d{d[0] / len, d[1] / len} : Vec2d{1, 0};
    *w = n == 2 ? len : 0;
    *ht = 0;
    *lo = {(*dir)[0] * h[0][0] + (*dir)[1] * h[0][1], -(*dir)[1] * h[0][0] + (*dir)[0] * h[0][1]};
    return 0;
  }
  auto dot = [](const Vec2d& a, const Vec2d& b) { return a[0] * b[0] + a[1] * b[1]; };
  size_t right = 0, top = 0, left = 0;  // max along e, max along normal, min along e
  double best = std::numeric_limits<double>::infinity();
  for (size_t i = 0; i < n; ++i) {
    const Vec2d& a = h[i];
    const Vec2d& b = h[(i + 1) % n];
    const double len = std::hypot(b[0] - a[0], b[1] - a[1]);
    if (len <= 0) continue;
    const Vec2d e{(b[0] - a[0]) / len, (b[1] - a[1]) / len};
    const Vec2d nr{-e[1], e[0]};  // inward for a counter-clockwise polygon
    if (i == 0) right = (i + 1) % n;
    // Each caliper only moves forward around the polygon; its projection is
    // unimodal, so stop when the next vertex does not improve it.
    for (size_t s = 0; s < n && dot(e, h[(right + 1) % n]) > dot(e, h[right]); ++s)
      right = (right + 1) % n;
    if (i == 0) top = right;
    for (size_t s = 0; s < n && dot(nr, h[(top + 1) % n]) > dot(nr, h[top]); ++s)
      top = (top + 1) % n;
    if (i == 0) left = top;
    for (size_t s = 0; s < n && dot(e, h[(left + 1) % n]) < dot(e, h[left]); ++s)
      left = (left + 1) % n;
    const double width = dot(e, h[right]) - dot(e, h[left]);
    const double height = dot(nr, h[top]) - dot(nr, a);
    const double area = width * height;
    if (area < best) {
      best = area;
      *dir = e;
      *w = width;
      *ht = height;
      *lo = {dot(e, h[left]), dot(nr, a)};
    }
  }
  return best;
}

// Box with first axis n (unit): extent [hmin, hmax] along n, and the
// minimum-area rectangle of `silhouette` (points whose projection along n has
// the same convex hull as the whole set's).
OrientedBox BoxFromParts(const Vec3d& n, double hmin, double hmax,
                         const std::vector<Vec3d>& silhouette) {
  Vec3d u, v;
  Basis(n, &u, &v);
  std::vector<Vec2d> proj(silhouette.size());
  for (size_t i = 0; i < silhouette.size(); ++i)
    proj[i] = {Dot(u, silhouette[i]), Dot(v, silhouette[i])};
  Vec2d dir, lo;
  double w = 0, h = 0;
  MinAreaRectOfHull(Hull2D(std::move(proj)), &dir, &w, &h, &lo);
  OrientedBox box;
  const Vec3d ax1 = Add(Mul(u, dir[0]), Mul(v, dir[1]));
  const Vec3d ax2 = Add(Mul(u, -dir[1]), Mul(v, dir[0]));
  box.axes = {ax1, ax2, n};
  box.size = {w, h, hmax - hmin};
  box.center =
      Add(Add(Mul(ax1, lo[0] + w / 2), Mul(ax2, lo[1] + h / 2)), Mul(n, (hmin + hmax) / 2));
  return box;
}

// Best box with first axis n around arbitrary points (degenerate inputs).
OrientedBox BoxForAxis(const Vec3d& n, const std::vector<Vec3d>& q) {
  double hmin = std::numeric_limits<double>::infinity(), hmax = -hmin;
  for (const auto& p : q) {
    hmin = std::min(hmin, Dot(n, p));
    hmax = std::max(hmax, Dot(n, p));
  }
  return BoxFromParts(n, hmin, hmax, q);
}

// Box evaluation on a convex hull. Only silhouette vertices (on edges between
// a face turned towards n and one turned away) can be corners of the
// projected outline, so the 2D hull is built from a few hundred points even
// for hulls of ten thousand vertices.
class HullEval {
 public:
  explicit HullEval(const Mesh& hull) : hull_(hull), stamp_(hull.vertices.size(), 0) {
    normals_.reserve(hull.faces.size());
    for (const auto& f : hull.faces) {
      const Vec3d& a = hull.vertices[f[0]];
      normals_.push_back(Cross(Sub(hull.vertices[f[1]], a), Sub(hull.vertices[f[2]], a)));
    }
    std::unordered_map<uint64_t, int> first;  // undirected edge -> first face
    for (size_t fi = 0; fi < hull.faces.size(); ++fi) {
      const auto& f = hull.faces[fi];
      for (int k = 0; k < 3; ++k) {
        const int a = std::min(f[k], f[(k + 1) % 3]), b = std::max(f[k], f[(k + 1) % 3]);
        const uint64_t key = (static_cast<uint64_t>(a) << 32) | static_cast<uint32_t>(b);
        auto [it, inserted] = first.try_emplace(key, static_cast<int>(fi));
        if (!inserted) edges_.push_back({a, b, it->second, static_cast<int>(fi)});
      }
    }
  }

  const std::vector<Vec3d>& vertices() const { return hull_.vertices; }
  const std::vector<Vec3d>& normals() const { return normals_; }
  std::vector<Vec3d> EdgeDirections() const {
    std::vector<Vec3d> d;
    for (const Edge& e : edges_)
      d.push_back(Normalized(Sub(hull_.vertices[e.b], hull_.vertices[e.a])));
    return d;
  }

  OrientedBox Box(const Vec3d& n) {
    double hmin = std::numeric_limits<double>::infinity(), hmax = -hmin;
    for (const auto& p : hull_.vertices) {
      const double h = Dot(n, p);
      hmin = std::min(hmin, h);
      hmax = std::max(hmax, h);
    }
    front_.resize(normals_.size());
    for (size_t f = 0; f < normals_.size(); ++f) front_[f] = Dot(normals_[f], n) > 0 ? 1 : 0;
    ++round_;
    sil_.clear();
    for (const Edge& e : edges_) {
      if (front_[e.f1] == front_[e.f2]) continue;
      for (int v : {e.a, e.b}) {
        if (stamp_[v] != round_) {
          stamp_[v] = round_;
          sil_.push_back(hull_.vertices[v]);
        }
      }
    }
    if (sil_.size() < 3) sil_ = hull_.vertices;  // n along a face: fall back to every vertex
    return BoxFromParts(n, hmin, hmax, sil_);
  }

 private:
  struct Edge {
    int a, b, f1, f2;
  };
  const Mesh& hull_;
  std::vector<Vec3d> normals_;
  std::vector<Edge> edges_;
  std::vector<char> front_;
  std::vector<int> stamp_;
  int round_ = 0;
  std::vector<Vec3d> sil_;
};

// Eigenvectors of a symmetric 3x3 matrix (cyclic Jacobi); columns of *vecs.
void SymmetricEigen(std::array<std::array<double, 3>, 3> a, std::array<Vec3d, 3>* vecs) {
  std::array<std::array<double, 3>, 3> v{};
  for (int i = 0; i < 3; ++i) v[i][i] = 1;
  for (int sweep = 0; sweep < 50; ++sweep) {
    const double off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
    if (off < 1e-30) break;
    for (int p = 0; p < 2; ++p)
      for (int q = p + 1; q < 3; ++q) {
        if (std::fabs(a[p][q]) < 1e-300) continue;
        const double theta = (a[q][q] - a[p][p]) / (2 * a[p][q]);
        const double t = (theta >= 0 ? 1 : -1) / (std::fabs(theta) + std::sqrt(theta * theta + 1));
        const double c = 1 / std::sqrt(t * t + 1), s = t * c;
        for (int k = 0; k < 3; ++k) {  // A = J^T A J
          const double akp = a[k][p], akq = a[k][q];
          a[k][p] = c * akp - s * akq;
          a[k][q] = s * akp + c * akq;
        }
        for (int k = 0; k < 3; ++k) {
          const double apk = a[p][k], aqk = a[q][k];
          a[p][k] = c * apk - s * aqk;
          a[q][k] = s * apk + c * aqk;
        }
        for (int k = 0; k < 3; ++k) {
          const double vkp = v[k][p], vkq = v[k][q];
          v[k][p] = c * vkp - s * vkq;
          v[k][q] = s * vkp + c * vkq;
        }
      }
  }
  for (int j = 0; j < 3; ++j) (*vecs)[j] = Normalized({v[0][j], v[1][j], v[2][j]});
}

std::array<Vec3d, 3> PrincipalAxes(const std::vector<Vec3d>& q) {
  Vec3d mean{0, 0, 0};
  for (const auto& p : q) mean = Add(mean, p);
  mean = Mul(mean, 1.0 / static_cast<double>(std::max<size_t>(1, q.size())));
  std::array<std::array<double, 3>, 3> cov{};
  for (const auto& p : q) {
    const Vec3d d = Sub(p, mean);
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) cov[i][j] += d[i] * d[j];
  }
  std::array<Vec3d, 3> axes;
  SymmetricEigen(cov, &axes);
  return axes;
}

// Points of `q` extreme along many directions (a Fibonacci sphere): a small
// subset whose hull approximates the hull of q for the coarse search.
std::vector<Vec3d> ExtremeSubset(const std::vector<Vec3d>& q, int directions) {
  std::vector<char> used(q.size(), 0);
  std::vector<Vec3d> out;
  for (const Vec3d& d : FibonacciDirections(directions)) {
    size_t best = 0;
    double bd = -std::numeric_limits<double>::infinity();
    for (size_t i = 0; i < q.size(); ++i) {
      const double s = Dot(d, q[i]);
      if (s > bd) {
        bd = s;
        best = i;
      }
    }
    if (!used[best]) {
      used[best] = 1;
      out.push_back(q[best]);
    }
  }
  return out;
}

// Local search over the box's first axis: pattern search on the sphere of
// directions, the step shrinking from `step_deg` to 0.005 degrees. The
// rotation about the axis needs no search: the calipers solve it exactly.
OrientedBox Refine(const Vec3d& n0, HullEval& eval, double step_deg) {
  Vec3d n = n0;
  OrientedBox best = eval.Box(n);
  constexpr double kDeg = std::numbers::pi / 180.0;
  for (double step = step_deg * kDeg; step >= 0.005 * kDeg; step /= 2) {
    for (int moves = 0; moves < 40; ++moves) {
      Vec3d t1, t2;
      Basis(n, &t1, &t2);
      bool improved = false;
      const double ts = std::tan(step);
      const Vec3d d1 = Normalized(Add(t1, t2)), d2 = Normalized(Sub(t1, t2));
      const std::array<Vec3d, 8> dirs = {t1, Mul(t1, -1), t2, Mul(t2, -1),
                                         d1, Mul(d1, -1), d2, Mul(d2, -1)};
      for (const Vec3d& d : dirs) {
        const Vec3d cand = Normalized(Add(n, Mul(d, ts)));
        OrientedBox b = eval.Box(cand);
        if (b.Volume() < best.Volume() * (1 - 1e-12)) {
          best = b;
          n = cand;
          improved = true;
          break;
        }
      }
      if (!improved) break;
    }
  }
  return best;
}

// A box is the same whichever of its axes a search started from: all three
// axes agree within a degree.
bool SameBox(const OrientedBox& a, const OrientedBox& b) {
  const double same_cos = std::cos(1.0 * std::numbers::pi / 180);
  int same = 0;
  for (const Vec3d& ax : a.axes)
    for (const Vec3d& bx : b.axes)
      if (std::fabs(Dot(ax, bx)) > same_cos) ++same;
  return same >= 3;
}

// Boxes without repeats, smallest volume first once sorted.
struct DistinctBoxes {
  std::vector<OrientedBox> boxes;
  bool Has(const OrientedBox& b) const {
    return std::any_of(boxes.begin(), boxes.end(),
                       [&](const OrientedBox& o) { return SameBox(b, o); });
  }
  void Add(const OrientedBox& b) {
    if (!Has(b)) boxes.push_back(b);
  }
  std::vector<OrientedBox> Sorted() && {
    std::sort(boxes.begin(), boxes.end(),
              [](const OrientedBox& a, const OrientedBox& b) { return a.Volume() < b.Volume(); });
    return std::move(boxes);
  }
};

// The candidate axes scored on `eval`; the `starts` best distinct boxes are
// each refined from all three of their axes. Returns the distinct refined
// boxes, smallest first.
std::vector<OrientedBox> SearchBoxes(HullEval& eval, const std::vector<Vec3d>& cand, int starts,
                                     double step_deg) {
  struct Scored {
    double volume;
    Vec3d axis;
  };
  std::vector<Scored> scored;
  scored.reserve(cand.size());
  for (const Vec3d& n : cand) scored.push_back({eval.Box(n).Volume(), n});
  std::sort(scored.begin(), scored.end(),
            [](const Scored& a, const Scored& b) { return a.volume < b.volume; });
  DistinctBoxes chosen, refined;
  for (const Scored& s : scored) {
    if (static_cast<int>(chosen.boxes.size()) >= starts) break;
    const OrientedBox b = eval.Box(s.axis);
    if (chosen.Has(b)) continue;
    chosen.Add(b);
    for (const Vec3d& ax : b.axes) refined.Add(Refine(ax, eval, step_deg));
  }
  return std::move(refined).Sorted();
}

}  // namespace

double SignedVolume(const Mesh& mesh) {
  // Divergence theorem: sum of signed tetrahedra (origin, a, b, c). The
  // centroid as origin keeps the terms small for meshes far from 0.
  Vec3d o{0, 0, 0};
  for (const auto& v : mesh.vertices) o = Add(o, v);
  if (!mesh.vertices.empty()) o = Mul(o, 1.0 / static_cast<double>(mesh.vertices.size()));
  double v6 = 0;
  for (const auto& f : mesh.faces) {
    const Vec3d a = Sub(mesh.vertices[f[0]], o), b = Sub(mesh.vertices[f[1]], o),
                c = Sub(mesh.vertices[f[2]], o);
    v6 += Dot(a, Cross(b, c));
  }
  return v6 / 6.0;
}

double SurfaceArea(const Mesh& mesh) {
  double a2 = 0;
  for (const auto& f : mesh.faces) {
    const Vec3d& a = mesh.vertices[f[0]];
    a2 += Norm(Cross(Sub(mesh.vertices[f[1]], a), Sub(mesh.vertices[f[2]], a)));
  }
  return a2 / 2.0;
}

std::vector<Vec3d> FibonacciDirections(int n, bool half) {
  std::vector<Vec3d> dirs;
  dirs.reserve(static_cast<size_t>(std::max(0, n)));
  const double golden = std::numbers::pi * (3.0 - std::sqrt(5.0));  // golden angle
  const double span = half ? 1.0 : 2.0;                             // z from 1 down to 0 or -1
  for (int k = 0; k < n; ++k) {
    const double z = 1.0 - span * (k + 0.5) / n, r = std::sqrt(std::max(0.0, 1.0 - z * z));
    dirs.push_back({r * std::cos(golden * k), r * std::sin(golden * k), z});
  }
  return dirs;
}

bool ConvexHull(const std::vector<Vec3d>& points, Mesh* hull) {
  // Qhull (reentrant libqhull_r): its merging of nearly coplanar facets keeps
  // it exact on rounded input, such as the float vertices of a PLY file with
  // a flat base, where a plain quickhull's horizon can pinch and never close.
  hull->vertices.clear();
  hull->faces.clear();
  if (points.size() < 4) return false;
  std::vector<coordT> coords(points.size() * 3);
  for (size_t i = 0; i < points.size(); ++i)
    for (int k = 0; k < 3; ++k)
      coords[3 * i + static_cast<size_t>(k)] = points[i][static_cast<size_t>(k)];
  // Qhull reports problems (flat or too few distinct points) on a stream:
  // here an in-memory one, discarded, since false already says "degenerate".
  char* err_text = nullptr;
  size_t err_size = 0;
  FILE* err = open_memstream(&err_text, &err_size);
  qhT qh_storage;
  qhT* qh = &qh_storage;
  qh_zero(qh, err);
  char flags[] = "qhull Qt";  // triangulated output
  const int code = qh_new_qhull(qh, 3, static_cast<int>(points.size()), coords.data(), False, flags,
                                nullptr, err);
  if (code == 0) {
    std::unordered_map<int, int> remap;
    facetT* facet = nullptr;
    FORALLfacets {
      std::array<int, 3> tri{};
      int k = 0;
      vertexT* vertex = nullptr;
      vertexT** vertexp = nullptr;
      FOREACHvertex_(facet->vertices) {
        if (k == 3) break;
        const int id = qh_pointid(qh, vertex->point);
        auto [it, inserted] = remap.try_emplace(id, static_cast<int>(hull->vertices.size()));
        if (inserted) hull->vertices.push_back(points[static_cast<size_t>(id)]);
        tri[static_cast<size_t>(k++)] = it->second;
      }
      if (k != 3) continue;
      // Counter-clockwise seen from outside: agree with Qhull's outward normal.
      const Vec3d& a = hull->vertices[static_cast<size_t>(tri[0])];
      const Vec3d n = Cross(Sub(hull->vertices[static_cast<size_t>(tri[1])], a),
                            Sub(hull->vertices[static_cast<size_t>(tri[2])], a));
      if (n[0] * facet->normal[0] + n[1] * facet->normal[1] + n[2] * facet->normal[2] < 0)
        std::swap(tri[1], tri[2]);
      hull->faces.push_back(tri);
    }
  }
  qh_freeqhull(qh, !qh_ALL);
  int curlong = 0, totlong = 0;
  qh_memfreeshort(qh, &curlong, &totlong);
  std::fclose(err);
  std::free(err_text);
  if (code != 0 || hull->faces.size() < 4) {
    hull->vertices.clear();
    hull->faces.clear();
    return false;
  }
  return true;
}

double MinAreaRect(const std::vector<std::array<double, 2>>& points, std::array<double, 2>* dir,
                   double* w, double* h, std::array<double, 2>* lo) {
  return MinAreaRectOfHull(Hull2D(points), dir, w, h, lo);
}

std::vector<OrientedBox> MinVolumeBoxes(const std::vector<Vec3d>& points, int starts) {
  Mesh hull;
  std::vector<Vec3d> hv;
  if (!ConvexHull(points, &hull)) {
    // Flat or degenerate: the principal axes of the points themselves; the
    // thinnest one is the normal of the plane the points lie in.
    OrientedBox best;
    bool first = true;
    for (const Vec3d& ax : PrincipalAxes(points)) {
      OrientedBox b = BoxForAxis(ax, points);
      if (first || b.size[2] < best.size[2]) best = b;
      first = false;
    }
    return {best};
  }
  hv = hull.vertices;

  HullEval full(hull);
  // Large hulls: search on the hull of a few hundred extreme points first,
  // then refine the winners on the whole hull.
  constexpr size_t kSmallHull = 500;
  Mesh coarse_hull;
  const bool two_stage = hv.size() > kSmallHull && ConvexHull(ExtremeSubset(hv, 600), &coarse_hull);
  HullEval coarse(two_stage ? coarse_hull : hull);

  std::vector<Vec3d> cand;
  for (const Vec3d& n : coarse.normals())
    if (Norm(n) > 0) cand.push_back(Normalized(n));
  // Pairs of edge directions: a box face parallel to two hull edges.
  const std::vector<Vec3d> edges = coarse.EdgeDirections();
  if (edges.size() <= 200) {
    for (size_t i = 0; i < edges.size(); ++i)
      for (size_t j = i + 1; j < edges.size(); ++j) {
        const Vec3d c = Cross(edges[i], edges[j]);
        if (Norm(c) > 1e-6) cand.push_back(Normalized(c));
      }
  }
  for (const Vec3d& ax : PrincipalAxes(hv)) cand.push_back(ax);
  cand.push_back({1, 0, 0});
  cand.push_back({0, 1, 0});
  cand.push_back({0, 0, 1});
  std::vector<OrientedBox> boxes = SearchBoxes(coarse, cand, std::max(1, starts), 2.0);
  if (two_stage) {
    DistinctBoxes fine;
    for (const OrientedBox& b : boxes) {
      const std::vector<Vec3d> axes(b.axes.begin(), b.axes.end());
      for (const OrientedBox& r : SearchBoxes(full, axes, 1, 0.5)) fine.Add(r);
    }
    boxes = std::move(fine).Sorted();
  }
  // The best candidates above all lie in the deepest basins. A rounded rock
  // may have other boxes within a fraction of a percent of the minimum's
  // volume in basins no hull face points into (its a, b, c are then
  // ill-conditioned, and a user is told so only if they are found): every
  // local minimum over directions spread evenly on the half sphere (a
  // Fibonacci lattice, about 2.6 deg apart) within 5 % of the minimum is
  // refined as well, on the whole hull (a few hundred extreme points hide
  // such basins).
  {
    constexpr int kSpread = 3000;
    // Scored on at most a few thousand extreme points (a rock's whole hull).
    Mesh spread_hull;
    std::optional<HullEval> subset;
    if (hv.size() > 3000 && ConvexHull(ExtremeSubset(hv, 3000), &spread_hull))
      subset.emplace(spread_hull);
    HullEval& spread = subset ? *subset : full;
    const std::vector<Vec3d> dirs = FibonacciDirections(kSpread, /*half=*/true);
    std::vector<double> vol(dirs.size());
    for (size_t i = 0; i < dirs.size(); ++i) vol[i] = spread.Box(dirs[i]).Volume();
    const double limit = 1.05 * boxes.front().Volume();  // unrefined lattice boxes run high
    const double near_cos =
        std::cos(4.7 * std::numbers::pi / 180);  // the lattice's nearest neighbours
    std::vector<std::pair<double, size_t>> minima;
    for (size_t i = 0; i < dirs.size(); ++i) {
      if (vol[i] > limit) continue;
      bool minimum = true;
      for (size_t j = 0; j < dirs.size() && minimum; ++j)
        if (j != i && std::fabs(Dot(dirs[i], dirs[j])) > near_cos && vol[j] < vol[i])
          minimum = false;
      if (minimum) minima.emplace_back(vol[i], i);
    }
    // A sphere is all minima: the 24 smallest are plenty for a rock.
    std::sort(minima.begin(), minima.end());
    if (minima.size() > 24) minima.resize(24);
    DistinctBoxes all;
    for (const OrientedBox& b : boxes) all.Add(b);
    for (const auto& [v, i] : minima) {
      for (const OrientedBox& r : SearchBoxes(full, {dirs[i]}, 1, 2.0)) all.Add(r);
    }
    boxes = std::move(all).Sorted();
  }
  return boxes;
}

OrientedBox MinVolumeBox(const std::vector<Vec3d>& points) {
  return MinVolumeBoxes(points, 4).front();
}

void TaubinSmooth(Mesh* mesh, int iterations, double lambda, double mu) {
  const size_t nv = mesh->vertices.size();
  std::vector<std::vector<int>> nb(nv);
  for (const auto& f : mesh->faces) {
    for (int k = 0; k < 3; ++k) {
      nb[f[k]].push_back(f[(k + 1) % 3]);
      nb[f[k]].push_back(f[(k + 2) % 3]);
    }
  }
  for (auto& n : nb) {
    std::sort(n.begin(), n.end());
    n.erase(std::unique(n.begin(), n.end()), n.end());
  }
  std::vector<Vec3d> next(nv);
  for (int it = 0; it < 2 * iterations; ++it) {
    const double f = it % 2 == 0 ? lambda : mu;
    for (size_t i = 0; i < nv; ++i) {
      next[i] = mesh->vertices[i];
      if (nb[i].empty()) continue;
      Vec3d c{0, 0, 0};
      for (int j : nb[i]) c = Add(c, mesh->vertices[j]);
      const double inv = 1.0 / static_cast<double>(nb[i].size());
      for (int k = 0; k < 3; ++k) next[i][k] += f * (c[k] * inv - mesh->vertices[i][k]);
    }
    mesh->vertices.swap(next);
  }
}

MeshProps ComputeMeshProps(const Mesh& mesh) {
  MeshProps p;
  if (mesh.faces.empty() || mesh.vertices.empty()) return p;
  p.volume_mm3 = std::fabs(SignedVolume(mesh));
  p.surface_area_mm2 = SurfaceArea(mesh);
  // Only vertices used by a face belong to the surface.
  std::vector<char> used(mesh.vertices.size(), 0);
  for (const auto& f : mesh.faces)
    for (int i : f) used[i] = 1;
  std::vector<Vec3d> pts;
  for (size_t i = 0; i < mesh.vertices.size(); ++i)
    if (used[i]) pts.push_back(mesh.vertices[i]);
  const std::vector<OrientedBox> boxes = MinVolumeBoxes(pts, 8);
  auto sorted_sides = [](const OrientedBox& b) {
    std::array<double, 3> d = b.size;
    std::sort(d.begin(), d.end());
    return d;
  };
  const std::array<double, 3> d = sorted_sides(boxes.front());
  p.a_mm = d[0];
  p.b_mm = d[1];
  p.c_mm = d[2];
  std::vector<std::array<double, 3>> kept = {d};
  for (size_t i = 1; i < boxes.size(); ++i) {
    const std::array<double, 3> e = sorted_sides(boxes[i]);
    // Distinct from every box already kept (the minimum first).
    bool distinct = true;
    for (const auto& k : kept) {
      double differ = 0;
      for (size_t j = 0; j < 3; ++j) differ = std::max(differ, std::fabs(e[j] / k[j] - 1));
      distinct = distinct && differ > kBoxDistinct;
    }
    if (!distinct) continue;
    kept.push_back(e);
    const double ratio = boxes[i].Volume() / boxes.front().Volume();
    if (p.second_box_volume_ratio == 0) {
      p.second_box_volume_ratio = ratio;
      p.second_a_mm = e[0];
      p.second_b_mm = e[1];
      p.second_c_mm = e[2];
    }
    if (ratio <= 1 + kBoxAmbiguousVolume) p.near_boxes.push_back({e[0], e[1], e[2], ratio});
  }
  if (p.surface_area_mm2 > 0)
    p.sphericity =
        std::cbrt(36.0 * std::numbers::pi * p.volume_mm3 * p.volume_mm3) / p.surface_area_mm2;
  if (p.a_mm > 0) p.fer_3d = p.c_mm / p.a_mm;
  if (p.b_mm > 0) p.c_over_b = p.c_mm / p.b_mm;
  if (p.a_mm > 0) p.b_over_a = p.b_mm / p.a_mm;
  return p;
}

nlohmann::json MeshPropsJson(const MeshProps& p) {
  return {{"volume_mm3", p.volume_mm3},
          {"surface_area_mm2", p.surface_area_mm2},
          {"a_mm", p.a_mm},
          {"b_mm", p.b_mm},
          {"c_mm", p.c_mm},
          {"fer_3d", p.fer_3d},
          {"ratio_c_b", p.c_over_b},
          {"ratio_b_a", p.b_over_a},
          {"sphericity", p.sphericity},
          {"second_box", p.second_box_volume_ratio > 0
                             ? nlohmann::json{{"volume_ratio", p.second_box_volume_ratio},
                                              {"a_mm", p.second_a_mm},
                                              {"b_mm", p.second_b_mm},
                                              {"c_mm", p.second_c_mm}}
                             : nlohmann::json()},
          {"box_ill_conditioned", BoxIllConditioned(p)},
          {"near_minimal_boxes", [&] {
             nlohmann::json a = nlohmann::json::array();
             for (const MeshProps::NearBox& b : p.near_boxes)
               a.push_back({{"a_mm", b.a_mm},
                            {"b_mm", b.b_mm},
                            {"c_mm", b.c_mm},
                            {"volume_ratio", b.volume_ratio}});
             return a;
           }()}};
}

}  // namespace aggscan
