// Stitching the two sides on sim renders at the rig's 2016 x 1512: markers,
// features, their cross-check and the choice, against the true motion. The
// stitch error is measured where it matters: as the displacement of the rock
// mesh's vertices (RMS and max) between the estimate and the truth.
#include <gtest/gtest.h>

#include <cstdio>

#include "tests/markers/sim_capture.h"

namespace aggscan {
namespace {

using testing::CaptureSide;
using testing::SideCapture;

struct StitchRun {
  StitchResult result;
  testing::StitchError chosen, markers, features;
  bool ok = false;
  std::string error;
};

// Renders both sides, locates the markers, builds the feature clouds and
// stitches; prints the figures and the time per side.
StitchRun StitchSeed(uint64_t seed) {
  StitchRun run;
  Config cfg;
  cfg.sim.seed = seed;
  auto world = sim::SimWorld::Create(cfg);
  if (!world.ok()) return run;
  const sim::SimWorld& w = **world;
  sim::Renderer r(w, 2016, 1512);
  const RigCalibration cal = w.TruthCalibration(2016, 1512);
  std::array<SideMarkers, 2> markers;
  std::array<FeatureCloud, 2> clouds;
  for (int side : {1, 2}) {
    const SideCapture s = CaptureSide(r, cal, side, seed);
    const TimeNs t0 = MonotonicNs();
    markers[side - 1] =
        LocateObjectMarkers(s.markers, s.poses, cal.camera, testing::ObjectColors());
    const TimeNs t1 = MonotonicNs();
    std::vector<ViewFeatures> vf(s.views.size());
    for (int i : DistinctViewpoints(s.poses))
      vf[i] = ExtractRockFeatures(s.views[i].bgr, s.views[i].truth_mask);
    const TimeNs t2 = MonotonicNs();
    clouds[side - 1] = BuildFeatureCloud(vf, s.poses, cal.camera);
    const TimeNs t3 = MonotonicNs();
    std::printf(
        "seed %llu side %d: markers: detect %.0f ms/view, locate %.0f ms, %d of 4 points; "
        "features: SIFT %.0f ms (%d viewpoints), cloud %.0f ms, %zu points (Debug)\n",
        static_cast<unsigned long long>(seed), side, s.detect_ms_per_view, (t1 - t0) / 1e6,
        markers[side - 1].located(), (t2 - t1) / 1e6, clouds[side - 1].views, (t3 - t2) / 1e6,
        clouds[side - 1].points.size());
  }
  const TimeNs t0 = MonotonicNs();
  Result<StitchResult> st = StitchSides(markers[0], markers[1], &clouds[0], &clouds[1]);
  std::printf("seed %llu: stitch %.0f ms\n", static_cast<unsigned long long>(seed),
              (MonotonicNs() - t0) / 1e6);
  auto show = [&](const char* what, const StitchEstimate& e, testing::StitchError* err) {
    if (e.valid) *err = testing::MeasureStitch(w, e.T);
    std::printf("  %-8s valid %d, %d of %d pairs, residual RMS %.3f mm max %.3f mm%s%s", what,
                e.valid, e.inliers, e.pairs, e.rms_mm, e.max_mm, e.note.empty() ? "" : "; ",
                e.note.c_str());
    if (e.valid) {
      std::printf(" | error: rotation %.3f deg, rock displacement RMS %.3f mm max %.3f mm",
                  err->rot_deg, err->rms_mm, err->max_mm);
    }
    std::printf("\n");
  };
  if (!st.ok()) {
    run.error = st.error().ToString();
    std::printf("  %s\n", run.error.c_str());
    return run;
  }
  run.ok = true;
  run.result = st.value();
  show("markers", st->markers, &run.markers);
  show("features", st->features, &run.features);
  run.chosen = testing::MeasureStitch(w, st->T);
  std::printf(
      "  chosen: %s, cross-checked %d, disagreement %.3f deg / %.3f mm, marker weak-axis "
      "sigma %.2f deg | error: rotation %.3f deg, rock displacement RMS %.3f mm max %.3f mm %s\n",
      st->source.c_str(), st->cross_checked, st->disagreement_deg, st->disagreement_mm,
      st->markers.rotation_sigma_deg, run.chosen.rot_deg, run.chosen.rms_mm, run.chosen.max_mm,
      st->warning.c_str());
  return run;
}

// Both estimates exist and agree; the features are chosen.
TEST(StitchSim, MarkersAndFeaturesAgree) {
  const StitchRun run = StitchSeed(1);
  ASSERT_TRUE(run.ok) << run.error;
  EXPECT_TRUE(run.result.markers.valid);
  EXPECT_TRUE(run.result.features.valid);
  EXPECT_TRUE(run.result.cross_checked);
  EXPECT_TRUE(run.result.consistent);
  EXPECT_EQ(run.result.source, "features");
  EXPECT_LT(run.result.disagreement_deg, 2.0);  // measured 0.36
  EXPECT_LT(run.result.disagreement_mm, 1.5);   // measured 0.33
  EXPECT_LT(run.chosen.rot_deg, 0.8);           // measured 0.34
  EXPECT_LT(run.chosen.rms_mm, 0.6);            // measured 0.19
  EXPECT_LT(run.markers.rot_deg, 2.0);          // measured 0.36
  EXPECT_LT(run.markers.rms_mm, 1.5);
}

// The red marker lies on the face side 2 rests on: features alone.
TEST(StitchSim, FeaturesWhenAMarkerIsHidden) {
  const StitchRun run = StitchSeed(2);
  ASSERT_TRUE(run.ok) << run.error;
  EXPECT_FALSE(run.result.markers.valid);
  EXPECT_NE(run.result.markers.note.find("only 2 marker points"), std::string::npos);
  EXPECT_EQ(run.result.source, "features");
  EXPECT_GE(run.result.features.inliers, 30);  // measured 63
  EXPECT_LT(run.chosen.rot_deg, 0.4);          // measured 0.10
  EXPECT_LT(run.chosen.rms_mm, 0.5);           // measured 0.16
}

// A small rock: too few SIFT matches survive the flip; markers alone.
TEST(StitchSim, MarkersWhenFeaturesAreTooFew) {
  const StitchRun run = StitchSeed(6);
  ASSERT_TRUE(run.ok) << run.error;
  EXPECT_FALSE(run.result.features.valid);
  EXPECT_TRUE(run.result.markers.valid);
  EXPECT_EQ(run.result.source, "markers");
  EXPECT_LT(run.chosen.rot_deg, 4.0);  // measured 2.9 (the weak axis)
  EXPECT_LT(run.chosen.rms_mm, 2.0);   // measured
}

}  // namespace
}  // namespace aggscan
