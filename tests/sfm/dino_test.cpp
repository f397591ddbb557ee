// The SfM path on real turntable photos, Oxford VGG's dino
// (36 views 720x576, ~10° apart, projection matrices given; camera centres on
// a circle of radius 1). Skips when the data or /usr/bin/colmap is absent.
#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <opencv2/calib3d.hpp>
#include <random>
#include <sstream>

#include "common/fsutil.h"
#include "pipeline/sfm/colmap_sfm.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

constexpr const char* kColmap = "/usr/bin/colmap";
const std::string kDino = std::string(AGGSCAN_SHARED_DATA) + "/multiview/oxford_dino";
constexpr int kViews = 36;

std::vector<Eigen::Matrix<double, 3, 4>> ReadProjections(const std::string& path) {
  std::ifstream f(path);
  std::vector<Eigen::Matrix<double, 3, 4>> out;
  std::string line;
  while (std::getline(f, line)) {
    if (line.rfind("# P{", 0) != 0) continue;
    Eigen::Matrix<double, 3, 4> P;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 4; ++c) f >> P(r, c);
    out.push_back(P);
  }
  return out;
}

Eigen::Vector3d CentreOf(const Eigen::Matrix<double, 3, 4>& P) {
  return -P.leftCols<3>().inverse() * P.col(3);
}

// The intrinsics of P = K [R | t] (OpenCV's RQ decomposition), normalised.
cv::Matx33d IntrinsicsOf(const Eigen::Matrix<double, 3, 4>& P) {
  cv::Matx34d p;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 4; ++c) p(r, c) = P(r, c);
  cv::Mat K, R, t;
  cv::decomposeProjectionMatrix(p, K, R, t);
  cv::Matx33d k = K;
  // RQ is unique up to the signs of K's columns: make the diagonal positive.
  for (int c = 0; c < 3; ++c) {
    if (k(c, c) < 0)
      for (int r = 0; r < 3; ++r) k(r, c) = -k(r, c);
  }
  return k * (1.0 / k(2, 2));
}

class Dino : public ::testing::Test {
 protected:
  void SetUp() override {
    if (!PathExists(kDino + "/dino_Ps.txt")) GTEST_SKIP() << "no data at " << kDino;
    if (::access(kColmap, X_OK) != 0) GTEST_SKIP() << kColmap << " not installed";
    Ps_ = ReadProjections(kDino + "/dino_Ps.txt");
    ASSERT_EQ(Ps_.size(), static_cast<size_t>(kViews));
    for (const auto& P : Ps_) truth_.push_back(CentreOf(P));
    K_ = IntrinsicsOf(Ps_[0]);
  }

  // Views first .. first+count-1 as a turntable capture, with the angles of
  // the given camera centres as the "measured turntable angles".
  ColmapSfmOptions Options(const std::string& workspace, int first, int count) const {
    ColmapSfmOptions o;
    o.colmap_binary = kColmap;
    o.workspace = workspace;
    for (int i = first; i < first + count; ++i) {
      char name[64];
      std::snprintf(name, sizeof name, "/images/viff.%03d.png", i);
      o.images.push_back(kDino + name);
      o.angles_deg.push_back(std::atan2(truth_[i].y(), truth_[i].x()) * 180 / M_PI);
    }
    // The plaster dino has little texture: a lower DoG threshold triples the
    // usable keypoints; affine shape + DSP (SiftOptions::LowTexture) made
    // extraction 4x slower here for no gain in accuracy.
    o.sift.peak_threshold = 0.002;
    o.matching.mode = SfmMatching::kCircular;
    o.matching.circular_neighbours = 3;
    o.expect_ring = true;
    o.num_threads = 2;  // the notes' budget: 2 cores
    return o;
  }

  // Camera-centre RMS after a similarity alignment onto the given P's
  // centres, in units of the ring radius (1).
  double CentreRms(const SfmResult& r, int first) const {
    std::vector<Eigen::Vector3d> src, dst;
    for (const auto& im : r.model.images) {
      EXPECT_GE(im.input_index, 0);
      src.push_back(im.Centre());
      dst.push_back(truth_[first + im.input_index]);
    }
    double rms = INFINITY;
    auto sim = EstimateSimilarity(src, dst, true, &rms);
    EXPECT_TRUE(sim.ok()) << sim.error().ToString();
    return rms;
  }

  static void Print(const SfmResult& r, double wall_s) {
    for (const auto& t : r.timings) {
      std::printf("  step %-18s %6.1f s%s\n", t.step.c_str(), t.wall_s,
                  t.skipped ? " (reused)" : "");
    }
    std::printf(
        "  total %.1f s; registered %d/%d; %zu points; reprojection %.3f px; %d verified pairs; "
        "%zu other sub-models; camera %s f=%.1f px\n",
        wall_s, r.num_registered, r.num_input_images, r.model.points.size(), r.mean_reprojection_px,
        r.num_verified_pairs, r.other_models_registered.size(), r.model.cameras[0].model.c_str(),
        r.model.cameras[0].FocalPx());
    for (const auto& c : r.checks.checks) {
      std::printf("  check %-20s %s %s\n", c.name.c_str(),
                  !c.applicable ? "n/a "
                  : c.passed    ? "pass"
                                : "FAIL",
                  c.detail.c_str());
    }
  }

  std::vector<Eigen::Matrix<double, 3, 4>> Ps_;
  std::vector<Eigen::Vector3d> truth_;
  cv::Matx33d K_;
};

TEST_F(Dino, ProjectionMatricesAreARingOfRadiusOne) {
  for (const auto& c : truth_) {
    EXPECT_NEAR(c.head<2>().norm(), 1.0, 0.001);
    EXPECT_NEAR(c.z(), 0.0, 1e-6);
  }
  std::printf("dino K from P0: fx %.1f fy %.1f skew %.1f cx %.1f cy %.1f\n", K_(0, 0), K_(1, 1),
              K_(0, 1), K_(0, 2), K_(1, 2));
  EXPECT_NEAR(K_(0, 0), 3217.3, 1.0);
}

// Item 10: all 36 views, focal from P0 as a hint (COLMAP refines it; the
// focal_length check holds it within 25 %). P's frame is not Euclidean in
// its intrinsics (skew -79 px, fy/fx 0.71, principal point 1070 px above the
// image): fixed as they are, COLMAP finds no initial pair.
TEST_F(Dino, SfmThroughColmapRegistersTheRing) {
  test::TempDir tmp;
  ColmapSfmOptions o = Options(tmp.path() + "/sfm", 0, kViews);
  o.expected_focal_px = K_(0, 0);

  const auto t0 = std::chrono::steady_clock::now();
  auto r = RunColmapSfm(o);
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  Print(*r, wall);
  const double rms = CentreRms(*r, 0);
  std::printf("  camera-centre RMS after similarity: %.4f = %.3f %% of the ring radius\n", rms,
              100 * rms);
  RecordProperty("registered", r->num_registered);
  RecordProperty("centre_rms_permille_x10", static_cast<int>(std::lround(1e4 * rms)));
  RecordProperty("wall_ms", static_cast<int>(1000 * wall));
  EXPECT_GE(r->num_registered, 33) << "need >= 90 % of 36 views";
  EXPECT_LE(rms, 0.01) << "need <= 1 % of the ring radius";
  EXPECT_TRUE(r->checks.ok());
  EXPECT_TRUE(r->checks.Find("focal_length")->applicable);
  EXPECT_TRUE(PathExists(r->model_dir + "/images.txt"));
  EXPECT_TRUE(PathExists(o.workspace + "/result.json"));
  auto exported = ReadColmapTextModel(r->model_dir);
  ASSERT_TRUE(exported.ok());
  EXPECT_EQ(exported->images.size(), r->model.images.size());

  // Resumable: a second run reuses every COLMAP step and gives the same model.
  auto again = RunColmapSfm(o);
  ASSERT_TRUE(again.ok()) << again.error().ToString();
  for (const auto& t : again->timings) EXPECT_TRUE(t.skipped || t.step == "parse_check") << t.step;
  EXPECT_EQ(again->num_registered, r->num_registered);
  EXPECT_EQ(again->model.points.size(), r->model.points.size());

  // The checker on this real model, made wrong: views out of capture order
  // and a focal 0.3x the expected one are both rejected, by name.
  SfmModel shuffled = r->model;
  std::vector<int> perm(kViews);
  for (int i = 0; i < kViews; ++i) perm[i] = i;
  std::mt19937 rng(11);
  std::shuffle(perm.begin(), perm.end(), rng);
  for (auto& im : shuffled.images) im.input_index = perm[im.input_index];
  SfmExpectations ex;
  ex.num_input_images = kViews;
  ex.ring = true;
  const auto rs = CheckSfmModel(shuffled, ex);
  ASSERT_NE(rs.FirstFailure(), nullptr);
  EXPECT_EQ(rs.FirstFailure()->name, "ring_direction");
  ex.expected_focal_px = r->model.cameras[0].FocalPx() / 0.3;
  const auto rf = CheckSfmModel(r->model, ex);
  ASSERT_NE(rf.FirstFailure(), nullptr);
  EXPECT_EQ(rf.FirstFailure()->name, "focal_length");
  EXPECT_NE(rf.ToError().message.find("rig calibration"), std::string::npos);
}

// Fixed intrinsics through real COLMAP (the calibrated-rig case), on a
// 120° arc of 13 views (cheap): the camera must come back unchanged and the
// arc must still pass the ring checks.
TEST_F(Dino, FixedIntrinsicsOnAnArc) {
  test::TempDir tmp;
  constexpr int kFirst = 4, kCount = 13;
  ColmapSfmOptions o = Options(tmp.path() + "/sfm", kFirst, kCount);
  CameraModel cam;
  cam.width = 720;
  cam.height = 576;
  cam.fx = cam.fy = K_(0, 0);
  cam.cx = 359.5;  // P's principal point is off the image (see above): centre it
  cam.cy = 287.5;
  o.fixed_camera = cam;
  const auto t0 = std::chrono::steady_clock::now();
  auto r = RunColmapSfm(o);
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  Print(*r, wall);
  const double rms = CentreRms(*r, kFirst);
  std::printf("  camera-centre RMS after similarity: %.4f = %.3f %% of the ring radius\n", rms,
              100 * rms);
  EXPECT_GE(r->num_registered, 12);
  EXPECT_LE(rms, 0.01);
  ASSERT_NE(r->checks.Find("fixed_intrinsics"), nullptr);
  EXPECT_TRUE(r->checks.Find("fixed_intrinsics")->applicable);
  EXPECT_TRUE(r->checks.Find("fixed_intrinsics")->passed);
  EXPECT_EQ(r->model.cameras.size(), 1u);
  EXPECT_EQ(r->model.cameras[0].model, "PINHOLE");
  EXPECT_DOUBLE_EQ(r->model.cameras[0].params[2], 360.0);
}

// A deliberately wrong setup through real COLMAP: the fixed focal 0.3x the
// true one. It must end in an error that names the failed check (or the step
// that found no model), never in a "successful" model.
TEST_F(Dino, WrongFixedFocalIsRejected) {
  test::TempDir tmp;
  constexpr int kFirst = 4, kCount = 13;
  ColmapSfmOptions o = Options(tmp.path() + "/sfm", kFirst, kCount);
  CameraModel cam;
  cam.width = 720;
  cam.height = 576;
  cam.fx = cam.fy = 0.3 * K_(0, 0);
  cam.cx = 359.5;
  cam.cy = 287.5;
  o.fixed_camera = cam;
  const auto t0 = std::chrono::steady_clock::now();
  auto r = RunColmapSfm(o);
  const double wall = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  if (r.ok()) {
    Print(*r, wall);
    std::printf("  camera-centre RMS after similarity: %.4f\n", CentreRms(*r, kFirst));
  }
  ASSERT_FALSE(r.ok()) << "a wrong focal produced an accepted model";
  std::printf("  %.1f s: %s\n  detail: %s\n", wall, r.error().message.c_str(),
              r.error().detail.c_str());
  EXPECT_EQ(r.error().cls, ErrorClass::kCorrupt);
  // Measured: COLMAP builds a self-consistent model (13/13 views, 0.62 px,
  // centres on a circle, cameras facing the axis) whose steps around the
  // ring are wrong by up to 16° over 120°: only the turntable angles expose it.
  const std::string& m = r.error().message;
  EXPECT_TRUE(m.find("check ring_angles failed") != std::string::npos ||
              m.find("reconstructed no model") != std::string::npos)
      << m;
  EXPECT_TRUE(PathExists(o.workspace + "/result.json")) << "the rejected model is summarised too";
}

}  // namespace
}  // namespace aggscan
