#include "drivers/sim/world.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <limits>
#include <map>
#include <stdexcept>
#include <unordered_map>

#include "common/mesh_props.h"

namespace aggscan::sim {

namespace {

constexpr double kPi = 3.14159265358979323846;

// splitmix64: small, fast and identical on every platform (std distributions
// are not), so a seed gives the same rock everywhere.
class Rng {
 public:
  explicit Rng(uint64_t seed) : s_(seed) {}
  uint64_t Next() {
    uint64_t z = (s_ += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  double Uniform() { return static_cast<double>(Next() >> 11) * (1.0 / 9007199254740992.0); }
  double Uniform(double a, double b) { return a + (b - a) * Uniform(); }
  int Int(int n) { return static_cast<int>(Next() % static_cast<uint64_t>(n)); }
  Vec3 UnitVector() {
    const double z = Uniform(-1.0, 1.0);
    const double phi = Uniform(0.0, 2.0 * kPi);
    const double r = std::sqrt(std::max(0.0, 1.0 - z * z));
    return {r * std::cos(phi), r * std::sin(phi), z};
  }

 private:
  uint64_t s_;
};

// --- value noise (texture and roughness) ---

inline uint32_t Hash3(int x, int y, int z, uint32_t seed) {
  uint32_t h = static_cast<uint32_t>(x) * 0x8da6b343u ^ static_cast<uint32_t>(y) * 0xd8163841u ^
               static_cast<uint32_t>(z) * 0xcb1ab31fu ^ seed;
  h ^= h >> 13;
  h *= 0x5bd1e995u;
  h ^= h >> 15;
  return h;
}
inline float HashUnit(int x, int y, int z, uint32_t seed) {
  return static_cast<float>(Hash3(x, y, z, seed) & 0xffffffu) * (1.0f / 16777216.0f);
}

// Trilinear value noise in [0, 1) with smoothstep weights; lattice spacing 1.
float ValueNoise(float x, float y, float z, uint32_t seed) {
  const float fx = std::floor(x), fy = std::floor(y), fz = std::floor(z);
  const int ix = static_cast<int>(fx), iy = static_cast<int>(fy), iz = static_cast<int>(fz);
  float tx = x - fx, ty = y - fy, tz = z - fz;
  tx = tx * tx * (3.0f - 2.0f * tx);
  ty = ty * ty * (3.0f - 2.0f * ty);
  tz = tz * tz * (3.0f - 2.0f * tz);
  const float c000 = HashUnit(ix, iy, iz, seed), c100 = HashUnit(ix + 1, iy, iz, seed);
  const float c010 = HashUnit(ix, iy + 1, iz, seed), c110 = HashUnit(ix + 1, iy + 1, iz, seed);
  const float c001 = HashUnit(ix, iy, iz + 1, seed), c101 = HashUnit(ix + 1, iy, iz + 1, seed);
  const float c011 = HashUnit(ix, iy + 1, iz + 1, seed),
              c111 = HashUnit(ix + 1, iy + 1, iz + 1, seed);
  const float x00 = c000 + (c100 - c000) * tx, x10 = c010 + (c110 - c010) * tx;
  const float x01 = c001 + (c101 - c001) * tx, x11 = c011 + (c111 - c011) * tx;
  const float y0 = x00 + (x10 - x00) * ty, y1 = x01 + (x11 - x01) * ty;
  return y0 + (y1 - y0) * tz;
}

// --- convex hull (adapter over aggscan::ConvexHull) ---

struct HullTri {
  int a, b, c;  // indices into the input points, counter-clockwise seen from outside
  Vec3 n;       // outward unit normal (zero for a degenerate sliver)
  double d;     // plane offset: n . p = d on the face
};

// Indices of the points that can be hull vertices (Akl-Toussaint): the
// points extreme along 62 spread directions span an inner polytope, and a
// point strictly inside it is inside the hull. A rock mesh has ~7% of its
// vertices on the hull, so this leaves quickhull (unoptimised in Debug
// builds) far less to do.
std::vector<int> HullCandidates(const std::vector<Vec3>& pts) {
  const int n = static_cast<int>(pts.size());
  std::vector<int> all(n);
  for (int i = 0; i < n; ++i) all[i] = i;
  if (n < 256) return all;
  constexpr int kDirs = 62;
  std::vector<int> ext;
  for (const Vec3d& d : aggscan::FibonacciDirections(kDirs)) {
    const Vec3 dir{d[0], d[1], d[2]};
    int best = 0;
    double best_d = Dot(dir, pts[0]);
    for (int i = 1; i < n; ++i) {
      const double d = Dot(dir, pts[i]);
      if (d > best_d) best_d = d, best = i;
    }
    ext.push_back(best);
  }
  std::sort(ext.begin(), ext.end());
  ext.erase(std::unique(ext.begin(), ext.end()), ext.end());
  std::vector<Vec3d> inner_pts;
  double mag = 0;
  for (int i : ext) {
    inner_pts.push_back({pts[i].x, pts[i].y, pts[i].z});
    mag = std::max({mag, std::abs(pts[i].x), std::abs(pts[i].y), std::abs(pts[i].z)});
  }
  Mesh inner;
  if (!aggscan::ConvexHull(inner_pts, &inner)) return all;
  struct Plane {
    Vec3 n;
    double d;
  };
  std::vector<Plane> planes;
  for (const auto& f : inner.faces) {
    const Vec3 a = ToVec3(inner.vertices[f[0]]);
    const Vec3 nn =
        Normalized(Cross(ToVec3(inner.vertices[f[1]]) - a, ToVec3(inner.vertices[f[2]]) - a));
    if (Norm(nn) > 0.5) planes.push_back({nn, Dot(nn, a)});
  }
  // Keep anything not clearly inside: on or near an inner face counts as outside.
  const double tol = 1e-9 * std::max(mag, 1.0);
  std::vector<int> keep;
  for (int i = 0; i < n; ++i) {
    for (const Plane& pl : planes) {
      if (Dot(pl.n, pts[i]) - pl.d > -tol) {
        keep.push_back(i);
        break;
      }
    }
  }
  return keep;
}

// Convex hull of `pts` as outward triangles indexed into `pts` (Qhull through
// common/mesh_props); empty for degenerate input (fewer than 4 non-coplanar points).
std::vector<HullTri> ConvexHull(const std::vector<Vec3>& pts) {
  const std::vector<int> cand = HullCandidates(pts);
  std::vector<Vec3d> in;
  in.reserve(cand.size());
  for (int i : cand) in.push_back({pts[i].x, pts[i].y, pts[i].z});
  Mesh hull;
  if (!aggscan::ConvexHull(in, &hull)) return {};
  // The hull's vertices are exact copies of input points: map them back by
  // value (exact duplicates are interchangeable).
  struct Key {
    size_t operator()(const Vec3d& v) const {
      size_t h = 0;
      for (double c : v) h = h * 1000003u ^ std::hash<double>{}(c);
      return h;
    }
  };
  std::unordered_map<Vec3d, int, Key> index;
  index.reserve(hull.vertices.size());
  for (const Vec3d& v : hull.vertices) index.emplace(v, -1);
  for (int i = 0; i < static_cast<int>(in.size()); ++i) {
    auto it = index.find(in[i]);
    if (it != index.end() && it->second < 0) it->second = cand[i];
  }
  std::vector<HullTri> out;
  out.reserve(hull.faces.size());
  for (const auto& f : hull.faces) {
    const int a = index.at(hull.vertices[f[0]]), b = index.at(hull.vertices[f[1]]),
              c = index.at(hull.vertices[f[2]]);
    const Vec3 n = Normalized(Cross(pts[b] - pts[a], pts[c] - pts[a]));
    out.push_back({a, b, c, n, Dot(n, pts[a])});
  }
  return out;
}

// A flat facet of the hull: adjacent hull triangles whose corners all lie
// within a tolerance of one face plane (a sawn or chipped face of a rock, a
// cube side split into two triangles).
struct HullFacet {
  Vec3 n;                  // outward unit normal of the facet's largest triangle
  double d;                // its plane offset; every hull point has n . p <= d
  std::vector<int> verts;  // indices into the points, unordered, without repeats
};

// Merges the hull triangles into facets: grown over shared edges from the
// largest triangle left, a neighbour joins when its three corners are within
// `eps` of the seed's plane. The seed plane is a true hull face, so a rock put
// down on the facet rests on it exactly; the other corners are within eps.
std::vector<HullFacet> MergeCoplanar(const std::vector<HullTri>& tris, const std::vector<Vec3>& pts,
                                     double eps) {
  const int nt = static_cast<int>(tris.size());
  std::unordered_map<uint64_t, int> edge_tri;  // directed edge -> triangle holding it
  auto key = [](int u, int v) {
    return (static_cast<uint64_t>(static_cast<uint32_t>(u)) << 32) | static_cast<uint32_t>(v);
  };
  edge_tri.reserve(3 * tris.size());
  for (int t = 0; t < nt; ++t) {
    edge_tri[key(tris[t].a, tris[t].b)] = t;
    edge_tri[key(tris[t].b, tris[t].c)] = t;
    edge_tri[key(tris[t].c, tris[t].a)] = t;
  }
  std::vector<double> area(tris.size());
  std::vector<int> order(tris.size());
  for (int t = 0; t < nt; ++t) {
    const HullTri& h = tris[t];
    area[t] = Norm(Cross(pts[h.b] - pts[h.a], pts[h.c] - pts[h.a]));
    order[t] = t;
  }
  std::sort(order.begin(), order.end(),
            [&](int x, int y) { return area[x] > area[y] || (area[x] == area[y] && x < y); });
  std::vector<char> used(tris.size(), 0);
  std::vector<HullFacet> facets;
  std::vector<int> stack;
  for (int seed : order) {
    if (used[seed]) continue;
    const HullTri& s = tris[seed];
    HullFacet f{s.n, s.d, {}};
    auto on_plane = [&](int v) { return std::abs(Dot(f.n, pts[v]) - f.d) <= eps; };
    used[seed] = 1;
    stack.assign(1, seed);
    while (!stack.empty()) {
      const HullTri& t = tris[stack.back()];
      stack.pop_back();
      for (int v : {t.a, t.b, t.c}) f.verts.push_back(v);
      const int e[3][2] = {{t.a, t.b}, {t.b, t.c}, {t.c, t.a}};
      for (const auto& ed : e) {
        auto it = edge_tri.find(key(ed[1], ed[0]));
        if (it == edge_tri.end() || used[it->second]) continue;
        const HullTri& nb = tris[it->second];
        if (on_plane(nb.a) && on_plane(nb.b) && on_plane(nb.c)) {
          used[it->second] = 1;
          stack.push_back(it->second);
        }
      }
    }
    std::sort(f.verts.begin(), f.verts.end());
    f.verts.erase(std::unique(f.verts.begin(), f.verts.end()), f.verts.end());
    facets.push_back(std::move(f));
  }
  return facets;
}

// Signed distance from q to the boundary of the convex hull of `corners`
// (all on the plane with unit normal n): positive inside, negative outside.
double SupportMargin(const Vec3& q, const std::vector<Vec3>& corners, const Vec3& n) {
  const Vec3 u = Normalized(Cross(n, std::abs(n.x) < 0.9 ? Vec3{1, 0, 0} : Vec3{0, 1, 0}));
  const Vec3 w = Cross(n, u);
  std::vector<std::array<double, 2>> p;
  p.reserve(corners.size());
  for (const Vec3& c : corners) p.push_back({Dot(c - q, u), Dot(c - q, w)});
  // Andrew's monotone chain, counter-clockwise seen from the tip of n.
  std::sort(p.begin(), p.end());
  auto cross = [](const std::array<double, 2>& o, const std::array<double, 2>& a,
                  const std::array<double, 2>& b) {
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
  };
  std::vector<std::array<double, 2>> h(2 * p.size());
  size_t k = 0;
  for (size_t i = 0; i < p.size(); ++i) {
    while (k >= 2 && cross(h[k - 2], h[k - 1], p[i]) <= 0) --k;
    h[k++] = p[i];
  }
  for (size_t i = p.size() - 1, lo = k + 1; i-- > 0;) {
    while (k >= lo && cross(h[k - 2], h[k - 1], p[i]) <= 0) --k;
    h[k++] = p[i];
  }
  if (k < 4) return -1.0;  // fewer than 3 distinct corners: no area to stand on
  h.resize(k - 1);
  // q is the origin; the inward normal of edge (a, b) is its left normal.
  double margin = std::numeric_limits<double>::max();
  for (size_t i = 0; i < h.size(); ++i) {
    const auto& a = h[i];
    const auto& b = h[(i + 1) % h.size()];
    const double ex = b[0] - a[0], ey = b[1] - a[1], len = std::hypot(ex, ey);
    margin = std::min(margin, (ex * (0 - a[1]) - ey * (0 - a[0])) / len);
  }
  return margin;
}

// Geodesic sphere: each icosahedron face split into freq^2 triangles, vertices
// on the unit sphere, outward counter-clockwise faces.
void GeodesicSphere(int freq, std::vector<Vec3>* dirs, std::vector<std::array<int, 3>>* faces) {
  const double phi = (1.0 + std::sqrt(5.0)) / 2.0;
  std::vector<Vec3> ico;
  for (double s1 : {-1.0, 1.0})
    for (double s2 : {-1.0, 1.0}) {
      ico.push_back({0, s1, s2 * phi});
      ico.push_back({s1, s2 * phi, 0});
      ico.push_back({s2 * phi, 0, s1});
    }
  const std::vector<HullTri> ico_faces = ConvexHull(ico);
  // A vertex is identified by its integer weights on the icosahedron's
  // corners (sorted by corner), so shared edge points are built once.
  std::map<std::array<int, 6>, int> index;
  auto vertex = [&](std::array<std::pair<int, int>, 3> w) {
    std::sort(w.begin(), w.end());
    std::array<int, 6> k{-1, 0, -1, 0, -1, 0};
    size_t m = 0;
    Vec3 p;
    for (const auto& [corner, weight] : w) {
      if (weight == 0) continue;
      k[2 * m] = corner;
      k[2 * m + 1] = weight;
      ++m;
      p = p + ico[corner] * static_cast<double>(weight);
    }
    auto it = index.find(k);
    if (it != index.end()) return it->second;
    const int id = static_cast<int>(dirs->size());
    dirs->push_back(Normalized(p));
    index.emplace(k, id);
    return id;
  };
  for (const HullTri& f : ico_faces) {
    std::vector<std::vector<int>> g(freq + 1);
    for (int i = 0; i <= freq; ++i) {
      g[i].resize(freq + 1 - i);
      for (int j = 0; j + i <= freq; ++j) {
        g[i][j] = vertex({std::pair{f.a, freq - i - j}, std::pair{f.b, i}, std::pair{f.c, j}});
      }
    }
    for (int i = 0; i < freq; ++i) {
      for (int j = 0; i + j < freq; ++j) {
        faces->push_back({g[i][j], g[i + 1][j], g[i][j + 1]});
        if (i + j + 2 <= freq) faces->push_back({g[i + 1][j], g[i + 1][j + 1], g[i][j + 1]});
      }
    }
  }
}

// Volume and centre of mass of a closed mesh (divergence theorem).
void MassProperties(const Mesh& m, double* volume, Vec3* com) {
  double v = 0;
  Vec3 c;
  for (const auto& f : m.faces) {
    const Vec3 a = ToVec3(m.vertices[f[0]]), b = ToVec3(m.vertices[f[1]]),
               d = ToVec3(m.vertices[f[2]]);
    const double vi = Dot(a, Cross(b, d)) / 6.0;
    v += vi;
    c = c + (a + b + d) * (vi / 4.0);
  }
  *volume = v;
  *com = std::abs(v) > 0 ? c * (1.0 / v) : Vec3{};
}

// Rotation taking unit vector a onto unit vector b.
Rigid RotationBetween(const Vec3& a, const Vec3& b) {
  Rigid r;
  Vec3 axis = Cross(a, b);
  const double s = Norm(axis), c = Dot(a, b);
  if (s < 1e-12) {
    if (c > 0) return r;
    // Opposite: half turn about any axis perpendicular to a.
    axis = Normalized(Cross(a, std::abs(a.x) < 0.9 ? Vec3{1, 0, 0} : Vec3{0, 1, 0}));
    const double x = axis.x, y = axis.y, z = axis.z;
    r.R = {2 * x * x - 1, 2 * x * y, 2 * x * z, 2 * x * y,    2 * y * y - 1,
           2 * y * z,     2 * x * z, 2 * y * z, 2 * z * z - 1};
    return r;
  }
  axis = axis * (1.0 / s);
  const double x = axis.x, y = axis.y, z = axis.z, t = 1 - c;
  r.R = {t * x * x + c,     t * x * y - s * z, t * x * z + s * y, t * x * y + s * z, t * y * y + c,
         t * y * z - s * x, t * x * z - s * y, t * y * z + s * x, t * z * z + c};
  return r;
}

// Ray vs mesh (Moller-Trumbore); all hit distances t > 0 with face index.
void RayHits(const Mesh& m, const Vec3& o, const Vec3& dir,
             std::vector<std::pair<double, int>>* hits) {
  hits->clear();
  for (int f = 0; f < static_cast<int>(m.faces.size()); ++f) {
    const Vec3 a = ToVec3(m.vertices[m.faces[f][0]]);
    const Vec3 e1 = ToVec3(m.vertices[m.faces[f][1]]) - a,
               e2 = ToVec3(m.vertices[m.faces[f][2]]) - a;
    const Vec3 pv = Cross(dir, e2);
    const double det = Dot(e1, pv);
    if (std::abs(det) < 1e-12) continue;
    const double inv = 1.0 / det;
    const Vec3 tv = o - a;
    const double u = Dot(tv, pv) * inv;
    if (u < 0 || u > 1) continue;
    const Vec3 qv = Cross(tv, e1);
    const double v = Dot(dir, qv) * inv;
    if (v < 0 || u + v > 1) continue;
    const double t = Dot(e2, qv) * inv;
    if (t > 1e-9) hits->push_back({t, f});
  }
  std::sort(hits->begin(), hits->end());
}

}  // namespace

// --- Rigid / Intrinsics ---

Rigid Rigid::Inverse() const {
  Rigid r;
  r.R = {R[0], R[3], R[6], R[1], R[4], R[7], R[2], R[5], R[8]};
  r.t = -r.Rotate(t);
  return r;
}

Rigid operator*(const Rigid& a, const Rigid& b) {
  Rigid r;
  for (size_t i = 0; i < 3; ++i)
    for (size_t j = 0; j < 3; ++j)
      r.R[3 * i + j] =
          a.R[3 * i] * b.R[j] + a.R[3 * i + 1] * b.R[3 + j] + a.R[3 * i + 2] * b.R[6 + j];
  r.t = a.Apply(b.t);
  return r;
}

std::array<double, 16> Rigid::Matrix4() const {
  return {R[0], R[1], R[2], t.x, R[3], R[4], R[5], t.y, R[6], R[7], R[8], t.z, 0, 0, 0, 1};
}

Rigid Rigid::RotZ(double deg) {
  const double a = deg * kPi / 180.0, c = std::cos(a), s = std::sin(a);
  Rigid r;
  r.R = {c, -s, 0, s, c, 0, 0, 0, 1};
  return r;
}

bool Intrinsics::Project(const Vec3& p, double* u, double* v) const {
  if (p.z <= 1e-9) return false;
  const double x = p.x / p.z, y = p.y / p.z, r2 = x * x + y * y;
  const double s = 1.0 + k1 * r2 + k2 * r2 * r2;
  *u = fx * x * s + cx;
  *v = fy * y * s + cy;
  return true;
}

bool ColorAlbedo(const std::string& name, std::array<float, 3>* rgb) {
  if (name == "red")
    *rgb = {0.62f, 0.04f, 0.04f};
  else if (name == "green")
    *rgb = {0.04f, 0.42f, 0.08f};
  else if (name == "blue")
    *rgb = {0.03f, 0.10f, 0.55f};
  else if (name == "yellow")
    *rgb = {0.75f, 0.62f, 0.03f};
  else if (name == "purple")
    *rgb = {0.30f, 0.04f, 0.42f};
  else
    return false;
  return true;
}

// --- procedural rock ---

Mesh MakeProceduralRock(uint64_t seed, double size_mm, int target_faces) {
  Rng rng(seed * 0x2545F4914F6CDD1Dull + 0x1234567ull);
  const double length = size_mm > 0 ? size_mm : rng.Uniform(70.0, 200.0);
  const double fer = rng.Uniform(1.35, 2.6);
  const double c = length / 2.0, a = c / fer;
  const double b = a * std::pow(c / a, rng.Uniform(0.35, 0.75));

  // Random points on the ellipsoid; the six axis points keep the origin inside.
  std::vector<Vec3> pts = {{c, 0, 0}, {-c, 0, 0}, {0, b, 0}, {0, -b, 0}, {0, 0, a}, {0, 0, -a}};
  for (auto& p : pts) p = p * rng.Uniform(0.88, 1.0);
  const int extra = 18 + rng.Int(18);
  for (int i = 0; i < extra; ++i) {
    const Vec3 d = rng.UnitVector();
    pts.push_back(Vec3{c * d.x, b * d.y, a * d.z} * rng.Uniform(0.85, 1.0));
  }
  struct Plane {
    Vec3 n;
    double d;
  };
  std::vector<Plane> planes;
  for (const HullTri& t : ConvexHull(pts)) planes.push_back({t.n, t.d});
  // Chips: flat cuts a little inside the support in a random direction.
  const int chips = 3 + rng.Int(5);
  for (int i = 0; i < chips; ++i) {
    const Vec3 u = rng.UnitVector();
    double h = 0;
    for (const auto& p : pts) h = std::max(h, Dot(u, p));
    planes.push_back({u, h - rng.Uniform(0.08, 0.3) * a});
  }
  struct Dent {
    Vec3 dir;
    double sigma, depth;
  };
  std::vector<Dent> dents;
  const int ndents = 2 + rng.Int(3);
  dents.reserve(ndents);
  for (int i = 0; i < ndents; ++i)
    dents.push_back({rng.UnitVector(), rng.Uniform(0.2, 0.45), rng.Uniform(0.05, 0.14) * a});
  const uint32_t rough_seed = static_cast<uint32_t>(rng.Next());

  std::vector<Vec3> dirs;
  Mesh m;
  const int freq =
      std::max(2, static_cast<int>(std::lround(std::sqrt(std::max(80, target_faces) / 20.0))));
  GeodesicSphere(freq, &dirs, &m.faces);
  m.vertices.resize(dirs.size());
  for (size_t i = 0; i < dirs.size(); ++i) {
    const Vec3& d = dirs[i];
    double r = std::numeric_limits<double>::max();
    for (const Plane& pl : planes) {
      const double nd = Dot(pl.n, d);
      if (nd > 1e-9) r = std::min(r, pl.d / nd);
    }
    for (const Dent& dn : dents) {
      const double cosang = Dot(d, dn.dir);
      if (cosang <= 0) continue;
      const double ang = std::acos(std::min(1.0, cosang));
      r -= dn.depth * std::exp(-ang * ang / (2 * dn.sigma * dn.sigma));
    }
    const Vec3 p = d * r;
    // Fine roughness, ~0.3 mm at ~5 mm scale: breaks the facets' perfect flatness.
    const float nz = ValueNoise(static_cast<float>(p.x / 5.0), static_cast<float>(p.y / 5.0),
                                static_cast<float>(p.z / 5.0), rough_seed);
    r += 0.6 * (nz - 0.5);
    m.vertices[i] = {d.x * r, d.y * r, d.z * r};
  }

  // Centre on the centre of mass, clamp the extent ratio, scale to the length.
  double vol;
  Vec3 com;
  MassProperties(m, &vol, &com);
  std::array<double, 3> lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  for (auto& v : m.vertices) {
    v = {v[0] - com.x, v[1] - com.y, v[2] - com.z};
    for (int k = 0; k < 3; ++k) lo[k] = std::min(lo[k], v[k]), hi[k] = std::max(hi[k], v[k]);
  }
  std::array<double, 3> ext{hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]};
  const int kmax = static_cast<int>(std::max_element(ext.begin(), ext.end()) - ext.begin());
  const int kmin = static_cast<int>(std::min_element(ext.begin(), ext.end()) - ext.begin());
  std::array<double, 3> scale{1, 1, 1};
  const double ratio = ext[kmax] / ext[kmin];
  if (ratio < 1.25) scale[kmin] = ratio / 1.25;
  if (ratio > 2.9) scale[kmin] = ratio / 2.9;
  const double s = length / ext[kmax];
  for (auto& v : m.vertices)
    for (int k = 0; k < 3; ++k) v[k] *= scale[k] * s;
  // Non-uniform scaling about the centroid keeps it the centre of mass.
  return m;
}

// --- SimWorld ---

Result<std::shared_ptr<SimWorld>> SimWorld::Create(const Config& config,
                                                   const SimWorldOptions& options) {
  try {
    return std::make_shared<SimWorld>(config, options);
  } catch (const std::exception& e) {
    return MakeError(ErrorClass::kInvalidConfig, "cannot build the simulated world", e.what());
  }
}

SimWorld::SimWorld(const Config& config, const SimWorldOptions& options)
    : config_(config), options_(options) {
  const double ref = config.camera.exposure.exposure_us * config.camera.exposure.gain;
  reference_exposure_ = ref > 0 ? ref : 8000.0;
  // Key light from the camera's front-left, about 50 degrees up: the shadow
  // falls back and to the right where the camera sees it.
  lighting_.to_light = Normalized({-0.7, -0.35, 0.9});

  const double e = config.sim.camera_elevation_deg * kPi / 180.0;
  const double dist = config.sim.camera_distance_mm;
  const Vec3 aim{0, 0, kAimHeightMm};
  const Vec3 centre = aim + Vec3{0, -std::cos(e), std::sin(e)} * dist;
  const Vec3 zc{0, std::cos(e), -std::sin(e)};  // optical axis towards the aim point
  const Vec3 xc{1, 0, 0};
  const Vec3 yc = Cross(zc, xc);  // points down in the image
  world_to_camera_.R = {xc.x, xc.y, xc.z, yc.x, yc.y, yc.z, zc.x, zc.y, zc.z};
  world_to_camera_.t = -world_to_camera_.Rotate(centre);

  if (config.sim.scene == "charuco") {
    Result<SimBoard> b = LoadSimBoard(config);
    if (!b) throw std::runtime_error(b.error().ToString());
    board_.push_back(std::move(b).value());
  }
  Result<std::vector<SimArucoMarker>> aruco = LoadSimArucoMarkers(config);
  if (!aruco) throw std::runtime_error(aruco.error().ToString());
  aruco_ = std::move(aruco).value();
  BuildRock();
  ComputePoses();
  PlaceMarkers();
}

void SimWorld::BuildRock() {
  if (config_.sim.rock_mesh.empty()) {
    rock_ = MakeProceduralRock(config_.sim.seed, config_.sim.rock_size_mm, options_.rock_faces);
  } else {
    Result<Mesh> m = LoadMesh(config_.sim.rock_mesh, config_.sim.rock_unit);
    if (!m) throw std::runtime_error(m.error().ToString());
    rock_ = std::move(m).value();
  }
  if (rock_.faces.empty()) throw std::runtime_error("rock mesh has no faces");
  MassProperties(rock_, &volume_mm3_, &com_);
  if (volume_mm3_ < 0) {
    // Inward-oriented file: flip every face so normals point out.
    for (auto& f : rock_.faces) std::swap(f[1], f[2]);
    MassProperties(rock_, &volume_mm3_, &com_);
  }
  if (volume_mm3_ <= 0) throw std::runtime_error("rock mesh encloses no volume");
  face_normals_.resize(rock_.faces.size());
  for (size_t f = 0; f < rock_.faces.size(); ++f) {
    const auto& t = rock_.faces[f];
    const Vec3 a = ToVec3(rock_.vertices[t[0]]);
    face_normals_[f] =
        Normalized(Cross(ToVec3(rock_.vertices[t[1]]) - a, ToVec3(rock_.vertices[t[2]]) - a));
  }
  std::array<double, 3> lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  for (const auto& v : rock_.vertices)
    for (int k = 0; k < 3; ++k) lo[k] = std::min(lo[k], v[k]), hi[k] = std::max(hi[k], v[k]);
  longest_mm_ = std::max({hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]});
  Rng rng(config_.sim.seed * 0x9E3779B97F4A7C15ull + 77);
  texture_seed_ = static_cast<uint32_t>(rng.Next());
  // Slight per-rock colour cast: some rocks browner, some greyer.
  const float warm = static_cast<float>(rng.Uniform(-0.06, 0.08));
  tint_ = {1.0f + warm, 1.0f, 1.0f - warm};
}

void SimWorld::ComputePoses() {
  std::vector<Vec3> pts;
  pts.reserve(rock_.vertices.size());
  for (const auto& v : rock_.vertices) pts.push_back(ToVec3(v));
  // Corners within 0.02 mm of a resting face's plane count as touching the
  // disc: a flat face triangulated into many hull triangles supports the rock
  // over its whole outline, not just over the triangle under the COM.
  constexpr double kContactTolMm = 0.02;
  const std::vector<HullTri> hull = ConvexHull(pts);
  if (hull.empty()) throw std::runtime_error("rock mesh is flat; no convex hull");

  struct Candidate {
    Vec3 n;
    double height, margin;
  };
  std::vector<Candidate> cands;
  std::vector<Vec3> corners;
  for (const HullFacet& f : MergeCoplanar(hull, pts, kContactTolMm)) {
    const double h = f.d - Dot(f.n, com_);
    if (!(h > 0) || Norm(f.n) < 0.5) continue;  // not below the COM, or a degenerate sliver
    const Vec3 q = com_ + f.n * h;              // COM projected onto the face plane
    corners.clear();
    for (int v : f.verts) corners.push_back(pts[v]);
    const double margin = SupportMargin(q, corners, f.n);
    if (margin > 0) cands.push_back({f.n, h, margin});
  }
  if (cands.empty()) throw std::runtime_error("rock has no stable rest face");
  std::sort(cands.begin(), cands.end(),
            [](const Candidate& a, const Candidate& b) { return a.height < b.height; });

  std::vector<Candidate> chosen;
  // Side 1: the lowest centre of mass with a real support margin.
  auto first =
      std::find_if(cands.begin(), cands.end(), [](const Candidate& c) { return c.margin >= 1.0; });
  chosen.push_back(first != cands.end() ? *first : cands.front());
  // Side 2: flipped, the lowest rest whose down direction is roughly opposite.
  const Vec3 n1 = chosen[0].n;
  auto flip = std::find_if(cands.begin(), cands.end(),
                           [&](const Candidate& c) { return Dot(c.n, n1) < -0.5; });
  if (flip == cands.end()) {
    flip = std::min_element(
        cands.begin(), cands.end(),
        [&](const Candidate& a, const Candidate& b) { return Dot(a.n, n1) < Dot(b.n, n1); });
  }
  if (Dot(flip->n, n1) < 0.95) chosen.push_back(*flip);
  // Further sides: other distinct rests, most stable first.
  for (const Candidate& c : cands) {
    if (chosen.size() >= 6) break;
    bool distinct = true;
    for (const Candidate& u : chosen) distinct = distinct && Dot(c.n, u.n) < 0.95;
    if (distinct) chosen.push_back(c);
  }

  Rng rng(config_.sim.seed * 0xD1B54A32D192ED03ull + 5);
  for (const Candidate& c : chosen) {
    RestPose pose;
    pose.down_rock = c.n;
    pose.com_height_mm = c.height;
    pose.support_margin_mm = c.margin;
    Rigid r = Rigid::RotZ(rng.Uniform(0.0, 360.0)) * RotationBetween(c.n, {0, 0, -1});
    double zmin = std::numeric_limits<double>::max();
    for (const Vec3& p : pts) zmin = std::min(zmin, r.Rotate(p).z);
    const Vec3 com_r = r.Rotate(com_);
    const double rad = 10.0 * std::sqrt(rng.Uniform()), ang = rng.Uniform(0.0, 2 * kPi);
    r.t = {rad * std::cos(ang) - com_r.x, rad * std::sin(ang) - com_r.y, -zmin};
    pose.rock_to_turntable = r;
    poses_.push_back(pose);
  }
}

void SimWorld::PlaceMarkers() {
  const Vec3 d1 = poses_[0].down_rock;
  const Vec3 u = Normalized(Cross(d1, std::abs(d1.x) < 0.9 ? Vec3{1, 0, 0} : Vec3{0, 1, 0}));
  const Vec3 w = Cross(d1, u);
  // The longest horizontal direction of the rock resting on side 1.
  Vec3 long_axis = u;
  double best = -1;
  for (int i = 0; i < 90; ++i) {
    const double a = kPi * i / 90.0;
    const Vec3 dir = u * std::cos(a) + w * std::sin(a);
    double lo = 1e300, hi = -1e300;
    for (const auto& v : rock_.vertices) {
      const double s = Dot(ToVec3(v), dir);
      lo = std::min(lo, s), hi = std::max(hi, s);
    }
    if (hi - lo > best) best = hi - lo, long_axis = dir;
  }
  const Vec3 side_dir = Normalized(Cross(d1, long_axis));
  const double scale = std::clamp(longest_mm_ / 110.0, 0.7, 1.0);
  std::vector<std::pair<double, int>> hits;
  for (int k = 0; k < 2; ++k) {
    ObjectMarker m;
    m.color = k == 0 ? "purple" : "red";
    ColorAlbedo(m.color, &m.albedo);
    const Vec3 out = k == 0 ? side_dir : -side_dir;
    RayHits(rock_, com_, out, &hits);
    if (hits.empty()) continue;                 // COM outside a strange mesh: no marker
    m.origin = com_ + out * hits.back().first;  // outermost surface along the ray
    // Area-weighted normal of the faces around the origin: smoother than one face.
    Vec3 n;
    for (size_t f = 0; f < rock_.faces.size(); ++f) {
      const auto& t = rock_.faces[f];
      const Vec3 a = ToVec3(rock_.vertices[t[0]]), b = ToVec3(rock_.vertices[t[1]]),
                 c = ToVec3(rock_.vertices[t[2]]);
      if (Norm((a + b + c) * (1.0 / 3) - m.origin) < 10.0 * scale) n = n + Cross(b - a, c - a);
    }
    m.normal = Norm(n) > 0 ? Normalized(n) : out;
    m.axis = Normalized(long_axis - m.normal * Dot(long_axis, m.normal));
    if (k == 1) m.axis = -m.axis;
    m.head_mm *= scale, m.gap_mm *= scale, m.tail_mm *= scale, m.width_mm *= scale;
    const double total = m.head_mm + m.gap_mm + m.tail_mm;
    auto snap = [&](double along) {
      const Vec3 start = m.origin + m.axis * along + m.normal * 15.0;
      RayHits(rock_, start, -m.normal, &hits);
      return hits.empty() ? m.origin + m.axis * along : start - m.normal * hits.front().first;
    };
    m.head = snap(-total / 2 + m.head_mm / 2);
    m.tail = snap(-total / 2 + m.head_mm + m.gap_mm + m.tail_mm / 2);
    markers_.push_back(m);
  }
}

const RestPose& SimWorld::pose(int side) const {
  const int n = static_cast<int>(poses_.size());
  const int i = ((std::max(side, 1) - 1) % n + n) % n;
  return poses_[i];
}

Intrinsics SimWorld::IntrinsicsFor(int width, int height) const {
  Intrinsics k;
  k.width = width;
  k.height = height;
  k.fx = k.fy = FocalPxFromHfov(config_.sim.hfov_deg, width);
  k.cx = (width - 1) / 2.0;
  k.cy = (height - 1) / 2.0;
  k.k1 = config_.sim.k1;
  k.k2 = config_.sim.k2;
  return k;
}

RigCalibration SimWorld::TruthCalibration(int width, int height) const {
  const Intrinsics k = IntrinsicsFor(width, height);
  RigCalibration cal;
  cal.camera.width = k.width;
  cal.camera.height = k.height;
  cal.camera.fx = k.fx;
  cal.camera.fy = k.fy;
  cal.camera.cx = k.cx;
  cal.camera.cy = k.cy;
  cal.camera.k1 = k.k1;
  cal.camera.k2 = k.k2;
  // world is the table frame at platter angle 0 (world = Rz(platter) * turntable).
  cal.R_cam_table0 = world_to_camera_.R;
  cal.t_cam_table0 = {world_to_camera_.t.x, world_to_camera_.t.y, world_to_camera_.t.z};
  cal.method = "sim-truth";
  cal.camera_id = config_.camera.id;
  return cal;
}

Rigid SimWorld::RockToWorld(int side, double platter_deg) const {
  return TurntableToWorld(platter_deg) * pose(side).rock_to_turntable;
}

Rigid SimWorld::RockToCamera(int side, double platter_deg) const {
  return world_to_camera_ * RockToWorld(side, platter_deg);
}

bool SimWorld::ProjectTurntablePoint(const Vec3& p_tt, double platter_deg, const Intrinsics& intr,
                                     double* u, double* v) const {
  return intr.Project(world_to_camera_.Apply(TurntableToWorld(platter_deg).Apply(p_tt)), u, v);
}

std::array<float, 3> SimWorld::RockAlbedo(const Vec3& p, const Vec3& n) const {
  for (const ObjectMarker& m : markers_) {
    const Vec3 d = p - m.origin;
    const double h = Dot(d, m.normal);
    if (std::abs(h) > 12.0 || Dot(n, m.normal) < 0.3) continue;
    const double across = Dot(d, Cross(m.normal, m.axis));
    if (std::abs(across) > m.width_mm / 2) continue;
    const double along = Dot(d, m.axis) + (m.head_mm + m.gap_mm + m.tail_mm) / 2;
    if ((along >= 0 && along <= m.head_mm) ||
        (along >= m.head_mm + m.gap_mm && along <= m.head_mm + m.gap_mm + m.tail_mm)) {
      return m.albedo;
    }
  }
  const float x = static_cast<float>(p.x), y = static_cast<float>(p.y), z = static_cast<float>(p.z);
  const uint32_t s = texture_seed_;
  // Large-scale tone (fbm, 3 octaves from 16 mm), medium mottling (3 mm),
  // mineral grains (0.8 mm) and thin light veins: blobs at every scale SIFT uses.
  const float f = 1.0f / 16.0f;
  const float tone = 0.55f * ValueNoise(x * f, y * f, z * f, s) +
                     0.30f * ValueNoise(x * f * 2.1f, y * f * 2.1f, z * f * 2.1f, s + 1) +
                     0.15f * ValueNoise(x * f * 4.3f, y * f * 4.3f, z * f * 4.3f, s + 2);
  const float mottle = ValueNoise(x * 0.33f, y * 0.33f, z * 0.33f, s + 3);
  const float pits = ValueNoise(x * 0.55f, y * 0.55f, z * 0.55f, s + 5);  // ~2 mm
  const float grain = ValueNoise(x * 1.25f, y * 1.25f, z * 1.25f, s + 4);
  float r = 0.30f + 0.20f * tone, g = 0.29f + 0.17f * tone, b = 0.27f + 0.14f * tone;
  // Contrast like a quarried granite/limestone face at ~0.25 mm/px: strong
  // mottling and pitting, and grains dense enough to give SIFT blobs at the
  // 1-3 mm scales that survive 30 deg of turntable rotation.
  const float m = (0.62f + 0.76f * mottle) * (0.80f + 0.40f * pits);
  r *= m, g *= m, b *= m;
  if (grain > 0.74f) {
    r = 0.12f, g = 0.11f, b = 0.11f;  // dark grains
  } else if (grain < 0.20f) {
    r = 0.60f, g = 0.58f, b = 0.54f;  // light grains
  }
  const float vein = std::abs(std::sin(0.35f * (0.8f * x + 0.5f * y - 0.3f * z) + 9.0f * tone));
  if (vein < 0.05f) r = 0.60f, g = 0.59f, b = 0.56f;
  return {r * tint_[0], g * tint_[1], b * tint_[2]};
}

}  // namespace aggscan::sim
