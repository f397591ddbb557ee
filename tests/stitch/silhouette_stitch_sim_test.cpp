// Stitching by silhouette coherence on sim renders (computed masks, JPEG,
// noise, distortion, turntable angle errors): the deficit is smallest near the
// true motion, and refining a perturbed motion brings it back.
#include <gtest/gtest.h>

#include <cstdio>
#include <opencv2/imgproc.hpp>
#include <random>

#include "pipeline/masks/mask.h"
#include "pipeline/stitch/silhouette_stitch.h"
#include "pipeline/stitch/stitch.h"
#include "tests/markers/sim_capture.h"

namespace aggscan {
namespace {

struct Rig {
  std::shared_ptr<sim::SimWorld> world;
  RigCalibration cal;
  std::array<testing::SideCapture, 2> sides;
  std::array<SilhouetteSideInput, 2> sil;
  std::array<SideMarkers, 2> markers;  // object markers located per side
};

Rig Capture(uint64_t seed, int width, int height) {
  Rig rig;
  Config cfg;
  cfg.sim.seed = seed;
  auto world = sim::SimWorld::Create(cfg);
  EXPECT_TRUE(world.ok());
  rig.world = std::move(*world);
  sim::Renderer r(*rig.world, width, height);
  rig.cal = rig.world->TruthCalibration(width, height);
  for (int side : {1, 2}) {
    rig.sides[side - 1] = testing::CaptureSide(r, rig.cal, side, seed);
    for (size_t i = 0; i < rig.sides[side - 1].views.size(); ++i) {
      rig.sil[side - 1].masks.push_back(ComputeForegroundMask(rig.sides[side - 1].views[i].bgr));
      rig.sil[side - 1].cam_from_table.push_back(rig.sides[side - 1].poses[i]);
    }
    const testing::SideCapture& s = rig.sides[side - 1];
    rig.markers[side - 1] =
        LocateObjectMarkers(s.markers, s.poses, rig.cal.camera, testing::ObjectColors());
  }
  return rig;
}

geom::Rigid3 Perturb(const geom::Rigid3& T, const Eigen::Vector3d& c, const Eigen::Vector3d& axis,
                     double deg, const Eigen::Vector3d& shift) {
  geom::Rigid3 A;
  A.R = Eigen::AngleAxisd(deg * 3.14159265358979323846 / 180, axis.normalized()).toRotationMatrix();
  A.t = c - A.R * c + shift;
  return A * T;
}

void Print(const char* what, const sim::SimWorld& w, const StitchResult& st) {
  const testing::StitchError e = testing::MeasureStitch(w, st.T);
  const SilhouetteRefinement& sr = st.silhouettes;
  std::printf(
      "  %s: source %s, silhouettes: start %s, deficit %.4f -> %.4f, moved %.2f deg %.2f mm, %d "
      "evals "
      "%.1f s | error %.2f deg, rock displacement RMS %.2f mm max %.2f mm\n",
      what, st.source.c_str(), sr.start.c_str(), sr.deficit_start, sr.deficit, sr.moved_deg,
      sr.moved_mm, sr.evaluations, sr.seconds, e.rot_deg, e.rms_mm, e.max_mm);
}

// The deficit is small at the true motion and grows away from it; Nelder-Mead
// brings 3 and 8 deg errors back to under a degree.
TEST(SilhouetteStitchSim, RefinesPerturbedMotionsBackToTheTruth) {
  for (uint64_t seed : {1, 3}) {
    Rig rig = Capture(seed, 1008, 756);
    const TimeNs t0 = MonotonicNs();
    auto st = SilhouetteStitcher::Create(rig.sil[0], rig.sil[1], rig.cal.camera);
    ASSERT_TRUE(st.ok()) << st.error().ToString();
    const double prep_ms = (MonotonicNs() - t0) / 1e6;
    const geom::Rigid3 truth = testing::TruthStitch(*rig.world);
    const TimeNs t1 = MonotonicNs();
    const double d_truth = st->Deficit(truth);
    const double eval_ms = (MonotonicNs() - t1) / 1e6;
    std::printf(
        "seed %llu: voxel %.2f mm, scale %.3f, %d views/side, prepare %.0f ms, one deficit %.1f "
        "ms; "
        "deficit at truth %.4f\n",
        static_cast<unsigned long long>(seed), st->voxel_mm(), st->image_scale(), st->views_used(),
        prep_ms, eval_ms, d_truth);
    EXPECT_LT(d_truth, 0.006);  // measured 0.0031-0.0033
    const Eigen::Vector3d c = st->reference_centre();
    for (const auto& [deg, axis] :
         {std::pair{3.0, Eigen::Vector3d(1, 0, 0)}, std::pair{8.0, Eigen::Vector3d(0, 1, 1)}}) {
      const geom::Rigid3 start =
          Perturb(truth, c, axis, deg, Eigen::Vector3d(deg * 0.5, -deg * 0.3, 0));
      const SilhouetteFit fit = st->Refine(start);
      const testing::StitchError e0 = testing::MeasureStitch(*rig.world, start);
      const testing::StitchError e1 = testing::MeasureStitch(*rig.world, fit.T);
      std::printf(
          "  start %.1f deg about (%g %g %g): deficit %.4f -> %.4f, error %.2f deg %.2f mm -> "
          "%.2f deg %.2f mm RMS (max %.2f), %d evals %.1f s\n",
          deg, axis.x(), axis.y(), axis.z(), fit.deficit_start, fit.deficit, e0.rot_deg, e0.rms_mm,
          e1.rot_deg, e1.rms_mm, e1.max_mm, fit.evaluations, fit.seconds);
      EXPECT_GT(fit.deficit_start, 2 * d_truth);
      EXPECT_LT(fit.deficit, 0.006);
      EXPECT_LT(e1.rot_deg, 1.2);  // measured 0.24-0.85 (seeds 1, 3, 6; 3 axes; 1-8 deg starts)
      EXPECT_LT(e1.rms_mm, 0.6);   // measured 0.13-0.38
    }
  }
}

// Masks that take a contact shadow in (a dark band on the floor below the
// rock, in every view) leave it uncovered whatever the motion: the other
// views carve most of it away. The deficit each side's own hull leaves
// measures that floor, and a motion is judged by what it adds: the true one
// stays within silhouette_accept of it, one 3 deg off does not.
TEST(SilhouetteStitchSim, TheOwnDeficitMeasuresWhatShadowsInTheMasksLeaveUncovered) {
  Rig rig = Capture(1, 1008, 756);
  const geom::Rigid3 truth = testing::TruthStitch(*rig.world);
  auto clean = SilhouetteStitcher::Create(rig.sil[0], rig.sil[1], rig.cal.camera);
  ASSERT_TRUE(clean.ok()) << clean.error().ToString();
  std::array<SilhouetteSideInput, 2> shadowed = rig.sil;
  for (SilhouetteSideInput& side : shadowed) {
    for (cv::Mat& m : side.masks) {
      m = m.clone();
      const cv::Rect box = cv::boundingRect(m);
      // A third of the rock's width wide, at its foot, a twentieth of its height deep.
      cv::ellipse(m, cv::Point(box.x + box.width / 2, box.y + box.height),
                  cv::Size(box.width / 3, box.height / 20 + 2), 0, 0, 360, cv::Scalar(255),
                  cv::FILLED);
    }
  }
  auto st = SilhouetteStitcher::Create(shadowed[0], shadowed[1], rig.cal.camera);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  const geom::Rigid3 off = Perturb(truth, st->reference_centre(), Eigen::Vector3d(1, 0, 0), 3.0,
                                   Eigen::Vector3d(1.5, -0.9, 0));
  const double accept = StitchOptions{}.silhouette_accept;
  std::printf(
      "clean masks: own %.4f, at truth %.4f, 3 deg off %.4f; shadowed: own %.4f, at truth %.4f, "
      "3 deg off %.4f\n",
      clean->OwnDeficit(), clean->Deficit(truth), clean->Deficit(off), st->OwnDeficit(),
      st->Deficit(truth), st->Deficit(off));
  EXPECT_LT(clean->OwnDeficit(), 0.003);
  EXPECT_LE(clean->OwnDeficit(), clean->Deficit(truth));
  EXPECT_GT(st->OwnDeficit(), 0.01);
  EXPECT_GT(st->Deficit(truth), clean->Deficit(truth) + accept);  // an absolute limit would fail it
  EXPECT_LT(st->Deficit(truth) - st->OwnDeficit(), accept);
  EXPECT_GT(st->Deficit(off) - st->OwnDeficit(), accept);
}

// Seed 2: the red marker lies under the rock on side 2, so only the purple
// marker's head and tail are on both sides. Without features (as on a small
// rock, whose few SIFT matches do not survive the flip) the two points and
// the silhouettes still stitch: rotations about the line through the points
// are tried, the most coherent refined.
TEST(SilhouetteStitchSim, RescuesTwoMarkerPointsWithoutFeatures) {
  Rig rig = Capture(2, 1008, 756);
  const SideMarkers &m1 = rig.markers[0], &m2 = rig.markers[1];
  auto sil = SilhouetteStitcher::Create(rig.sil[0], rig.sil[1], rig.cal.camera);
  ASSERT_TRUE(sil.ok()) << sil.error().ToString();
  // Without the silhouettes: the clear error.
  auto none = StitchSides(m1, m2, nullptr, nullptr);
  ASSERT_FALSE(none.ok());
  EXPECT_NE(none.error().message.find("only 2 marker points"), std::string::npos)
      << none.error().message;
  auto st = StitchSides(m1, m2, nullptr, nullptr, {}, &*sil);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  Print("seed 2", *rig.world, *st);
  EXPECT_EQ(st->source, "silhouettes");
  EXPECT_TRUE(st->silhouettes.used);
  EXPECT_NE(st->silhouettes.start.find("swept"), std::string::npos);
  const testing::StitchError e = testing::MeasureStitch(*rig.world, st->T);
  EXPECT_LT(e.rot_deg, 1.5);
  EXPECT_LT(e.rms_mm, 0.8);
}

// Seed 6: a small rock stitched by its markers alone, whose rotation about
// the line joining them is weak; the silhouettes refine it.
// Marker points misnamed on one side (a head taken for its tail) can still
// fit one rigid motion, a wrong one. The silhouettes contradict it; a partial
// feature fit they confirm is taken instead, and the stitch says that its
// sources disagree.
TEST(SilhouetteStitchSim, AMarkerFitTheSilhouettesContradictGivesWayToOneTheyConfirm) {
  Rig rig = Capture(1, 1008, 756);
  const geom::Rigid3 truth = testing::TruthStitch(*rig.world);
  auto sil = SilhouetteStitcher::Create(rig.sil[0], rig.sil[1], rig.cal.camera);
  ASSERT_TRUE(sil.ok()) << sil.error().ToString();
  // Side 2's marker points where a motion 150 deg off the truth puts them:
  // they fit it exactly.
  const geom::Rigid3 wrong =
      Perturb(truth, sil->reference_centre(), Eigen::Vector3d(0, 0, 1), 150.0, {0, 0, 0});
  const SideMarkers& m1 = rig.markers[0];
  SideMarkers m2 = m1;
  for (MarkerPoint& p : m2.points) p.position = wrong.Inverse().Apply(p.position);
  ASSERT_GE(m1.located(), 3);
  // Five feature matches, too few alone, at the true motion.
  FeatureCloud ref, mov;
  std::mt19937 rng(3);
  std::uniform_real_distribution<float> d(0, 100);
  std::normal_distribution<double> noise(0, 0.2);
  const std::vector<Eigen::Vector3d> pts = {
      {10, 5, 30}, {-20, 12, 25}, {15, -25, 20}, {-8, -15, 40}, {25, 20, 15}};
  std::vector<cv::Mat> rows;
  for (size_t i = 0; i < pts.size(); ++i) {
    cv::Mat desc(1, 128, CV_32F);
    for (int k = 0; k < 128; ++k) desc.at<float>(k) = d(rng);
    rows.push_back(desc);
    const Eigen::Vector3d p = sil->reference_centre() + pts[i];
    ref.points.push_back(p);
    mov.points.push_back(truth.Inverse().Apply(p) +
                         Eigen::Vector3d(noise(rng), noise(rng), noise(rng)));
    ref.point_of_row.push_back(static_cast<int>(i));
    mov.point_of_row.push_back(static_cast<int>(i));
  }
  cv::vconcat(rows, ref.descriptors);
  mov.descriptors = ref.descriptors.clone();

  // Without the features the marker estimate is kept, and said unconfirmed.
  auto kept = StitchSides(m1, m2, nullptr, nullptr, {}, &*sil);
  ASSERT_TRUE(kept.ok()) << kept.error().ToString();
  EXPECT_EQ(kept->source, "markers");
  EXPECT_NE(kept->silhouettes.note.find("do not confirm"), std::string::npos)
      << kept->silhouettes.note;

  auto st = StitchSides(m1, m2, &ref, &mov, {}, &*sil);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  Print("seed 1, misnamed markers", *rig.world, *st);
  EXPECT_TRUE(st->markers.valid);
  EXPECT_FALSE(st->features.valid);
  EXPECT_EQ(st->features.inliers, 5);
  EXPECT_EQ(st->source, "silhouettes");
  EXPECT_FALSE(st->consistent);
  EXPECT_GT(st->disagreement_deg, 100.0);
  EXPECT_NE(st->warning.find("disagree"), std::string::npos) << st->warning;
  const testing::StitchError e = testing::MeasureStitch(*rig.world, st->T);
  EXPECT_LT(e.rot_deg, 1.2);
  EXPECT_LT(e.rms_mm, 0.8);
}

// Matches of 14 feature points, consistent with a motion 1.5 deg and 0.5
// mm off the true flip (a fit of few matches some of which are wrong), and no
// markers: the silhouettes accept the fit, and with sound masks their
// refinement is clearly more coherent and close to it, so it is taken. At the
// true motion the refinement is not clearly better: the fit is kept, and the
// record's deficit is the fit's own. Measured (1008x756, no polish at this
// size): the fit 1.33 deg / 0.76 mm RMS from the truth, refined 0.84 deg /
// 0.39 mm (deficit 0.0043 -> 0.0032); at the truth the refinement went 0.44
// deg away for 0.0033 -> 0.0032 and the fit (0.26 deg / 0.12 mm) was kept.
TEST(SilhouetteStitchSim, AFitOfFewFeaturesIsRefinedByTheSilhouettes) {
  Rig rig = Capture(1, 1008, 756);
  const geom::Rigid3 truth = testing::TruthStitch(*rig.world);
  auto sil = SilhouetteStitcher::Create(rig.sil[0], rig.sil[1], rig.cal.camera);
  ASSERT_TRUE(sil.ok()) << sil.error().ToString();
  const Eigen::Vector3d c = sil->reference_centre();
  auto features_at = [&](const geom::Rigid3& motion, FeatureCloud* ref, FeatureCloud* mov) {
    std::mt19937 rng(5);
    std::uniform_real_distribution<float> d(0, 100);
    std::uniform_real_distribution<double> at(-30, 30);
    std::normal_distribution<double> noise(0, 0.2);
    std::vector<cv::Mat> rows;
    for (int i = 0; i < 14; ++i) {
      cv::Mat desc(1, 128, CV_32F);
      for (int k = 0; k < 128; ++k) desc.at<float>(k) = d(rng);
      rows.push_back(desc);
      const Eigen::Vector3d p = c + Eigen::Vector3d(at(rng), at(rng), 0.5 * at(rng));
      ref->points.push_back(p);
      mov->points.push_back(motion.Inverse().Apply(p) +
                            Eigen::Vector3d(noise(rng), noise(rng), noise(rng)));
      ref->point_of_row.push_back(i);
      mov->point_of_row.push_back(i);
    }
    cv::vconcat(rows, ref->descriptors);
    mov->descriptors = ref->descriptors.clone();
  };
  const SideMarkers none1, none2;
  const geom::Rigid3 off = Perturb(truth, c, Eigen::Vector3d(1, 0.3, 0), 1.5, {0.3, 0, 0.4});
  FeatureCloud ref, mov;
  features_at(off, &ref, &mov);

  StitchOptions check_only;
  check_only.refine_features = false;
  auto kept = StitchSides(none1, none2, &ref, &mov, check_only, &*sil);
  ASSERT_TRUE(kept.ok()) << kept.error().ToString();
  Print("seed 1, 14 features 1.5 deg off, checked", *rig.world, *kept);
  EXPECT_EQ(kept->source, "features");
  const testing::StitchError e0 = testing::MeasureStitch(*rig.world, kept->T);
  EXPECT_GT(e0.rot_deg, 1.2);

  auto st = StitchSides(none1, none2, &ref, &mov, {}, &*sil);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  Print("seed 1, 14 features 1.5 deg off, refined", *rig.world, *st);
  EXPECT_EQ(st->source, "features+silhouettes");
  EXPECT_TRUE(st->silhouettes.used);
  EXPECT_LT(st->silhouettes.deficit, 0.9 * st->silhouettes.deficit_start);
  const testing::StitchError e = testing::MeasureStitch(*rig.world, st->T);
  EXPECT_LT(e.rot_deg, 0.7 * e0.rot_deg);
  EXPECT_LT(e.rms_mm, 0.6 * e0.rms_mm);

  FeatureCloud ref_t, mov_t;
  features_at(truth, &ref_t, &mov_t);
  auto right = StitchSides(none1, none2, &ref_t, &mov_t, {}, &*sil);
  ASSERT_TRUE(right.ok()) << right.error().ToString();
  Print("seed 1, 14 features at the truth", *rig.world, *right);
  EXPECT_EQ(right->source, "features");
  EXPECT_FALSE(right->silhouettes.used);
  EXPECT_EQ(right->silhouettes.deficit, right->silhouettes.deficit_start);
  EXPECT_NE(right->silhouettes.note.find("not clearly better"), std::string::npos)
      << right->silhouettes.note;
}

TEST(SilhouetteStitchSim, RefinesAMarkerOnlyStitch) {
  Rig rig = Capture(6, 1008, 756);
  const SideMarkers &m1 = rig.markers[0], &m2 = rig.markers[1];
  auto sil = SilhouetteStitcher::Create(rig.sil[0], rig.sil[1], rig.cal.camera);
  ASSERT_TRUE(sil.ok()) << sil.error().ToString();
  auto plain = StitchSides(m1, m2, nullptr, nullptr);
  ASSERT_TRUE(plain.ok()) << plain.error().ToString();
  Print("seed 6 markers only", *rig.world, *plain);
  auto st = StitchSides(m1, m2, nullptr, nullptr, {}, &*sil);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  Print("seed 6 with silhouettes", *rig.world, *st);
  EXPECT_EQ(st->source, "markers+silhouettes");
  const testing::StitchError e0 = testing::MeasureStitch(*rig.world, plain->T);
  const testing::StitchError e = testing::MeasureStitch(*rig.world, st->T);
  EXPECT_LT(e.rot_deg, 1.2);
  EXPECT_LT(e.rms_mm, std::max(0.6, 0.7 * e0.rms_mm));
}

// The polish on a grid with half the voxel brings a motion the silhouettes
// chose closer to the true flip at the rig's 2016x1512 (measured: seed 6's
// marker stitch refined by the silhouettes 0.69 -> 0.48 deg, 0.24 -> 0.19 mm
// RMS over the rock; seed 13's 0.73 -> 0.36 deg, 0.44 -> 0.26 mm). At
// 1008x756 the finer voxel is under two pixels and the polish is skipped
// (seed 6 there went 0.61 -> 0.69 deg).
TEST(SilhouetteStitchSim, PolishOnAFinerGridBringsTheMotionCloser) {
  for (uint64_t seed : {6, 13}) {
    Rig rig = Capture(seed, 2016, 1512);
    auto sil = SilhouetteStitcher::Create(rig.sil[0], rig.sil[1], rig.cal.camera);
    ASSERT_TRUE(sil.ok()) << sil.error().ToString();
    auto st = StitchSides(rig.markers[0], rig.markers[1], nullptr, nullptr, {}, &*sil);
    ASSERT_TRUE(st.ok()) << st.error().ToString();
    ASSERT_TRUE(st->silhouettes.used);
    const SilhouettePolish p =
        PolishSilhouetteStitch(*sil, rig.sil[0], rig.sil[1], rig.cal.camera, st->T);
    const testing::StitchError e0 = testing::MeasureStitch(*rig.world, st->T);
    const testing::StitchError e1 = testing::MeasureStitch(*rig.world, p.T);
    std::printf(
        "seed %llu: coarse voxel %.2f mm, fine %.2f mm; deficit %.5f -> %.5f, moved %.2f deg, %d "
        "evals %.1f s; "
        "error %.2f deg %.2f mm RMS -> %.2f deg %.2f mm RMS (max %.2f)\n",
        static_cast<unsigned long long>(seed), sil->voxel_mm(), p.voxel_mm, p.deficit_start,
        p.deficit, p.moved_deg, p.evaluations, p.seconds, e0.rot_deg, e0.rms_mm, e1.rot_deg,
        e1.rms_mm, e1.max_mm);
    EXPECT_TRUE(p.problem.empty()) << p.problem;
    EXPECT_TRUE(p.done);
    EXPECT_NEAR(p.voxel_mm, sil->voxel_mm() / 2, 0.1 * sil->voxel_mm());
    EXPECT_LT(p.deficit, p.deficit_start);
    EXPECT_LT(e1.rot_deg, e0.rot_deg);
    EXPECT_LT(e1.rms_mm, e0.rms_mm);
    EXPECT_LT(e1.rot_deg, 0.6);
  }
  // Photos at half the size do not resolve the finer grid: no polish.
  Rig low = Capture(6, 1008, 756);
  auto sil = SilhouetteStitcher::Create(low.sil[0], low.sil[1], low.cal.camera);
  ASSERT_TRUE(sil.ok()) << sil.error().ToString();
  const geom::Rigid3 truth = testing::TruthStitch(*low.world);
  const SilhouettePolish p =
      PolishSilhouetteStitch(*sil, low.sil[0], low.sil[1], low.cal.camera, truth);
  EXPECT_FALSE(p.done);
  EXPECT_NE(p.problem.find("do not resolve"), std::string::npos) << p.problem;
  EXPECT_EQ((p.T.R - truth.R).norm() + (p.T.t - truth.t).norm(), 0.0);
}

// No object marker seen on both sides and no feature matches: the silhouettes
// search every orientation and take the one motion that explains them. One
// view per side whose mask lost the rock's top (a face as bright as the disc)
// would carve that part away; those views are found and left out. Without the
// search, or when the runner-up is held too close, the stitch is refused.
TEST(SilhouetteStitchSim, SearchesEveryOrientationWhenNothingElseGivesAStart) {
  Rig rig = Capture(3, 1008, 756);
  std::array<SilhouetteSideInput, 2> sil = rig.sil;
  const std::array<int, 2> damaged = {4, 9};
  for (int k = 0; k < 2; ++k) {
    cv::Mat& m = sil[k].masks[damaged[k]];
    m = m.clone();
    const cv::Rect box = cv::boundingRect(m);
    m(cv::Rect(box.x, box.y, box.width, box.height / 4)).setTo(0);
  }
  auto st = SilhouetteStitcher::Create(sil[0], sil[1], rig.cal.camera);
  ASSERT_TRUE(st.ok()) << st.error().ToString();
  for (int k = 0; k < 2; ++k) {
    EXPECT_EQ(st->left_out(k), std::vector<int>{damaged[k]}) << "side " << k + 1;
  }
  // Kept in, the two cut masks leave their lost tops uncovered in every
  // other view whatever the motion: the own deficit and the one at the
  // true motion both rise.
  SilhouetteStitchOptions keep_all;
  keep_all.leave_out_disagreeing = false;
  auto kept = SilhouetteStitcher::Create(sil[0], sil[1], rig.cal.camera, keep_all);
  ASSERT_TRUE(kept.ok()) << kept.error().ToString();
  EXPECT_TRUE(kept->left_out(0).empty() && kept->left_out(1).empty());
  const geom::Rigid3 truth = testing::TruthStitch(*rig.world);
  std::printf("own deficit %.4f left out, %.4f kept in; at the truth %.4f, %.4f\n",
              st->OwnDeficit(), kept->OwnDeficit(), st->Deficit(truth), kept->Deficit(truth));
  EXPECT_GT(kept->OwnDeficit(), 2 * st->OwnDeficit());      // measured 0.0711 against 0.0014
  EXPECT_GT(kept->Deficit(truth), 2 * st->Deficit(truth));  // 0.1370 against 0.0031
  const SideMarkers none;
  auto result = StitchSides(none, none, nullptr, nullptr, {}, &*st);
  ASSERT_TRUE(result.ok()) << result.error().ToString();
  Print("seed 3, no markers", *rig.world, *result);
  const SilhouetteRefinement& sr = result->silhouettes;
  std::printf("  own %.4f, runner-up %.4f at %.1f deg, %d fits, search %.1f s\n", sr.own_deficit,
              sr.search_runner_up, sr.search_runner_up_deg, sr.search_fits, sr.search_seconds);
  EXPECT_EQ(result->source, "silhouettes");
  EXPECT_TRUE(sr.searched);
  EXPECT_EQ(sr.start, "search over every orientation");
  const testing::StitchError e = testing::MeasureStitch(*rig.world, result->T);
  EXPECT_LT(e.rot_deg, 1.5);  // measured 0.38-0.76 deg, 0.42-0.60 mm
  EXPECT_LT(e.rms_mm, 0.8);
  ASSERT_GE(sr.search_fits, 2);  // the runner-up found, and judged
  EXPECT_GT(sr.search_runner_up - sr.own_deficit, 3 * (sr.deficit - sr.own_deficit));

  StitchOptions no_search;
  no_search.search = false;
  auto refused = StitchSides(none, none, nullptr, nullptr, no_search, &*st);
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.error().detail.find("no partial estimate"), std::string::npos)
      << refused.error().detail;
  StitchOptions strict;
  strict.search_unique_margin = 1.0;  // no runner-up can be this far behind
  strict.search_options = {.directions = 24, .turns = 8, .refine = 2};  // a quicker search
  auto ambiguous = StitchSides(none, none, nullptr, nullptr, strict, &*st);
  ASSERT_FALSE(ambiguous.ok());
  EXPECT_NE(ambiguous.error().detail.find("cannot tell them apart"), std::string::npos)
      << ambiguous.error().detail;
}

}  // namespace
}  // namespace aggscan
