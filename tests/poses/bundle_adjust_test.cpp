// Bundle adjustment of one side's turntable angles on sim
// renders at 1008 x 756 with the sim's own angle errors (stop N(0, 0.05 deg),
// read N(0, 0.02 deg)) plus larger reading errors injected into a few views:
// the refined angles must come closer to where the platter really stood, the
// reprojection RMS must drop, and too few features must fall back cleanly.
#include "pipeline/poses/bundle_adjust.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <map>

#include "tests/markers/sim_capture.h"

namespace aggscan {
namespace {

constexpr int kW = 1008, kH = 756;

struct Side {
  std::shared_ptr<sim::SimWorld> world;
  RigCalibration cal;
  std::vector<testing::SimView> views;
};

// One full turn (12 distinct viewpoints, 30 deg apart), rendered once per seed.
const Side& RenderedSide(uint64_t seed) {
  static std::map<uint64_t, Side> cache;
  auto it = cache.find(seed);
  if (it != cache.end()) return it->second;
  Side s;
  Config cfg;
  cfg.sim.seed = seed;
  auto w = sim::SimWorld::Create(cfg);
  EXPECT_TRUE(w.ok());
  s.world = *w;
  sim::Renderer r(*s.world, kW, kH);
  s.cal = s.world->TruthCalibration(kW, kH);
  s.views = testing::RenderSide(r, 1, 12, seed);
  return cache.emplace(seed, std::move(s)).first->second;
}

// Reading errors larger than the turntable's own, on three views (deg).
const std::map<int, double> kInjected = {{3, +0.40}, {7, -0.35}, {10, +0.50}};

BundleAdjustResult Adjust(const Side& s, const std::vector<double>& measured,
                          const BundleAdjustOptions& o, bool erase_masks = false) {
  auto load = [&](int v, cv::Mat* bgr, cv::Mat* mask) {
    *bgr = s.views[v].bgr;
    *mask =
        erase_masks ? cv::Mat::zeros(s.views[v].truth_mask.size(), CV_8UC1) : s.views[v].truth_mask;
    return true;
  };
  return BundleAdjustSideImages(static_cast<int>(s.views.size()), load, measured, s.cal, o);
}

struct AngleErrors {
  double rms = 0, max = 0;
};
AngleErrors Errors(const Side& s, const std::vector<double>& angles) {
  AngleErrors e;
  for (size_t i = 0; i < angles.size(); ++i) {
    const double d = std::abs(angles[i] - s.views[i].true_deg);
    e.rms += d * d, e.max = std::max(e.max, d);
  }
  e.rms = std::sqrt(e.rms / static_cast<double>(angles.size()));
  return e;
}

void Print(const char* what, const Side& s, const std::vector<double>& measured,
           const BundleAdjustResult& r) {
  const AngleErrors before = Errors(s, measured), after = Errors(s, r.angle_deg);
  std::printf(
      "%s: refined %d, %d views, %d tracks, %d observations (%d outliers dropped), RMS %.3f -> "
      "%.3f px, "
      "%d iterations; angle error vs truth RMS %.3f -> %.3f deg, max %.3f -> %.3f deg; "
      "SIFT %.2f s, matching %.2f s, solve %.2f s%s%s\n",
      what, r.refined, r.views_used, r.tracks, r.observations, r.outliers_dropped, r.initial_rms_px,
      r.final_rms_px, r.iterations, before.rms, after.rms, before.max, after.max, r.features_s,
      r.matching_s, r.solve_s, r.reason.empty() ? "" : "; ", r.reason.c_str());
  for (size_t v = 0; v < measured.size(); ++v) {
    std::printf(
        "  view %2zu: true %8.3f measured %8.3f (err %+.3f) refined %8.3f (err %+.3f) correction "
        "%+.3f\n",
        v, s.views[v].true_deg, measured[v], measured[v] - s.views[v].true_deg, r.angle_deg[v],
        r.angle_deg[v] - s.views[v].true_deg, r.correction_deg[v]);
  }
}

std::vector<double> MeasuredWithInjected(const Side& s) {
  std::vector<double> m;
  for (const auto& v : s.views) m.push_back(v.measured_deg);
  for (const auto& [v, d] : kInjected) m[v] += d;
  return m;
}

TEST(BundleAdjust, OptionsAreChecked) {
  BundleAdjustOptions o;
  EXPECT_EQ(o.Check(), "");
  o.angle_prior_deg = 0;
  o.outlier_px = 0.5;
  const std::string e = o.Check();
  EXPECT_NE(e.find("angle_prior_deg"), std::string::npos) << e;
  EXPECT_NE(e.find("outlier_px"), std::string::npos) << e;
  const BundleAdjustResult r = BundleAdjustSide({}, {}, RigCalibration{}, o);
  EXPECT_FALSE(r.refined);
  EXPECT_NE(r.reason.find("invalid bundle adjustment options"), std::string::npos) << r.reason;
}

TEST(BundleAdjust, InjectedAngleErrorsAreCorrected) {
  for (uint64_t seed : {3u, 5u}) {
    const Side& s = RenderedSide(seed);
    ASSERT_EQ(s.views.size(), 12u);
    const std::vector<double> measured = MeasuredWithInjected(s);
    const BundleAdjustResult r = Adjust(s, measured, {});
    char what[32];
    std::snprintf(what, sizeof what, "seed %llu", static_cast<unsigned long long>(seed));
    Print(what, s, measured, r);
    ASSERT_TRUE(r.refined) << r.reason;
    EXPECT_EQ(r.fixed_view, 0);
    EXPECT_EQ(r.views_used, 12);
    EXPECT_GE(r.tracks, 100);
    EXPECT_LT(r.final_rms_px, r.initial_rms_px);
    // Every injected view ends nearer its true angle than it was measured.
    // Measured (Debug, 2 shared cores, 1008 x 756, 12 viewpoints): seed 3 (529
    // tracks, RMS 0.379 -> 0.358 px): view 3 +0.417 -> +0.217 deg, view 7
    // -0.332 -> -0.263, view 10 +0.494 -> +0.442, angle RMS over the views 0.211
    // -> 0.167 deg; seed 5 (450 tracks, RMS 0.363 -> 0.328 px): +0.423 ->
    // +0.314, -0.361 -> -0.321, +0.502 -> +0.298, RMS 0.217 -> 0.162 deg. The
    // well-read views move by 0.05-0.09 deg: with mostly two-view tracks a
    // rotation about the turntable axis is weakly observable (it shifts the
    // points along the epipolar lines), so the correction is partial.
    for (const auto& [v, d] : kInjected) {
      const double before = std::abs(measured[v] - s.views[v].true_deg);
      const double after = std::abs(r.angle_deg[v] - s.views[v].true_deg);
      EXPECT_LT(after, before) << "view " << v;
    }
    EXPECT_LT(Errors(s, r.angle_deg).rms, 0.9 * Errors(s, measured).rms);
  }
}

TEST(BundleAdjust, RefiningTheRigToo) {
  const Side& s = RenderedSide(3);
  const std::vector<double> measured = MeasuredWithInjected(s);
  BundleAdjustOptions o;
  o.refine_rig = true;
  const BundleAdjustResult r = Adjust(s, measured, o);
  Print("seed 3, rig refined", s, measured, r);
  ASSERT_TRUE(r.refined) << r.reason;
  EXPECT_LT(r.final_rms_px, r.initial_rms_px);
  // The rig's rotation about the axis trades against all angles (its prior
  // holds it): compare the angles up to their common offset. Measured: views
  // 3, 7, 10 off by 0.366, 0.383, 0.443 deg before, 0.178, 0.303, 0.397 after.
  auto centred_error = [&](const std::vector<double>& a, int v) {
    double mean = 0;
    for (size_t i = 0; i < a.size(); ++i) mean += a[i] - s.views[i].true_deg;
    mean /= static_cast<double>(a.size());
    return std::abs(a[v] - mean - s.views[v].true_deg);
  };
  for (const auto& [v, d] : kInjected) {
    EXPECT_LT(centred_error(r.angle_deg, v), centred_error(measured, v)) << "view " << v;
  }
}

// The study's capture: 30 views, 30 deg apart (2.5 turns, so 12 viewpoints
// seen 2-3 times). With every view in the adjustment each one gets its own
// angle, and the repeated viewpoints give longer tracks: the correction is
// much better than on the distinct viewpoints alone, at about 3x the cost.
// Measured (Debug, shared cores): 1066 tracks, 4567 observations, RMS 0.430 ->
// 0.381 px; views 3, 15, 22: +0.417 -> +0.076, -0.390 -> -0.071, +0.396 ->
// +0.264 deg; angle RMS over the 30 views 0.129 -> 0.057 deg, the well-read
// views within 0.07 deg; SIFT 6.8 s, matching 12.5 s, solve 9.2 s.
TEST(BundleAdjust, EveryViewOfAThirtyViewSide) {
  Config cfg;
  cfg.sim.seed = 3;
  auto w = sim::SimWorld::Create(cfg);
  ASSERT_TRUE(w.ok());
  sim::Renderer rr(**w, kW, kH);
  Side s;
  s.world = *w;
  s.cal = s.world->TruthCalibration(kW, kH);
  s.views = testing::RenderSide(rr, 1, 30, 3);
  std::vector<double> measured;
  for (const auto& v : s.views) measured.push_back(v.measured_deg);
  for (int v : {3, 15, 22}) measured[v] += (v == 15 ? -0.4 : 0.4);
  BundleAdjustOptions o;
  o.features.distinct_viewpoints_only = false;
  const BundleAdjustResult r = Adjust(s, measured, o);
  Print("seed 3, 30 views, every view", s, measured, r);
  ASSERT_TRUE(r.refined) << r.reason;
  EXPECT_LT(r.final_rms_px, r.initial_rms_px);
  for (int v : {3, 15, 22}) {
    EXPECT_LT(std::abs(r.angle_deg[v] - s.views[v].true_deg),
              std::abs(measured[v] - s.views[v].true_deg))
        << "view " << v;
  }
  EXPECT_LT(Errors(s, r.angle_deg).rms, 0.6 * Errors(s, measured).rms);
}

TEST(BundleAdjust, TooFewFeaturesFallsBackToTheMeasuredAngles) {
  const Side& s = RenderedSide(3);
  const std::vector<double> measured = MeasuredWithInjected(s);
  const BundleAdjustResult r = Adjust(s, measured, {}, /*erase_masks=*/true);
  EXPECT_FALSE(r.refined);
  EXPECT_EQ(r.tracks, 0);
  EXPECT_NE(r.reason.find("feature tracks inside the rock masks"), std::string::npos) << r.reason;
  EXPECT_EQ(r.angle_deg, measured);
  for (double c : r.correction_deg) EXPECT_EQ(c, 0.0);
}

}  // namespace
}  // namespace aggscan
