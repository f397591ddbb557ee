// Procedural rock and sim world: geometry, rest poses, markers, camera truth.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <map>

#include "drivers/sim/world.h"

namespace aggscan::sim {
namespace {

double SignedVolume(const Mesh& m) {
  double v = 0;
  for (const auto& f : m.faces) {
    v += Dot(ToVec3(m.vertices[f[0]]), Cross(ToVec3(m.vertices[f[1]]), ToVec3(m.vertices[f[2]]))) /
         6.0;
  }
  return v;
}

std::array<double, 3> Extents(const Mesh& m) {
  std::array<double, 3> lo{1e300, 1e300, 1e300}, hi{-1e300, -1e300, -1e300};
  for (const auto& v : m.vertices)
    for (int k = 0; k < 3; ++k) lo[k] = std::min(lo[k], v[k]), hi[k] = std::max(hi[k], v[k]);
  return {hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]};
}

TEST(ProceduralRock, ClosedManifoldConsistentlyOriented) {
  const Mesh m = MakeProceduralRock(3, 0, 20000);
  // Every directed edge once, and its reverse once: closed, 2-manifold, oriented.
  std::map<std::pair<int, int>, int> directed;
  for (const auto& f : m.faces) {
    ASSERT_NE(f[0], f[1]);
    ASSERT_NE(f[1], f[2]);
    ASSERT_NE(f[0], f[2]);
    for (int k = 0; k < 3; ++k) ++directed[{f[k], f[(k + 1) % 3]}];
  }
  for (const auto& [e, n] : directed) {
    ASSERT_EQ(n, 1) << e.first << "->" << e.second;
    auto rev = directed.find({e.second, e.first});
    ASSERT_NE(rev, directed.end()) << "open edge " << e.first << "-" << e.second;
    ASSERT_EQ(rev->second, 1);
  }
  // Euler characteristic of a sphere.
  EXPECT_EQ(static_cast<long>(m.vertices.size()) - static_cast<long>(directed.size() / 2) +
                static_cast<long>(m.faces.size()),
            2);
  EXPECT_GT(SignedVolume(m), 0.0);  // outward orientation
}

TEST(ProceduralRock, SizeShapeAndFaceCount) {
  for (uint64_t seed = 1; seed <= 6; ++seed) {
    const Mesh m = MakeProceduralRock(seed, 0, 2000);
    const auto e = Extents(m);
    const double c = *std::max_element(e.begin(), e.end()),
                 a = *std::min_element(e.begin(), e.end());
    EXPECT_GE(c, 70.0 - 1e-6) << seed;
    EXPECT_LE(c, 200.0 + 1e-6) << seed;
    EXPECT_GE(c / a, 1.2) << seed;
    EXPECT_LE(c / a, 3.0) << seed;
    EXPECT_GT(SignedVolume(m), 0.0);
  }
  const Mesh fixed = MakeProceduralRock(9, 150.0, 20000);
  const auto e = Extents(fixed);
  EXPECT_NEAR(*std::max_element(e.begin(), e.end()), 150.0, 1e-6);
  EXPECT_NEAR(static_cast<double>(fixed.faces.size()), 20000, 2000);
  const Mesh big = MakeProceduralRock(9, 150.0, 100000);
  EXPECT_NEAR(static_cast<double>(big.faces.size()), 100000, 5000);
}

TEST(ProceduralRock, NonConvex) {
  // Dents make some vertices lie strictly inside the hull: some edge is concave
  // (the opposite vertex of a neighbour face lies in front of the face plane).
  const Mesh m = MakeProceduralRock(4, 120, 5000);
  std::map<std::pair<int, int>, int> edge_face;
  for (int f = 0; f < static_cast<int>(m.faces.size()); ++f)
    for (int k = 0; k < 3; ++k) edge_face[{m.faces[f][k], m.faces[f][(k + 1) % 3]}] = f;
  int concave = 0;
  for (int f = 0; f < static_cast<int>(m.faces.size()); ++f) {
    const auto& t = m.faces[f];
    const Vec3 a = ToVec3(m.vertices[t[0]]);
    const Vec3 n = Normalized(Cross(ToVec3(m.vertices[t[1]]) - a, ToVec3(m.vertices[t[2]]) - a));
    const int g = edge_face[{t[1], t[0]}];
    for (int v : m.faces[g]) {
      if (Dot(ToVec3(m.vertices[v]) - a, n) > 0.05) ++concave;
    }
  }
  EXPECT_GT(concave, 10);
}

TEST(ProceduralRock, DeterministicPerSeed) {
  const Mesh a = MakeProceduralRock(11, 0, 3000), b = MakeProceduralRock(11, 0, 3000);
  ASSERT_EQ(a.vertices.size(), b.vertices.size());
  EXPECT_EQ(a.vertices, b.vertices);
  EXPECT_EQ(a.faces, b.faces);
  const Mesh c = MakeProceduralRock(12, 0, 3000);
  EXPECT_NE(a.vertices, c.vertices);
}

Config TestConfig(uint64_t seed) {
  Config c;
  c.sim.seed = seed;
  c.sim.rock_size_mm = 120.0;
  c.camera.width = 640;
  c.camera.height = 480;
  return c;
}

TEST(SimWorld, RestPosesTouchTheDiscAndAreStable) {
  for (uint64_t seed : {1u, 2u, 5u}) {
    const SimWorld w(TestConfig(seed), {.rock_faces = 8000});
    ASSERT_GE(w.num_poses(), 2);
    for (int side = 1; side <= 2; ++side) {
      const RestPose& pose = w.pose(side);
      double zmin = 1e300;
      std::vector<Vec3> pts;
      for (const auto& v : w.rock().vertices) {
        pts.push_back(pose.rock_to_turntable.Apply(ToVec3(v)));
        zmin = std::min(zmin, pts.back().z);
      }
      EXPECT_NEAR(zmin, 0.0, 1e-9) << "seed " << seed << " side " << side;
      // Resting: the centre of mass projects inside the contact points' hull.
      const Vec3 com = pose.rock_to_turntable.Apply(w.center_of_mass());
      std::vector<Vec3> contact;
      for (const Vec3& p : pts)
        if (p.z < 0.1) contact.push_back(p);
      ASSERT_GE(contact.size(), 3u);
      // COM inside the 2D hull <=> no direction separates it from all contact points.
      bool inside = true;
      for (int i = 0; i < 360 && inside; ++i) {
        const double a = i * M_PI / 180.0;
        const double dx = std::cos(a), dy = std::sin(a);
        double best = -1e300;
        for (const Vec3& p : contact)
          best = std::max(best, (p.x - com.x) * dx + (p.y - com.y) * dy);
        inside = best > 0;
      }
      EXPECT_TRUE(inside) << "seed " << seed << " side " << side;
      EXPECT_LE(std::hypot(com.x, com.y), 10.0 + 1e-9);
      EXPECT_GT(com.z, 0.0);
    }
    // Side 2 is the rock flipped.
    EXPECT_LT(Dot(w.pose(1).down_rock, w.pose(2).down_rock), 0.0);
  }
}

TEST(SimWorld, ObjectMarkersOnOppositeSides) {
  const SimWorld w(TestConfig(7), {.rock_faces = 8000});
  ASSERT_EQ(w.object_markers().size(), 2u);
  const ObjectMarker& p = w.object_markers()[0];
  const ObjectMarker& r = w.object_markers()[1];
  EXPECT_EQ(p.color, "purple");
  EXPECT_EQ(r.color, "red");
  EXPECT_LT(Dot(p.origin - w.center_of_mass(), r.origin - w.center_of_mass()), 0.0);
  for (const ObjectMarker& m : w.object_markers()) {
    // Head to tail: gap + half of each segment apart, along the axis.
    const double expected = m.head_mm / 2 + m.gap_mm + m.tail_mm / 2;
    EXPECT_NEAR(Norm(m.tail - m.head), expected, 4.0);
    EXPECT_GT(Dot(m.tail - m.head, m.axis), 0.0);
    // The marker sits on the side: its normal roughly horizontal when resting.
    const Vec3 n_tt = w.pose(1).rock_to_turntable.Rotate(m.normal);
    EXPECT_LT(std::abs(n_tt.z), 0.7);
  }
}

TEST(SimWorld, CameraLooksAtTheTurntable) {
  const SimWorld w(TestConfig(1), {.rock_faces = 2000});
  const Intrinsics k = w.intrinsics();
  EXPECT_EQ(k.width, 640);
  EXPECT_NEAR(k.cx, 319.5, 1e-9);
  double u, v;
  ASSERT_TRUE(w.ProjectTurntablePoint({0, 0, kAimHeightMm}, 0, k, &u, &v));
  EXPECT_NEAR(u, k.cx, 1e-6);
  EXPECT_NEAR(v, k.cy, 1e-6);
  // The red label (+x) is right of centre; after 90 degrees it is behind (+y, up in the image).
  ASSERT_TRUE(w.ProjectTurntablePoint({120, 0, 0}, 0, k, &u, &v));
  EXPECT_GT(u, k.cx + 50);
  double u90, v90;
  ASSERT_TRUE(w.ProjectTurntablePoint({120, 0, 0}, 90, k, &u90, &v90));
  EXPECT_NEAR(u90, k.cx, 1.0);
  EXPECT_LT(v90, v);
  // Rock -> camera is the composition of the published transforms.
  const Rigid a = w.RockToCamera(2, 33.0);
  const Rigid b = w.world_to_camera() * Rigid::RotZ(33.0) * w.pose(2).rock_to_turntable;
  const Vec3 p{10, -20, 5};
  EXPECT_LT(Norm(a.Apply(p) - b.Apply(p)), 1e-9);
}

TEST(SimWorld, LoadsTheRockFromAMeshFile) {
  const Mesh m = MakeProceduralRock(21, 90.0, 3000);
  const std::string path = ::testing::TempDir() + "/sim_world_rock.ply";
  Status saved = SaveMeshPly(m, path);
  if (!saved.ok()) GTEST_SKIP() << "cannot write a PLY here: " << saved.error().ToString();
  Config c;
  c.sim.rock_mesh = path;
  c.sim.rock_unit = "cm";  // the file is read as centimetres: ten times larger
  Result<std::shared_ptr<SimWorld>> w = SimWorld::Create(c);
  ASSERT_TRUE(w.ok()) << w.error().ToString();
  ASSERT_EQ((*w)->rock().vertices.size(), m.vertices.size());
  EXPECT_NEAR((*w)->rock().vertices[7][0], 10.0 * m.vertices[7][0], 1e-3);
  EXPECT_GE((*w)->num_poses(), 2);
  c.sim.rock_mesh = ::testing::TempDir() + "/does_not_exist.ply";
  Result<std::shared_ptr<SimWorld>> bad = SimWorld::Create(c);
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.error().cls, ErrorClass::kInvalidConfig);
}

}  // namespace
}  // namespace aggscan::sim
