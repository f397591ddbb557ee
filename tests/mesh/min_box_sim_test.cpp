// The minimum-volume box on the sim's procedural rocks against a brute-force
// search (every direction of a dense sphere grid as a box axis, the exact
// minimum-area rectangle of the projection for the other two): rounded rocks
// have several nearly equal local minima, and a box that settles in the wrong
// one swaps b and c by 10-20 % (validate found seeds 6, 10 and 17).
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "common/mesh_props.h"
#include "config/config.h"
#include "drivers/sim/world.h"

namespace aggscan {
namespace {

double Dot(const Vec3d& a, const Vec3d& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
Vec3d Cross(const Vec3d& a, const Vec3d& b) {
  return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
Vec3d Normalized(const Vec3d& a) {
  const double n = std::sqrt(Dot(a, a));
  return {a[0] / n, a[1] / n, a[2] / n};
}

// Smallest box over n_dirs axis directions (Fibonacci sphere, one hemisphere).
double BruteForceBoxVolume(const std::vector<Vec3d>& pts, int n_dirs, std::array<double, 3>* dims) {
  double best = 1e300;
  const double golden = M_PI * (3.0 - std::sqrt(5.0));
  for (int i = 0; i < n_dirs; ++i) {
    const double z = 1.0 - (i + 0.5) / n_dirs;  // (0, 1]: one hemisphere
    const double r = std::sqrt(1 - z * z), th = golden * i;
    const Vec3d n{r * std::cos(th), r * std::sin(th), z};
    // Two axes perpendicular to n.
    Vec3d u = std::fabs(n[0]) < 0.9 ? Vec3d{1, 0, 0} : Vec3d{0, 1, 0};
    u = Normalized(Cross(n, u));
    const Vec3d v = Cross(n, u);
    std::vector<std::array<double, 2>> p2;
    double lo = 1e300, hi = -1e300;
    for (const Vec3d& p : pts) {
      p2.push_back({Dot(p, u), Dot(p, v)});
      const double h = Dot(p, n);
      lo = std::min(lo, h), hi = std::max(hi, h);
    }
    std::array<double, 2> dir{}, low{};
    double w = 0, h = 0;
    const double area = MinAreaRect(p2, &dir, &w, &h, &low);
    if (area * (hi - lo) < best) {
      best = area * (hi - lo);
      *dims = {w, h, hi - lo};
    }
  }
  std::sort(dims->begin(), dims->end());
  return best;
}

TEST(MinBoxSim, WithinHalfAPercentOfBruteForceOnSimRocks) {
  for (uint64_t seed : {6, 10, 17}) {
    Config cfg;
    cfg.sim.seed = seed;
    auto world = sim::SimWorld::Create(cfg);
    ASSERT_TRUE(world.ok());
    const Mesh& rock = (*world)->rock();
    Mesh hull;
    ASSERT_TRUE(ConvexHull(rock.vertices, &hull));
    std::array<double, 3> bf{};
    const double v_bf = BruteForceBoxVolume(hull.vertices, 6000, &bf);
    const OrientedBox box = MinVolumeBox(rock.vertices);
    std::array<double, 3> d{box.size[0], box.size[1], box.size[2]};
    std::sort(d.begin(), d.end());
    std::printf(
        "seed %llu: MinVolumeBox %.1f x %.1f x %.1f = %.0f mm3; brute force %.1f x %.1f x %.1f = "
        "%.0f mm3 "
        "(%+.2f %%)\n",
        static_cast<unsigned long long>(seed), d[0], d[1], d[2], box.Volume(), bf[0], bf[1], bf[2],
        v_bf, 100 * (box.Volume() / v_bf - 1));
    EXPECT_LT(box.Volume(), v_bf * 1.005);
  }
}

// Seed 17 has two boxes 0.16 % apart in volume, 77.9 x 108.4 x 155.4 and
// 82.6 x 118.9 x 133.6 mm: a, b, c swing by 10-15 % on a change of the
// surface far below any reconstruction's error. ComputeMeshProps reports the
// second box and every other box within 1 %, so that a user (and validate)
// can tell an ill-conditioned a, b, c from a wrong one. Seed 3 has no second
// box within 1 %.
TEST(MinBoxSim, ReportsTheSecondBoxOfAnIllConditionedRock) {
  for (uint64_t seed : {17, 3}) {
    Config cfg;
    cfg.sim.seed = seed;
    auto world = sim::SimWorld::Create(cfg);
    ASSERT_TRUE(world.ok());
    const MeshProps p = ComputeMeshProps((*world)->rock());
    std::printf(
        "seed %llu: box %.1f x %.1f x %.1f; second box %.1f x %.1f x %.1f at %+.2f %% volume\n",
        static_cast<unsigned long long>(seed), p.a_mm, p.b_mm, p.c_mm, p.second_a_mm, p.second_b_mm,
        p.second_c_mm, 100 * (p.second_box_volume_ratio - 1));
    if (seed == 17) {
      ASSERT_GT(p.second_box_volume_ratio, 1.0);
      EXPECT_LT(p.second_box_volume_ratio, 1.005);
      EXPECT_GT(std::fabs(p.second_c_mm / p.c_mm - 1), 0.1);  // 133.6 against 155.4
      // Every box within 1 % is listed, the second first, each distinct. The
      // spread search also finds 77.8 x 126.4 x 134.2 at +0.64 %, in a basin
      // no hull face points into: the face-normal starts alone listed one.
      ASSERT_GE(p.near_boxes.size(), 2u);
      EXPECT_EQ(p.near_boxes.front().c_mm, p.second_c_mm);
      for (const MeshProps::NearBox& b : p.near_boxes) {
        std::printf("  near box %.1f x %.1f x %.1f at %+.2f %%\n", b.a_mm, b.b_mm, b.c_mm,
                    100 * (b.volume_ratio - 1));
        EXPECT_LE(b.volume_ratio, 1 + kBoxAmbiguousVolume);
        EXPECT_GT(std::max({std::fabs(b.a_mm / p.a_mm - 1), std::fabs(b.b_mm / p.b_mm - 1),
                            std::fabs(b.c_mm / p.c_mm - 1)}),
                  kBoxDistinct);
      }
      EXPECT_TRUE(MeshPropsJson(p)["near_minimal_boxes"].is_array());
      EXPECT_EQ(MeshPropsJson(p)["near_minimal_boxes"].size(), p.near_boxes.size());
    } else {
      EXPECT_TRUE(p.second_box_volume_ratio == 0 || p.second_box_volume_ratio > 1.01)
          << p.second_box_volume_ratio;
      EXPECT_TRUE(p.near_boxes.empty());
    }
    if (p.second_box_volume_ratio > 0) {
      for (double side : {p.second_a_mm, p.second_b_mm, p.second_c_mm}) EXPECT_GT(side, 0);
    }
    EXPECT_LE(p.a_mm, p.b_mm);
    EXPECT_LE(p.b_mm, p.c_mm);
  }
}

}  // namespace
}  // namespace aggscan
