// Ground-truth morphology: synthetic solids with exact answers, and the SHAPE
// toolbox meshes against their analytic table (skipped without shared data).
#include "common/mesh_props.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <numbers>
#include <ostream>
#include <random>
#include <set>

#include "common/mesh.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using std::numbers::pi;

using Mat3 = std::array<Vec3d, 3>;

Mat3 RotationZyx(double az, double ay, double ax) {
  const double cz = std::cos(az), sz = std::sin(az), cy = std::cos(ay), sy = std::sin(ay),
               cx = std::cos(ax), sx = std::sin(ax);
  return {{{cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx},
           {sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx},
           {-sy, cy * sx, cy * cx}}};
}

Mesh Transform(Mesh m, const Mat3& r, const Vec3d& t) {
  for (auto& v : m.vertices) {
    const Vec3d p = v;
    for (int i = 0; i < 3; ++i) v[i] = r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + t[i];
  }
  return m;
}

Mesh Box(double x, double y, double z) {
  Mesh m;
  m.vertices = {{0, 0, 0}, {x, 0, 0}, {x, y, 0}, {0, y, 0},
                {0, 0, z}, {x, 0, z}, {x, y, z}, {0, y, z}};
  for (const auto& q : std::vector<std::array<int, 4>>{
           {0, 3, 2, 1}, {4, 5, 6, 7}, {0, 1, 5, 4}, {2, 3, 7, 6}, {0, 4, 7, 3}, {1, 2, 6, 5}}) {
    m.faces.push_back({q[0], q[1], q[2]});
    m.faces.push_back({q[0], q[2], q[3]});
  }
  return m;
}

// Regular tetrahedron on alternate corners of the cube [0,s]^3.
Mesh Tetrahedron(double s) {
  Mesh m;
  m.vertices = {{0, 0, 0}, {s, s, 0}, {s, 0, s}, {0, s, s}};
  m.faces = {{0, 2, 1}, {0, 1, 3}, {0, 3, 2}, {1, 2, 3}};
  return m;
}

// UV-sphere-like ellipsoid with semi-axes (a, b, c).
Mesh Ellipsoid(double a, double b, double c, int rings, int segs) {
  Mesh m;
  m.vertices.push_back({0, 0, c});
  for (int i = 1; i < rings; ++i) {
    const double th = pi * i / rings;
    for (int j = 0; j < segs; ++j) {
      const double ph = 2 * pi * j / segs;
      m.vertices.push_back(
          {a * std::sin(th) * std::cos(ph), b * std::sin(th) * std::sin(ph), c * std::cos(th)});
    }
  }
  m.vertices.push_back({0, 0, -c});
  const int south = static_cast<int>(m.vertices.size()) - 1;
  auto idx = [&](int ring, int seg) { return 1 + (ring - 1) * segs + (seg % segs); };
  for (int j = 0; j < segs; ++j) m.faces.push_back({0, idx(1, j), idx(1, j + 1)});
  for (int i = 1; i + 1 < rings; ++i)
    for (int j = 0; j < segs; ++j) {
      m.faces.push_back({idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)});
      m.faces.push_back({idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)});
    }
  for (int j = 0; j < segs; ++j)
    m.faces.push_back({south, idx(rings - 1, j + 1), idx(rings - 1, j)});
  return m;
}

TEST(MeshProps, RotatedBox) {
  const Mesh m = Transform(Box(10, 20, 35), RotationZyx(0.3, 0.7, -1.1), {100, -50, 7});
  const MeshProps p = ComputeMeshProps(m);
  EXPECT_NEAR(p.volume_mm3, 7000, 1e-6);
  EXPECT_NEAR(p.surface_area_mm2, 2 * (200 + 350 + 700), 1e-6);
  EXPECT_NEAR(p.a_mm, 10, 1e-6);
  EXPECT_NEAR(p.b_mm, 20, 1e-6);
  EXPECT_NEAR(p.c_mm, 35, 1e-6);
  EXPECT_NEAR(p.fer_3d, 3.5, 1e-6);
  EXPECT_NEAR(p.c_over_b, 1.75, 1e-6);
  EXPECT_NEAR(p.b_over_a, 2.0, 1e-6);
}

TEST(MeshProps, InvertedOrientationStillPositiveVolume) {
  Mesh m = Box(1, 2, 3);
  for (auto& f : m.faces) std::swap(f[1], f[2]);
  EXPECT_NEAR(SignedVolume(m), -6.0, 1e-12);
  EXPECT_NEAR(ComputeMeshProps(m).volume_mm3, 6.0, 1e-12);
}

TEST(MeshProps, TetrahedronBoxIsTheCube) {
  // The minimum box of a regular tetrahedron is the cube it is inscribed in
  // (volume s^3), not a box on one of its faces (volume 2 s^3): needs the
  // edge-pair candidates.
  const Mesh m = Transform(Tetrahedron(3), RotationZyx(1.0, -0.4, 0.2), {5, 5, 5});
  const MeshProps p = ComputeMeshProps(m);
  EXPECT_NEAR(p.volume_mm3, 9.0, 1e-9);
  EXPECT_NEAR(p.sphericity, 0.67114, 1e-5);
  EXPECT_NEAR(p.a_mm, 3, 1e-6);
  EXPECT_NEAR(p.b_mm, 3, 1e-6);
  EXPECT_NEAR(p.c_mm, 3, 1e-6);
}

TEST(MeshProps, RotatedEllipsoidBoxIsTwiceTheSemiAxes) {
  const Mesh m = Transform(Ellipsoid(10, 25, 40, 90, 180), RotationZyx(0.9, 0.5, 0.3), {1, 2, 3});
  const MeshProps p = ComputeMeshProps(m);
  EXPECT_NEAR(p.a_mm, 20, 20 * 0.005);
  EXPECT_NEAR(p.b_mm, 50, 50 * 0.005);
  EXPECT_NEAR(p.c_mm, 80, 80 * 0.005);
  EXPECT_NEAR(p.volume_mm3, 4.0 / 3 * pi * 10 * 25 * 40, 4.0 / 3 * pi * 10 * 25 * 40 * 0.005);
}

TEST(MeshProps, BoxEnclosesAllPointsAndBeatsAxisAligned) {
  std::mt19937_64 rng(7);
  std::normal_distribution<double> g(0, 1);
  for (int trial = 0; trial < 5; ++trial) {
    std::vector<Vec3d> pts;
    for (int i = 0; i < 400; ++i) pts.push_back({g(rng) * 30, g(rng) * 12, g(rng) * 5});
    const Mat3 r = RotationZyx(trial * 0.7, trial * 0.3, 1.0 - trial * 0.2);
    for (auto& p : pts) {
      const Vec3d q = p;
      for (int i = 0; i < 3; ++i) p[i] = r[i][0] * q[0] + r[i][1] * q[1] + r[i][2] * q[2];
    }
    const OrientedBox b = MinVolumeBox(pts);
    for (const auto& p : pts) {
      for (int k = 0; k < 3; ++k) {
        double s = 0;
        for (int i = 0; i < 3; ++i) s += (p[i] - b.center[i]) * b.axes[k][i];
        EXPECT_LE(std::fabs(s), b.size[k] / 2 + 1e-7);
      }
    }
    // Axes orthonormal.
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < 3; ++j) {
        double d = 0;
        for (int k = 0; k < 3; ++k) d += b.axes[i][k] * b.axes[j][k];
        EXPECT_NEAR(d, i == j ? 1.0 : 0.0, 1e-9);
      }
    Vec3d lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
    for (const auto& p : pts)
      for (int i = 0; i < 3; ++i) {
        lo[i] = std::min(lo[i], p[i]);
        hi[i] = std::max(hi[i], p[i]);
      }
    EXPECT_LT(b.Volume(), (hi[0] - lo[0]) * (hi[1] - lo[1]) * (hi[2] - lo[2]));
  }
}

TEST(MeshProps, ConvexHullOfCubeWithInteriorAndFacePoints) {
  std::vector<Vec3d> pts;
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> u(0, 1);
  for (int i = 0; i < 2000; ++i) pts.push_back({u(rng), u(rng), u(rng)});
  for (int i = 0; i < 200; ++i) pts.push_back({u(rng), u(rng), 1.0});  // on the top face
  for (double x : {0.0, 1.0})
    for (double y : {0.0, 1.0})
      for (double z : {0.0, 1.0}) pts.push_back({x, y, z});
  Mesh hull;
  ASSERT_TRUE(ConvexHull(pts, &hull));
  EXPECT_NEAR(SignedVolume(hull), 1.0, 1e-12);
  EXPECT_NEAR(SurfaceArea(hull), 6.0, 1e-12);
  EXPECT_EQ(hull.vertices.size(), 8u);
  // Closed: every directed edge has its opposite.
  std::set<std::pair<int, int>> e;
  for (const auto& f : hull.faces)
    for (int k = 0; k < 3; ++k) e.insert({f[k], f[(k + 1) % 3]});
  for (const auto& [a, b] : e) EXPECT_TRUE(e.count({b, a}));
}

TEST(MeshProps, ConvexHullOfSpherePointsIsClosedAndConvex) {
  std::vector<Vec3d> pts;
  std::mt19937_64 rng(11);
  std::normal_distribution<double> g(0, 1);
  for (int i = 0; i < 3000; ++i) {
    Vec3d p{g(rng), g(rng), g(rng)};
    const double n = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    for (double& c : p) c *= 50 / n;
    pts.push_back(p);
  }
  Mesh hull;
  ASSERT_TRUE(ConvexHull(pts, &hull));
  EXPECT_EQ(hull.vertices.size(), 3000u);
  EXPECT_EQ(hull.faces.size(), 2 * 3000u - 4);
  EXPECT_NEAR(SignedVolume(hull), 4.0 / 3 * pi * 50 * 50 * 50, 4.0 / 3 * pi * 125000 * 0.02);
  for (const auto& f : hull.faces) {  // every point behind every face plane
    const Vec3d &a = hull.vertices[f[0]], &b = hull.vertices[f[1]], &c = hull.vertices[f[2]];
    const Vec3d ab{b[0] - a[0], b[1] - a[1], b[2] - a[2]},
        ac{c[0] - a[0], c[1] - a[1], c[2] - a[2]};
    const Vec3d n{ab[1] * ac[2] - ab[2] * ac[1], ab[2] * ac[0] - ab[0] * ac[2],
                  ab[0] * ac[1] - ab[1] * ac[0]};
    for (size_t i = 0; i < pts.size(); i += 37) {
      const double s =
          n[0] * (pts[i][0] - a[0]) + n[1] * (pts[i][1] - a[1]) + n[2] * (pts[i][2] - a[2]);
      EXPECT_LE(s, 1e-6);
    }
  }
}

// Nearly coplanar input, as a PLY's rounded vertices or a carved hull's flat
// base give: a rotated 12 x 12 x 12 lattice (every face a plane of 144
// points) rounded to float, each point twice. A quickhull without merging of
// coplanar facets pinched its horizon on such input and grew without end
// (a 50k-vertex reconstruction hung `aggscan morph` at 3.5 GB).
TEST(MeshProps, ConvexHullOfRoundedCoplanarLatticeIsTheCube) {
  const Mat3 r = RotationZyx(0.3, -0.7, 1.1);
  const double side = 110.0;  // mm: 11 steps of 10 mm
  std::vector<Vec3d> pts;
  for (int i = 0; i < 12; ++i)
    for (int j = 0; j < 12; ++j)
      for (int k = 0; k < 12; ++k) {
        const Vec3d q{10.0 * i - 55, 10.0 * j - 55, 10.0 * k - 55};
        Vec3d p{};
        for (int a = 0; a < 3; ++a) {
          const double x = r[a][0] * q[0] + r[a][1] * q[1] + r[a][2] * q[2] + 40.0 * (a + 1);
          p[a] = static_cast<double>(static_cast<float>(x));
        }
        pts.push_back(p);
        pts.push_back(p);
      }
  Mesh hull;
  ASSERT_TRUE(ConvexHull(pts, &hull));
  EXPECT_NEAR(SignedVolume(hull), side * side * side, side * side * side * 1e-5);
  EXPECT_NEAR(SurfaceArea(hull), 6 * side * side, 6 * side * side * 1e-5);
  std::set<std::pair<int, int>> e;
  for (const auto& f : hull.faces)
    for (int k = 0; k < 3; ++k) e.insert({f[k], f[(k + 1) % 3]});
  for (const auto& [a, b] : e) EXPECT_TRUE(e.count({b, a}));
  // Every input point inside every face plane, to the rounding.
  for (const auto& f : hull.faces) {
    const Vec3d &a = hull.vertices[f[0]], &b = hull.vertices[f[1]], &c = hull.vertices[f[2]];
    const Vec3d ab{b[0] - a[0], b[1] - a[1], b[2] - a[2]},
        ac{c[0] - a[0], c[1] - a[1], c[2] - a[2]};
    Vec3d n{ab[1] * ac[2] - ab[2] * ac[1], ab[2] * ac[0] - ab[0] * ac[2],
            ab[0] * ac[1] - ab[1] * ac[0]};
    const double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    if (len < 1e-9) continue;  // a sliver from the triangulation of a merged face
    for (double& x : n) x /= len;
    for (const Vec3d& p : pts)
      EXPECT_LE(n[0] * (p[0] - a[0]) + n[1] * (p[1] - a[1]) + n[2] * (p[2] - a[2]), 1e-4);
  }
  const OrientedBox box = MinVolumeBox(pts);
  for (double s : box.size) EXPECT_NEAR(s, side, 1e-3);
}

TEST(MeshProps, DegenerateInputs) {
  EXPECT_EQ(ComputeMeshProps(Mesh{}).volume_mm3, 0.0);
  Mesh flat;  // a single square in the plane z = 0
  flat.vertices = {{0, 0, 0}, {4, 0, 0}, {4, 2, 0}, {0, 2, 0}};
  flat.faces = {{0, 1, 2}, {0, 2, 3}};
  const MeshProps p = ComputeMeshProps(flat);
  EXPECT_NEAR(p.volume_mm3, 0, 1e-12);
  EXPECT_NEAR(p.surface_area_mm2, 8, 1e-12);
  EXPECT_NEAR(p.a_mm, 0, 1e-9);
  EXPECT_NEAR(p.b_mm, 2, 1e-9);
  EXPECT_NEAR(p.c_mm, 4, 1e-9);
  EXPECT_EQ(p.fer_3d, 0.0);
  Mesh hull;
  EXPECT_FALSE(ConvexHull(flat.vertices, &hull));
}

TEST(MeshProps, MinAreaRectMatchesBruteForce) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int trial = 0; trial < 50; ++trial) {
    std::vector<std::array<double, 2>> pts;
    const int n = 3 + trial;
    for (int i = 0; i < n; ++i) pts.push_back({u(rng) * 3, u(rng)});
    std::array<double, 2> dir, lo;
    double w, h;
    const double area = MinAreaRect(pts, &dir, &w, &h, &lo);
    // Brute force over a fine set of angles (the optimum lies on a hull edge,
    // so a 0.01 degree sweep comes within a small margin of it).
    double brute = 1e300;
    for (int k = 0; k < 18000; ++k) {
      const double a = pi * k / 36000;
      const double c = std::cos(a), s = std::sin(a);
      double x0 = 1e300, x1 = -1e300, y0 = 1e300, y1 = -1e300;
      for (const auto& p : pts) {
        const double x = c * p[0] + s * p[1], y = -s * p[0] + c * p[1];
        x0 = std::min(x0, x), x1 = std::max(x1, x), y0 = std::min(y0, y), y1 = std::max(y1, y);
      }
      brute = std::min(brute, (x1 - x0) * (y1 - y0));
    }
    EXPECT_LE(area, brute + 1e-12);
    EXPECT_GE(area, brute * (1 - 1e-3));
    EXPECT_NEAR(area, w * h, 1e-12);
  }
}

// ---------------------------------------------------------------- shape toolbox

struct Analytic {
  const char* name;
  double volume, area, sphericity;
  double a, b, c;  // minimum-volume box; 0 = not checked
};

// Readable CTest names (gtest prints the parameter).
void PrintTo(const Analytic& a, std::ostream* os) { *os << a.name; }

class ShapeToolbox : public ::testing::TestWithParam<Analytic> {};

TEST_P(ShapeToolbox, MatchesAnalyticTable) {
  const fs::path dir = fs::path(AGGSCAN_SHARED_DATA) / "meshes" / "shape_toolbox";
  if (!fs::is_directory(dir)) GTEST_SKIP() << "no shared data at " << dir;
  const Analytic& t = GetParam();
  auto m = LoadMesh((dir / (std::string(t.name) + ".stl")).string(), "mm");
  ASSERT_TRUE(m.ok()) << m.error().ToString();
  const MeshProps p = ComputeMeshProps(*m);
  EXPECT_NEAR(p.volume_mm3, t.volume, t.volume * 0.002);
  EXPECT_NEAR(p.surface_area_mm2, t.area, t.area * 0.002);
  EXPECT_NEAR(p.sphericity, t.sphericity, 0.002);
  if (t.a > 0) {
    EXPECT_NEAR(p.a_mm, t.a, t.a * 0.005);
    EXPECT_NEAR(p.b_mm, t.b, t.b * 0.005);
    EXPECT_NEAR(p.c_mm, t.c, t.c * 0.005);
  }
  std::printf("%-18s V %.6f A %.6f sph %.5f box %.5f x %.5f x %.5f\n", t.name, p.volume_mm3,
              p.surface_area_mm2, p.sphericity, p.a_mm, p.b_mm, p.c_mm);
}

// Platonic solids sit in a unit axis-aligned box; the tetrahedron's minimum
// box is that unit cube too (see TetrahedronBoxIsTheCube).
INSTANTIATE_TEST_SUITE_P(
    Analytic, ShapeToolbox,
    ::testing::Values(Analytic{"Sphere_R_1", 4.188790, 12.566371, 1.0, 2, 2, 2},
                      Analytic{"Ellipsoid_R_1_1_2", 8.377580, 21.478435, 0.92874, 2, 2, 4},
                      Analytic{"Ellipsoid_R_1_2_2", 16.755161, 34.687531, 0.91287, 2, 4, 4},
                      Analytic{"Ellipsoid_R_1_2_3", 25.132741, 48.8822, 0.84884, 2, 4, 6},
                      Analytic{"Tetrahedron", 1.0 / 3, 3.464102, 0.67114, 1, 1, 1},
                      Analytic{"Hexahedron", 1, 6, 0.80600, 1, 1, 1},
                      Analytic{"Octahedron", 1.0 / 6, 1.732051, 0.84558, 0, 0, 0},
                      Analytic{"Dodecahedron", 0.427051, 3.012171, 0.91045, 0, 0, 0},
                      Analytic{"Icosahedron", 0.515028, 3.307923, 0.93933, 0, 0, 0}),
    [](const ::testing::TestParamInfo<Analytic>& i) { return std::string(i.param.name); });

}  // namespace
}  // namespace aggscan

namespace aggscan {
namespace {

// Scanned stones: sane morphology, box at least as large as the solid.
TEST(MeshPropsSharedData, ScannedStones) {
  const fs::path dir = fs::path(AGGSCAN_SHARED_DATA) / "meshes";
  if (!fs::is_directory(dir)) GTEST_SKIP() << "no shared data at " << dir;
  struct Stone {
    const char* file;
    const char* unit;
    bool closed;
  };
  const Stone stones[] = {
      {"epfl_stones/low_res_0.ply", "m", true},
      {"epfl_stones/low_res_E22.ply", "m", true},
      {"epfl_stones/remeshed_high_res_A13.ply", "mm",
       false},  // non-manifold, misoriented: must not crash
      {"ashlar_stones/846.obj", "m", true},
      {"classic/spot.obj", "mm", true},
  };
  for (const Stone& s : stones) {
    SCOPED_TRACE(s.file);
    auto m = LoadMesh((dir / s.file).string(), s.unit);
    ASSERT_TRUE(m.ok()) << m.error().ToString();
    const MeshProps p = ComputeMeshProps(*m);
    EXPECT_GT(p.a_mm, 0);
    EXPECT_LE(p.a_mm, p.b_mm);
    EXPECT_LE(p.b_mm, p.c_mm);
    EXPECT_GE(p.fer_3d, 1.0);
    if (s.closed) {
      EXPECT_GT(p.volume_mm3, 0);
      EXPECT_LE(p.volume_mm3, p.a_mm * p.b_mm * p.c_mm);
      EXPECT_GT(p.sphericity, 0.3);
      EXPECT_LE(p.sphericity, 1.0);
    }
    std::printf("%-40s V %.4g mm3 A %.4g mm2 sph %.3f box %.2f x %.2f x %.2f mm\n", s.file,
                p.volume_mm3, p.surface_area_mm2, p.sphericity, p.a_mm, p.b_mm, p.c_mm);
  }
}

}  // namespace
}  // namespace aggscan
