// The COLMAP SfM module without running COLMAP: camera conversion, the text
// model reader/writer, the similarity, the plausibility checks on synthetic
// good and deliberately wrong models, and the runner's errors with a missing
// or failing colmap binary.
#include "pipeline/sfm/colmap_sfm.h"

#include <gtest/gtest.h>
#include <sys/stat.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <random>
#include <set>

#include "common/fsutil.h"
#include "pipeline/sfm/sfm_poses.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

constexpr double kPi = 3.14159265358979323846;

CameraModel TestCamera() {
  CameraModel c;
  c.width = 640;
  c.height = 480;
  c.fx = c.fy = 800;
  c.cx = 319.5;
  c.cy = 239.5;
  return c;
}

// A camera at `centre` looking at `target`, world z up (OpenCV camera axes).
void LookAt(const Eigen::Vector3d& centre, const Eigen::Vector3d& target, SfmImage* im) {
  const Eigen::Vector3d z = (target - centre).normalized();
  const Eigen::Vector3d x = z.cross(Eigen::Vector3d::UnitZ()).normalized();
  const Eigen::Vector3d y = z.cross(x);
  im->R_cam_world.row(0) = x;
  im->R_cam_world.row(1) = y;
  im->R_cam_world.row(2) = z;
  im->t_cam_world = -im->R_cam_world * centre;
}

// A turntable ring: n cameras on a circle of radius 1 at height 0.6, every
// `step_deg`, looking at the object (points in a ball of radius 0.15 at the
// origin); observations are exact projections.
SfmModel RingModel(int n = 24, double step_deg = 15, int npts = 300, unsigned seed = 1) {
  SfmModel m;
  SfmCamera cam = ColmapCameraFromOpenCv(TestCamera());
  m.cameras.push_back(cam);
  for (int i = 0; i < n; ++i) {
    SfmImage im;
    im.id = i + 1;
    im.camera_id = 1;
    im.input_index = i;
    char name[32];
    std::snprintf(name, sizeof name, "view_%03d.jpg", i);
    im.name = name;
    const double a = i * step_deg * kPi / 180;
    LookAt(Eigen::Vector3d(std::cos(a), std::sin(a), 0.6), Eigen::Vector3d::Zero(), &im);
    m.images.push_back(im);
  }
  std::mt19937 rng(seed);
  std::uniform_real_distribution<double> u(-0.15, 0.15);
  for (int k = 0; k < npts; ++k) {
    SfmPoint p;
    p.id = k + 1;
    p.xyz = Eigen::Vector3d(u(rng), u(rng), u(rng));
    p.rgb = {200, 100, 50};
    for (auto& im : m.images) {
      Eigen::Vector2d px;
      if (!ProjectColmap(cam, im.R_cam_world * p.xyz + im.t_cam_world, &px)) continue;
      if ((im.id + k) % 3 == 0) continue;  // partial tracks
      p.track.push_back({im.id, static_cast<int>(im.points2d.size())});
      im.points2d.push_back(px);
      im.point3d_ids.push_back(p.id);
    }
    m.points.push_back(p);
  }
  // An untriangulated keypoint, as COLMAP writes them (POINT3D_ID -1).
  m.images[0].points2d.emplace_back(10.5, 20.5);
  m.images[0].point3d_ids.push_back(-1);
  return m;
}

// Recomputes every observation from the model itself (a self-consistent,
// possibly wrong model, as a bundle adjustment would leave it).
void Reproject(SfmModel* m) {
  for (const auto& p : m->points) {
    for (const auto& t : p.track) {
      SfmImage& im = m->images[t.image_id - 1];
      Eigen::Vector2d px;
      if (ProjectColmap(m->cameras[0], im.R_cam_world * p.xyz + im.t_cam_world, &px))
        im.points2d[t.point2d_idx] = px;
    }
  }
}

SfmExpectations RingExpect(int n, const CameraModel* fixed = nullptr) {
  SfmExpectations e;
  e.num_input_images = n;
  e.ring = true;
  if (fixed) e.fixed_camera = *fixed;
  return e;
}

void ExpectFails(const SfmCheckReport& r, const std::string& name) {
  const SfmCheck* c = r.Find(name);
  ASSERT_NE(c, nullptr) << name;
  EXPECT_TRUE(c->applicable) << name;
  EXPECT_FALSE(c->passed) << name << ": " << c->detail;
  EXPECT_FALSE(r.ok());
  const Error e = r.ToError();
  EXPECT_EQ(e.cls, ErrorClass::kCorrupt);
  EXPECT_NE(e.message.find("SfM model rejected"), std::string::npos);
  EXPECT_NE(e.detail.find(name), std::string::npos) << e.detail;
}

// ------------------------------------------------------------------ cameras

TEST(ColmapCamera, ChoosesTheSmallestExactModel) {
  CameraModel c = TestCamera();
  EXPECT_EQ(ColmapCameraFromOpenCv(c).model, "PINHOLE");
  c.k1 = -0.1;
  c.k2 = 0.02;
  EXPECT_EQ(ColmapCameraFromOpenCv(c).model, "RADIAL");
  c.fy = 801;
  EXPECT_EQ(ColmapCameraFromOpenCv(c).model, "OPENCV");
  c.fy = 800;
  c.p1 = 1e-3;
  EXPECT_EQ(ColmapCameraFromOpenCv(c).model, "OPENCV");
  c.k3 = 0.001;
  EXPECT_EQ(ColmapCameraFromOpenCv(c).model, "FULL_OPENCV");
}

// COLMAP puts pixel centres at +0.5, OpenCV at integers: a point projects to
// the same pixel up to that shift, for every lens model.
TEST(ColmapCamera, ProjectionMatchesOpenCvLensModelWithHalfPixelShift) {
  std::vector<CameraModel> cams(4, TestCamera());
  cams[1].k1 = -0.12;
  cams[1].k2 = 0.03;
  cams[2].k1 = -0.12;
  cams[2].k2 = 0.03;
  cams[2].p1 = 0.001;
  cams[2].p2 = -0.002;
  cams[2].fy = 805;
  cams[3] = cams[2];
  cams[3].k3 = 0.01;
  for (const auto& c : cams) {
    const SfmCamera sc = ColmapCameraFromOpenCv(c);
    for (const auto& p : {Eigen::Vector3d(0.1, -0.05, 1), Eigen::Vector3d(-0.3, 0.2, 1.5),
                          Eigen::Vector3d(0, 0, 2)}) {
      double u, v;
      ASSERT_TRUE(c.Project({p.x(), p.y(), p.z()}, &u, &v));
      Eigen::Vector2d px;
      ASSERT_TRUE(ProjectColmap(sc, p, &px)) << sc.model;
      EXPECT_NEAR(px.x(), u + 0.5, 1e-9) << sc.model;
      EXPECT_NEAR(px.y(), v + 0.5, 1e-9) << sc.model;
    }
    auto back = OpenCvCameraFromColmap(sc);
    ASSERT_TRUE(back.ok());
    EXPECT_DOUBLE_EQ(back->cx, c.cx);
    EXPECT_DOUBLE_EQ(back->fy, c.fy);
    EXPECT_DOUBLE_EQ(back->k3, c.k3);
    EXPECT_DOUBLE_EQ(back->p2, c.p2);
  }
  Eigen::Vector2d px;
  EXPECT_FALSE(ProjectColmap(ColmapCameraFromOpenCv(cams[0]), Eigen::Vector3d(0, 0, -1), &px));
  SfmCamera fisheye{1, "OPENCV_FISHEYE", 640, 480, {800, 800, 320, 240, 0, 0, 0, 0}};
  EXPECT_FALSE(OpenCvCameraFromColmap(fisheye).ok());
}

// The focal hint of a rig without calibration: the config's lens (focal over
// sensor width, times the image width) over the sim's nominal lens; a real
// camera without a lens in its config has none.
TEST(FocalHint, FromTheConfigsLensElseTheSimsElseNone) {
  Config c;  // sim camera, hfov 40 deg
  auto h = FocalHintFromConfig(c, 2016);
  ASSERT_TRUE(h);
  EXPECT_NEAR(h->focal_px, 1008.0 / std::tan(20.0 * M_PI / 180), 1e-9);
  EXPECT_NE(h->source.find("sim.hfov_deg 40"), std::string::npos) << h->source;
  c.camera.lens_focal_mm = 6.0;
  c.camera.sensor_width_mm = 6.287;
  h = FocalHintFromConfig(c, 4056);
  ASSERT_TRUE(h);
  EXPECT_NEAR(h->focal_px, 6.0 / 6.287 * 4056, 1e-9);
  EXPECT_NE(h->source.find("camera.lens_focal_mm 6 / camera.sensor_width_mm 6.287"),
            std::string::npos)
      << h->source;
  c.camera.backend = "v4l2";
  EXPECT_TRUE(FocalHintFromConfig(c, 4056));
  c.camera.lens_focal_mm = 0;
  c.camera.sensor_width_mm = 0;
  EXPECT_FALSE(FocalHintFromConfig(c, 4056));
  EXPECT_FALSE(FocalHintFromConfig(Config{}, 0));
}

TEST(CircularPairs, EachUnorderedPairOnce) {
  auto p = CircularPairs(36, 3);
  EXPECT_EQ(p.size(), 108u);
  std::set<std::pair<int, int>> s;
  for (auto [i, j] : p) {
    EXPECT_TRUE(s.insert({std::min(i, j), std::max(i, j)}).second);
    const int d = (j - i + 36) % 36;
    EXPECT_TRUE(d >= 1 && d <= 3);
  }
  EXPECT_EQ(CircularPairs(4, 3).size(), 6u);  // all pairs of 4, none twice
  EXPECT_EQ(CircularPairs(6, 3).size(), 15u);
}

TEST(AnglePairs, FollowTheTurntableAngles) {
  auto normalized = [](std::vector<std::pair<int, int>> p) {
    for (auto& [i, j] : p) {
      if (i > j) std::swap(i, j);
    }
    std::sort(p.begin(), p.end());
    return p;
  };
  // One turn of 12 views at 30 deg (with encoder noise): the circular list.
  std::vector<double> one;
  for (int i = 0; i < 12; ++i) one.push_back(30.0 * i + (i % 2 ? 0.07 : -0.05));
  EXPECT_EQ(normalized(AnglePairs(one, 3)), normalized(CircularPairs(12, 3)));
  // The paper profile: 30 views at 30 deg go round 2.5 times. Views of one
  // angle on different turns are paired (0, 12, 24), views 4 steps apart are not.
  std::vector<double> paper;
  for (int i = 0; i < 30; ++i) paper.push_back(std::fmod(30.0 * i, 360.0) + 0.02 * i);
  const auto p = AnglePairs(paper, 3);
  const std::set<std::pair<int, int>> s(p.begin(), p.end());
  EXPECT_EQ(s.size(), p.size());
  EXPECT_TRUE(s.count({0, 12}) && s.count({0, 24}) && s.count({12, 24}));
  EXPECT_TRUE(s.count({0, 1}) && s.count({0, 3}) && s.count({0, 11}) && s.count({2, 27}));
  EXPECT_FALSE(s.count({0, 4}) || s.count({0, 16}) || s.count({0, 8}));
  for (auto [i, j] : p) {
    EXPECT_LT(i, j);
    EXPECT_LE(std::abs(std::remainder(paper[j] - paper[i], 360.0)), 105.0) << i << " " << j;
  }
  // No usable angles: empty (the caller falls back to capture order).
  EXPECT_TRUE(AnglePairs({}, 3).empty());
  EXPECT_TRUE(AnglePairs({0, 0, 0}, 3).empty());
  EXPECT_TRUE(AnglePairs({0, NAN, 60}, 3).empty());
}

// --------------------------------------------------------------- text model

TEST(ColmapTextModel, WriteReadRoundTrip) {
  test::TempDir tmp;
  const SfmModel m = RingModel();
  ASSERT_TRUE(WriteColmapTextModel(tmp.path() + "/m", m).ok());
  auto r = ReadColmapTextModel(tmp.path() + "/m");
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  ASSERT_EQ(r->images.size(), m.images.size());
  ASSERT_EQ(r->points.size(), m.points.size());
  ASSERT_EQ(r->cameras.size(), 1u);
  EXPECT_EQ(r->cameras[0].model, "PINHOLE");
  EXPECT_EQ(r->cameras[0].params, m.cameras[0].params);
  for (size_t i = 0; i < m.images.size(); ++i) {
    EXPECT_EQ(r->images[i].name, m.images[i].name);
    EXPECT_LT((r->images[i].R_cam_world - m.images[i].R_cam_world).norm(), 1e-12);
    EXPECT_LT((r->images[i].Centre() - m.images[i].Centre()).norm(), 1e-12);
    EXPECT_EQ(r->images[i].points2d.size(), m.images[i].points2d.size());
  }
  EXPECT_EQ(r->images[0].point3d_ids.back(), -1);
  EXPECT_EQ(r->points[7].track.size(), m.points[7].track.size());
  EXPECT_LT(MeanReprojectionErrorPx(*r), 1e-6);
}

TEST(ColmapTextModel, ImageWithoutObservationsAndBadLines) {
  test::TempDir tmp;
  const std::string d = tmp.path();
  auto write = [&](const std::string& f, const std::string& s) {
    ASSERT_TRUE(WriteFileAtomic(d + "/" + f, s).ok());
  };
  write("cameras.txt", "# c\n1 SIMPLE_RADIAL 720 576 3000 360 288 0.01\n");
  write("images.txt",
        "# i\n# j\n1 1 0 0 0 0 0 5 1 a.png\n\n2 1 0 0 0 1 0 5 1 b.png\n100 50 1 7 7 -1\n");
  write("points3D.txt", "1 0 0 0 255 255 255 0.5 2 0\n");
  auto r = ReadColmapTextModel(d);
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  ASSERT_EQ(r->images.size(), 2u);
  EXPECT_TRUE(r->images[0].points2d.empty());
  EXPECT_EQ(r->images[1].points2d.size(), 2u);
  EXPECT_DOUBLE_EQ(r->cameras[0].FocalPx(), 3000);

  write("points3D.txt", "1 0 0 0 255 255 255 0.5 9 0\n");
  auto bad = ReadColmapTextModel(d);
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(bad.error().message.find("points3D.txt line 1"), std::string::npos)
      << bad.error().message;

  write("cameras.txt", "1 PINHOLE 720 576 3000 360\n");
  EXPECT_EQ(ReadColmapTextModel(d).error().cls, ErrorClass::kCorrupt);
  EXPECT_EQ(ReadColmapTextModel(d + "/missing").error().cls, ErrorClass::kNotFound);
}

// --------------------------------------------------------------- similarity

TEST(Similarity, RecoversScaleRotationTranslation) {
  std::mt19937 rng(3);
  std::normal_distribution<double> g(0, 1);
  std::vector<Eigen::Vector3d> src, dst;
  const Eigen::Matrix3d R =
      Eigen::AngleAxisd(0.7, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix();
  const Eigen::Vector3d t(10, -4, 2);
  for (int i = 0; i < 20; ++i) {
    src.emplace_back(g(rng), g(rng), g(rng));
    dst.push_back(152.4 * R * src.back() + t);
  }
  double rms = -1;
  auto s = EstimateSimilarity(src, dst, true, &rms);
  ASSERT_TRUE(s.ok());
  EXPECT_NEAR(s->scale, 152.4, 1e-9);
  EXPECT_LT((s->R - R).norm(), 1e-12);
  EXPECT_LT((s->t - t).norm(), 1e-9);
  EXPECT_LT(rms, 1e-9);
  auto rigid = EstimateSimilarity(src, dst, false);
  ASSERT_TRUE(rigid.ok());
  EXPECT_EQ(rigid->scale, 1.0);

  // A mirrored target is fitted with a proper rotation, never a reflection.
  std::vector<Eigen::Vector3d> mirrored;
  for (const auto& p : dst) mirrored.emplace_back(-p.x(), p.y(), p.z());
  auto m = EstimateSimilarity(src, mirrored, true, &rms);
  ASSERT_TRUE(m.ok());
  EXPECT_NEAR(m->R.determinant(), 1.0, 1e-9);
  EXPECT_GT(rms, 1.0);
}

TEST(Similarity, DegenerateInputsRejected) {
  std::vector<Eigen::Vector3d> line = {{0, 0, 0}, {1, 1, 1}, {2, 2, 2}, {3, 3, 3}};
  EXPECT_EQ(EstimateSimilarity(line, line).error().cls, ErrorClass::kInvalidArgument);
  std::vector<Eigen::Vector3d> two = {{0, 0, 0}, {1, 0, 0}};
  EXPECT_FALSE(EstimateSimilarity(two, two).ok());
  std::vector<Eigen::Vector3d> three = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  EXPECT_FALSE(EstimateSimilarity(three, two).ok());
  EXPECT_TRUE(EstimateSimilarity(three, three).ok());  // a plane is enough
}

// A model moved into another frame keeps its projections; its centres move.
TEST(Similarity, ApplyToModelKeepsReprojection) {
  SfmModel m = RingModel();
  Similarity3 s;
  s.scale = 250;  // model units -> mm
  s.R = Eigen::AngleAxisd(1.1, Eigen::Vector3d(0.3, -1, 0.2).normalized()).toRotationMatrix();
  s.t = Eigen::Vector3d(5, 6, 7);
  const Eigen::Vector3d c0 = m.images[3].Centre();
  ApplySimilarity(s, &m);
  EXPECT_LT(MeanReprojectionErrorPx(m), 1e-6);
  EXPECT_LT((m.images[3].Centre() - s.Apply(c0)).norm(), 1e-9);
  EXPECT_NEAR(m.images[3].R_cam_world.determinant(), 1.0, 1e-12);
  auto report = CheckSfmModel(m, RingExpect(24));
  EXPECT_TRUE(report.ok()) << report.ToError().ToString();
}

// ------------------------------------------------------------- plausibility

TEST(SfmChecks, GoodRingPasses) {
  SfmModel m = RingModel();
  SfmExpectations e = RingExpect(24);
  for (int i = 0; i < 24; ++i)
    e.angles_deg.push_back(-15.0 * i);  // table turns the other way: sense is free
  auto r = CheckSfmModel(m, e);
  EXPECT_TRUE(r.ok()) << r.ToError().ToString();
  for (const char* n :
       {"registered_fraction", "point_count", "reprojection_error", "points_in_front", "ring_plane",
        "ring_circle", "ring_facing", "ring_direction", "ring_angles", "ring_points"}) {
    ASSERT_NE(r.Find(n), nullptr) << n;
    EXPECT_TRUE(r.Find(n)->applicable) << n;
    EXPECT_TRUE(r.Find(n)->passed) << n << ": " << r.Find(n)->detail;
  }
  EXPECT_FALSE(r.Find("focal_length")->applicable);
  const auto j = r.ToJson();
  EXPECT_TRUE(j["ok"].get<bool>());
  EXPECT_EQ(j["checks"].size(), r.checks.size());

  // Turntable turning the same way as the model's ring: passes as well.
  for (int i = 0; i < 24; ++i) e.angles_deg[i] = 15.0 * i + 40;
  EXPECT_TRUE(CheckSfmModel(m, e).ok()) << CheckSfmModel(m, e).ToError().ToString();

  // Not a ring capture: ring checks do not apply.
  auto free = CheckSfmModel(m, SfmExpectations{24, std::nullopt, std::nullopt, false, {}});
  EXPECT_TRUE(free.ok());
  EXPECT_FALSE(free.Find("ring_circle")->applicable);
}

TEST(SfmChecks, FixedIntrinsicsMustComeBackUnchanged) {
  SfmModel m = RingModel();
  const CameraModel cam = TestCamera();
  EXPECT_TRUE(CheckSfmModel(m, RingExpect(24, &cam)).ok());
  m.cameras[0].params[0] *= 1.01;
  ExpectFails(CheckSfmModel(m, RingExpect(24, &cam)), "fixed_intrinsics");
}

// The failure seen in the notes: a focal far from the truth. Here the model's
// focal is 0.3x the expected one.
TEST(SfmChecks, WrongFocalRejected) {
  SfmModel m = RingModel();
  m.cameras[0].params[0] *= 0.3;
  m.cameras[0].params[1] *= 0.3;
  Reproject(&m);
  SfmExpectations e = RingExpect(24);
  e.expected_focal_px = 800;
  auto r = CheckSfmModel(m, e);
  ExpectFails(r, "focal_length");
  EXPECT_EQ(r.FirstFailure()->name, "focal_length");
  EXPECT_NE(r.ToError().message.find("rig calibration"), std::string::npos) << r.ToError().message;
  EXPECT_NEAR(r.Find("focal_length")->value, 0.7, 1e-9);
}

TEST(SfmChecks, TooFewRegisteredRejected) {
  SfmModel m = RingModel();
  auto r = CheckSfmModel(m, RingExpect(36));  // 24 of 36
  ExpectFails(r, "registered_fraction");
  EXPECT_EQ(r.FirstFailure()->name, "registered_fraction");
  EXPECT_NE(r.ToError().message.find("24 of 36"), std::string::npos);
}

// Rotations off by a large angle (the notes: 117°) with plausible centres:
// the cameras no longer look at the turntable axis.
TEST(SfmChecks, RotationsOffRejected) {
  SfmModel m = RingModel();
  for (auto& im : m.images) {
    const Eigen::Vector3d c = im.Centre();
    im.R_cam_world =
        Eigen::AngleAxisd(117 * kPi / 180, Eigen::Vector3d::UnitY()).toRotationMatrix() *
        im.R_cam_world;
    im.t_cam_world = -im.R_cam_world * c;
  }
  ExpectFails(CheckSfmModel(m, RingExpect(24)), "ring_facing");
}

// Views shuffled: centres still on a circle, but the capture order jumps
// back and forth.
TEST(SfmChecks, ShuffledViewsRejected) {
  SfmModel m = RingModel();
  std::vector<int> perm(24);
  for (int i = 0; i < 24; ++i) perm[i] = i;
  std::mt19937 rng(5);
  std::shuffle(perm.begin(), perm.end(), rng);
  for (int i = 0; i < 24; ++i) m.images[i].input_index = perm[i];
  ExpectFails(CheckSfmModel(m, RingExpect(24)), "ring_direction");
}

// The turntable said 10° steps, the model has 15°.
TEST(SfmChecks, AnglesNotMatchingTheTurntableRejected) {
  SfmModel m = RingModel();
  SfmExpectations e = RingExpect(24);
  for (int i = 0; i < 24; ++i) e.angles_deg.push_back(10.0 * i);
  auto r = CheckSfmModel(m, e);
  ExpectFails(r, "ring_angles");
  EXPECT_TRUE(r.Find("ring_direction")->passed);
}

TEST(SfmChecks, CentresOffTheCircleRejected) {
  SfmModel m = RingModel();
  for (size_t i = 0; i < m.images.size(); i += 2) {  // every other camera pulled in by 40 %
    SfmImage& im = m.images[i];
    const Eigen::Vector3d c = im.Centre();
    LookAt(Eigen::Vector3d(0.6 * c.x(), 0.6 * c.y(), c.z()), Eigen::Vector3d::Zero(), &im);
  }
  ExpectFails(CheckSfmModel(m, RingExpect(24)), "ring_circle");
}

TEST(SfmChecks, PointsBehindCamerasAndBadReprojectionRejected) {
  SfmModel m = RingModel();
  for (auto& p : m.points) p.xyz *= -40;  // far outside, behind the far side's cameras
  auto r = CheckSfmModel(m, RingExpect(24));
  ExpectFails(r, "points_in_front");
  ExpectFails(r, "reprojection_error");
  ExpectFails(r, "ring_points");
}

// ------------------------------------------------------ runner error paths

class FakeColmap : public ::testing::Test {
 protected:
  void SetUp() override {
    // The smallest photo the image loader measures is 64 px a side.
    cv::Mat img(96, 128, CV_8UC3, cv::Scalar(90, 120, 150));
    for (int i = 0; i < 3; ++i) {
      images_.push_back(tmp_.path() + "/in/view_00" + std::to_string(i) + ".png");
      std::filesystem::create_directories(tmp_.path() + "/in");
      ASSERT_TRUE(cv::imwrite(images_.back(), img));
    }
  }
  std::string Script(const std::string& body) {
    const std::string p = tmp_.path() + "/fake-colmap";
    std::ofstream(p) << "#!/bin/sh\n" << body << "\n";
    ::chmod(p.c_str(), 0755);
    return p;
  }
  ColmapSfmOptions Options(const std::string& binary) {
    ColmapSfmOptions o;
    o.colmap_binary = binary;
    o.workspace = tmp_.path() + "/ws";
    o.images = images_;
    o.step_timeout_s = 20;
    return o;
  }
  test::TempDir tmp_;
  std::vector<std::string> images_;
};

TEST_F(FakeColmap, MissingBinaryIsNotFoundWithWhatToDo) {
  auto r = RunColmapSfm(Options(tmp_.path() + "/no/colmap"));
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kNotFound);
  EXPECT_NE(r.error().message.find("COLMAP not found"), std::string::npos) << r.error().message;
  EXPECT_NE(r.error().message.find("install"), std::string::npos);
}

TEST_F(FakeColmap, FailingStepNamesStepAndLog) {
  auto r = RunColmapSfm(Options(Script("echo 'F1122 something broke' >&2; exit 1")));
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kIo);
  EXPECT_NE(r.error().message.find("feature_extractor failed (exit 1)"), std::string::npos)
      << r.error().message;
  EXPECT_NE(r.error().message.find("logs/feature_extractor.log"), std::string::npos);
  EXPECT_NE(r.error().detail.find("something broke"), std::string::npos) << r.error().detail;
  // The flags that keep COLMAP off the GPU/OpenGL were passed.
  const std::string log = *ReadFile(tmp_.path() + "/ws/logs/feature_extractor.log");
  EXPECT_NE(log.find("--SiftExtraction.use_gpu 0"), std::string::npos);
}

// Exit 0 but nothing written: the silent failure mode of the notes.
TEST_F(FakeColmap, SilentSuccessWithoutOutputIsCaught) {
  auto r = RunColmapSfm(Options(Script("exit 0")));
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kCorrupt);
  EXPECT_NE(r.error().message.find("wrote no database"), std::string::npos) << r.error().message;
}

TEST_F(FakeColmap, CrashBySignalAndTimeout) {
  auto r = RunColmapSfm(Options(Script("kill -9 $$")));
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.error().message.find("signal 9"), std::string::npos) << r.error().message;
  EXPECT_NE(r.error().message.find("out of memory"), std::string::npos);
  auto o = Options(Script("sleep 30"));
  o.step_timeout_s = 0.3;
  auto t = RunColmapSfm(o);
  ASSERT_FALSE(t.ok());
  EXPECT_EQ(t.error().cls, ErrorClass::kTimeout);
  EXPECT_NE(t.error().message.find("feature_extractor"), std::string::npos);
}

TEST_F(FakeColmap, InvalidOptionsListEveryProblem) {
  auto o = Options("/usr/bin/colmap");
  o.images.push_back(images_[0]);  // duplicate name
  o.masks = {"a.png"};
  o.matching.circular_neighbours = 0;
  o.free_camera_model = "FISHEYE";
  auto r = RunColmapSfm(o);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
  for (const char* w : {"appears twice", "masks:", "circular_neighbours", "free_camera_model"}) {
    EXPECT_NE(r.error().message.find(w), std::string::npos) << w << " in " << r.error().message;
  }
  auto m = Options("/usr/bin/colmap");
  m.images[1] = tmp_.path() + "/in/missing.png";
  auto rm = RunColmapSfm(m);
  ASSERT_FALSE(rm.ok());
  EXPECT_EQ(rm.error().cls, ErrorClass::kNotFound);
}

// Masks are linked as <image name>.png (COLMAP ignores other names silently);
// fixed intrinsics at another resolution with the same aspect are rescaled.
TEST_F(FakeColmap, MasksLinkedUnderColmapNamesAndCameraPassed) {
  std::vector<std::string> masks;
  cv::Mat mask(96, 128, CV_8UC1, cv::Scalar(255));
  for (int i = 0; i < 3; ++i) {
    masks.push_back(tmp_.path() + "/in/mask_" + std::to_string(i) + ".png");
    ASSERT_TRUE(cv::imwrite(masks.back(), mask));
  }
  auto o = Options(Script("exit 0"));
  o.masks = masks;
  CameraModel cam = TestCamera();  // 640x480 -> images are 128x96
  o.fixed_camera = cam;
  (void)RunColmapSfm(o);
  for (int i = 0; i < 3; ++i) {
    const std::string link = o.workspace + "/masks/view_00" + std::to_string(i) + ".png.png";
    ASSERT_TRUE(std::filesystem::is_symlink(link)) << link;
    EXPECT_EQ(std::filesystem::read_symlink(link).string(), masks[i]);
  }
  const std::string log = *ReadFile(o.workspace + "/logs/feature_extractor.log");
  EXPECT_NE(log.find("--ImageReader.camera_model PINHOLE --"), std::string::npos) << log;
  EXPECT_NE(log.find("--ImageReader.camera_params 160,160,64,48"), std::string::npos) << log;
  EXPECT_NE(log.find("--ImageReader.mask_path " + o.workspace + "/masks"), std::string::npos);

  CameraModel wrong = cam;
  wrong.width = 640;
  wrong.height = 640;
  o.fixed_camera = wrong;
  auto r = RunColmapSfm(o);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidArgument);
  EXPECT_NE(r.error().message.find("recalibrate"), std::string::npos);
}

}  // namespace
}  // namespace aggscan
