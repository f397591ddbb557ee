#include "pipeline/surface/visual_hull.h"

#include <gtest/gtest.h>

#include <cmath>

#include "common/mesh_check.h"
#include "common/mesh_props.h"
#include "config/config.h"
#include "drivers/sim/render.h"
#include "drivers/sim/world.h"

namespace aggscan {
namespace {

Eigen::Isometry3d ToIso(const std::array<double, 16>& m) {
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) T.linear()(r, c) = m[r * 4 + c];
    T.translation()(r) = m[r * 4 + 3];
  }
  return T;
}

Eigen::Isometry3d ToIso(const sim::Rigid& r) { return ToIso(r.Matrix4()); }

CameraModel Pinhole(int w, int h, double f) {
  CameraModel c;
  c.width = w;
  c.height = h;
  c.fx = c.fy = f;
  c.cx = (w - 1) / 2.0;
  c.cy = (h - 1) / 2.0;
  return c;
}

// A camera at distance d and elevation el looking at the origin, azimuth az.
Eigen::Isometry3d LookAt(double az_deg, double el_deg, double d) {
  const double az = az_deg * M_PI / 180, el = el_deg * M_PI / 180;
  const Eigen::Vector3d C(d * std::cos(el) * std::cos(az), d * std::cos(el) * std::sin(az),
                          d * std::sin(el));
  const Eigen::Vector3d z = (-C).normalized();
  const Eigen::Vector3d x = z.cross(Eigen::Vector3d::UnitZ()).normalized();
  const Eigen::Vector3d y = z.cross(x);
  Eigen::Matrix3d R;
  R.row(0) = x;
  R.row(1) = y;
  R.row(2) = z;
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = R;
  T.translation() = -R * C;
  return T;
}

// Exact silhouette of a sphere (centre c, radius r): pixels whose ray passes
// within r of the centre.
cv::Mat SphereMask(const CameraModel& cam, const Eigen::Isometry3d& T, const Eigen::Vector3d& c,
                   double r) {
  cv::Mat m(cam.height, cam.width, CV_8UC1);
  const Eigen::Vector3d cc = T * c;
  for (int y = 0; y < cam.height; ++y) {
    for (int x = 0; x < cam.width; ++x) {
      const Eigen::Vector3d ray =
          Eigen::Vector3d((x - cam.cx) / cam.fx, (y - cam.cy) / cam.fy, 1).normalized();
      const double along = ray.dot(cc);
      const double dist2 = cc.squaredNorm() - along * along;
      m.at<uint8_t>(y, x) = (along > 0 && dist2 <= r * r) ? 255 : 0;
    }
  }
  return m;
}

TEST(VisualHull, SphereFromTwoRingsIsClosedAndNearlyExact) {
  const CameraModel cam = Pinhole(640, 480, 900);
  const double r = 50;
  std::vector<SilhouetteView> views;
  for (int i = 0; i < 30; ++i) {
    for (double el : {35.0, -35.0}) {
      SilhouetteView v;
      v.camera = cam;
      v.cam_from_object = LookAt(i * 12.0 + (el < 0 ? 6 : 0), el, 600);
      v.mask = SphereMask(cam, v.cam_from_object, Eigen::Vector3d::Zero(), r);
      views.push_back(std::move(v));
    }
  }
  const Eigen::AlignedBox3d box(Eigen::Vector3d(-150, -150, -150), Eigen::Vector3d(150, 150, 150));
  auto res = CarveVisualHull(views, {}, box);
  ASSERT_TRUE(res) << res.error().ToString();
  EXPECT_TRUE(CheckClosedManifold(res->mesh, "hull"))
      << CheckClosedManifold(res->mesh, "hull").error().ToString();
  const MeshProps p = ComputeMeshProps(res->mesh);
  const double v_true = 4.0 / 3 * M_PI * r * r * r;
  const double a_true = 4 * M_PI * r * r;
  // A visual hull can only be larger than the object; 60 cones 12 deg apart
  // leave a thin excess shell.
  EXPECT_GT(p.volume_mm3, v_true * 0.995);
  EXPECT_LT(p.volume_mm3, v_true * 1.02);
  EXPECT_NEAR(p.surface_area_mm2 / a_true, 1.0, 0.02);
  EXPECT_NEAR(p.c_mm, 2 * r, 2 * r * 0.02);
  EXPECT_NEAR(p.a_mm, 2 * r, 2 * r * 0.02);
  // Face count follows the target.
  EXPECT_GT(res->mesh.faces.size(), 50000u);
  EXPECT_LT(res->mesh.faces.size(), 200000u);
  std::printf("sphere: V %.4f%%  A %.4f%%  faces %zu  voxel %.3f mm  %.2f s\n",
              100 * (p.volume_mm3 / v_true - 1), 100 * (p.surface_area_mm2 / a_true - 1),
              res->mesh.faces.size(), res->voxel_mm, res->seconds);
}

TEST(VisualHull, FloorCutsTheHull) {
  // Cameras only from above: the floor z >= 0 bounds the bottom, giving a
  // hemisphere-capped cylinder-like hull; with the floor at the centre the
  // result is at most the upper half of the hull.
  const CameraModel cam = Pinhole(640, 480, 900);
  std::vector<SilhouetteView> views;
  for (int i = 0; i < 30; ++i) {
    SilhouetteView v;
    v.camera = cam;
    v.cam_from_object = LookAt(i * 12.0, 35, 600);
    v.mask = SphereMask(cam, v.cam_from_object, Eigen::Vector3d::Zero(), 50);
    views.push_back(std::move(v));
  }
  const Eigen::AlignedBox3d box(Eigen::Vector3d(-150, -150, -150), Eigen::Vector3d(150, 150, 150));
  auto res = CarveVisualHull(views, {HalfSpace{Eigen::Vector3d::UnitZ(), 0.0}}, box);
  ASSERT_TRUE(res) << res.error().ToString();
  EXPECT_TRUE(CheckClosedManifold(res->mesh, "hull"));
  EXPECT_NEAR(res->box.min().z(), 0.0, 0.05);
  EXPECT_GT(res->box.max().z(), 49.0);
}

TEST(VisualHull, RefusesDisjointSilhouettesAndBadMasks) {
  const CameraModel cam = Pinhole(320, 240, 450);
  std::vector<SilhouetteView> views;
  for (int i = 0; i < 2; ++i) {
    SilhouetteView v;
    v.camera = cam;
    v.cam_from_object = LookAt(0, 30, 600);
    // The same camera sees a sphere at two different places (poses that do not
    // belong to the masks): the two cones have no common volume.
    v.mask = SphereMask(cam, v.cam_from_object, Eigen::Vector3d(0, i ? -80 : 80, 0), 20);
    views.push_back(std::move(v));
  }
  const Eigen::AlignedBox3d box(Eigen::Vector3d(-150, -150, -150), Eigen::Vector3d(150, 150, 150));
  auto res = CarveVisualHull(views, {}, box);
  ASSERT_FALSE(res);
  EXPECT_NE(res.error().message.find("no common volume"), std::string::npos) << res.error().message;

  views[0].mask = cv::Mat(10, 10, CV_8UC1, cv::Scalar(255));
  res = CarveVisualHull(views, {}, box);
  ASSERT_FALSE(res);
  EXPECT_NE(res.error().message.find("mask of view 0"), std::string::npos);

  // A mask that is all rock: the hull fills the search box.
  views[0].mask = cv::Mat(cam.height, cam.width, CV_8UC1, cv::Scalar(255));
  views[1].mask = cv::Mat(cam.height, cam.width, CV_8UC1, cv::Scalar(255));
  res = CarveVisualHull(
      views, {}, Eigen::AlignedBox3d(Eigen::Vector3d(-20, -20, -20), Eigen::Vector3d(20, 20, 20)));
  ASSERT_FALSE(res);
  EXPECT_NE(res.error().message.find("edge of the search region"), std::string::npos);
}

// The sim rock seen from both sides with ground-truth masks and poses: the
// hull's volume is the rock's plus what no silhouette can see (dents).
TEST(VisualHull, SimRockBothSidesWithTruthMasks) {
  Config config;
  config.sim.seed = 4;
  config.camera.width = 1008;
  config.camera.height = 756;
  sim::SimWorld world(config);
  sim::Renderer renderer(world, 1008, 756);
  const RigCalibration cal = world.TruthCalibration(1008, 756);
  const Eigen::Isometry3d rock_to_t1 = ToIso(world.pose(1).rock_to_turntable);
  std::vector<SilhouetteView> views;
  std::vector<HalfSpace> floors;
  for (int side = 1; side <= 2; ++side) {
    // object frame = side-1 table frame; table_s <- table_1
    const Eigen::Isometry3d ts_from_t1 =
        ToIso(world.pose(side).rock_to_turntable) * rock_to_t1.inverse();
    HalfSpace floor;
    floor.normal = ts_from_t1.linear().row(2).transpose();
    floor.offset = ts_from_t1.translation().z();
    floors.push_back(floor);
    for (int i = 0; i < 30; ++i) {
      const double angle = i * 12.0;
      sim::RenderOptions o;
      o.want_mask = true;
      o.noise_seed = i;
      const sim::RenderedImage img = renderer.Render(side, angle, o);
      SilhouetteView v;
      v.camera = cal.camera;
      v.mask =
          cv::Mat(img.height, img.width, CV_8UC1, const_cast<uint8_t*>(img.mask.data())).clone();
      v.cam_from_object = ToIso(cal.CamFromTable(angle)) * ts_from_t1;
      views.push_back(std::move(v));
    }
  }
  const double R = config.rig.turntable_diameter_mm / 2;
  const Eigen::AlignedBox3d box(Eigen::Vector3d(-R, -R, -5), Eigen::Vector3d(R, R, 300));
  auto res = CarveVisualHull(views, floors, box);
  ASSERT_TRUE(res) << res.error().ToString();
  ASSERT_TRUE(CheckClosedManifold(res->mesh, "hull"));
  const MeshProps got = ComputeMeshProps(res->mesh);
  const MeshProps truth = ComputeMeshProps(world.rock());
  const double dv = got.volume_mm3 / truth.volume_mm3 - 1;
  std::printf(
      "sim rock seed 4: V %.0f vs %.0f (%+.2f%%), A %+.2f%%, a %+.2f%% b %+.2f%% c %+.2f%%, faces "
      "%zu, "
      "voxel %.2f mm, %.2f s\n",
      got.volume_mm3, truth.volume_mm3, 100 * dv,
      100 * (got.surface_area_mm2 / truth.surface_area_mm2 - 1), 100 * (got.a_mm / truth.a_mm - 1),
      100 * (got.b_mm / truth.b_mm - 1), 100 * (got.c_mm / truth.c_mm - 1), res->mesh.faces.size(),
      res->voxel_mm, res->seconds);
  EXPECT_GT(dv, -0.01);
  EXPECT_LT(dv, 0.05);
  EXPECT_NEAR(got.c_mm / truth.c_mm, 1.0, 0.02);
  EXPECT_NEAR(got.b_mm / truth.b_mm, 1.0, 0.02);
  EXPECT_NEAR(got.a_mm / truth.a_mm, 1.0, 0.03);
}

}  // namespace
}  // namespace aggscan
