// ArUco scale markers (pipeline/markers/aruco_scale.h): corners on a drawn marker,
// then sim renders with the markers on the disc (truth calibration): 2D
// corners against the projected truth, 3D corners against the configured
// ones, the scale and its residual; a marker hidden by the rock or missing is
// reported and the others still give the scale; and the stitch stage's record.
// Each test prints its figures; tolerances carry a margin over what was
// measured (noted beside each).
#include "pipeline/markers/aruco_scale.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <vector>

#include "pipeline/masks/mask.h"
#include "pipeline/stitch/stitch_stage.h"
#include "tests/markers/sim_capture.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

// The stitch stage's record as it is written to results/stitch.json.
Result<nlohmann::json> StitchJson(const StitchStageInput& in) {
  auto r = RunStitchStage(in);
  if (!r) return r.error();
  return r->ToJson();
}

using testing::RenderSide;
using testing::SimView;

// Four markers between the colour labels, each turned differently.
std::vector<ArucoMarker> FourMarkers() {
  return {{1, 80.0, 80.0, 0.0},
          {5, -80.0, 80.0, 30.0},
          {9, -80.0, -80.0, -60.0},
          {13, 80.0, -80.0, 90.0}};
}

// Config whose sim draws rig.aruco_markers (the sheet written as the CLI does,
// 10 px/mm: finer than the camera sees the disc).
Config ArucoConfig(const std::string& dir, std::vector<ArucoMarker> markers, uint64_t seed,
                   double rock_mm) {
  Config cfg;
  cfg.sim.seed = seed;
  cfg.sim.rock_size_mm = rock_mm;
  cfg.rig.aruco_markers = std::move(markers);
  cfg.sim.aruco_image = dir + "/aruco.pgm";
  const Status s = WriteArucoSheet(cfg.rig, cfg.sim.aruco_image, 10.0);
  EXPECT_TRUE(s.ok()) << s.error().ToString();
  std::vector<ConfigProblem> problems;
  ValidateConfig(cfg, "test", &problems);
  for (const auto& p : problems) ADD_FAILURE() << p.ToString();
  return cfg;
}

TEST(ArucoSheet, SimWorldNeedsTheMarkerImage) {
  Config cfg;
  cfg.rig.aruco_markers = FourMarkers();
  auto none = sim::SimWorld::Create(cfg);
  ASSERT_FALSE(none.ok());
  EXPECT_EQ(none.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_NE(none.error().ToString().find("aggscan calibrate aruco --out FILE.pgm"),
            std::string::npos)
      << none.error().ToString();
  // A sheet of another marker count: named with the sizes and what to do.
  test::TempDir tmp;
  const std::string& dir = tmp.path();
  RigConfig three = cfg.rig;
  three.aruco_markers.pop_back();
  cfg.sim.aruco_image = dir + "/three.pgm";
  ASSERT_TRUE(WriteArucoSheet(three, cfg.sim.aruco_image, 5.0).ok());
  auto wrong = sim::SimWorld::Create(cfg);
  ASSERT_FALSE(wrong.ok());
  EXPECT_NE(wrong.error().ToString().find("not the 4 square markers"), std::string::npos)
      << wrong.error().ToString();
}

TEST(ArucoSheet, DrawsTheConfiguredMarkersSideBySide) {
  RigConfig rig;
  rig.aruco_markers = FourMarkers();
  Result<cv::Mat> sheet = DrawArucoSheet(rig, 120);
  ASSERT_TRUE(sheet.ok()) << sheet.error().ToString();
  EXPECT_EQ(sheet->rows, 120);  // 4x4 bits + border = 6 cells of 20 px
  EXPECT_EQ(sheet->cols, 4 * 120);
  // Each square decodes to its id, in list order.
  cv::Mat page(400, 4 * 200, CV_8UC1, cv::Scalar(255));
  for (int k = 0; k < 4; ++k)
    (*sheet)(cv::Rect(k * 120, 0, 120, 120)).copyTo(page(cv::Rect(k * 200 + 40, 140, 120, 120)));
  Result<ArucoViewDetections> d = DetectArucoMarkers(page, cv::Mat(), rig, nullptr);
  ASSERT_TRUE(d.ok()) << d.error().ToString();
  ASSERT_EQ(d->markers.size(), 4u);
  std::vector<int> ids;
  for (const ArucoSighting& s : d->markers) {
    ids.push_back(s.id);
    const int k =
        static_cast<int>(std::find_if(rig.aruco_markers.begin(), rig.aruco_markers.end(),
                                      [&](const ArucoMarker& m) { return m.id == s.id; }) -
                         rig.aruco_markers.begin());
    EXPECT_NEAR(s.corners_px[0].x(), k * 200 + 40 - 0.5, 0.6) << s.id;  // top-left first
    EXPECT_NEAR(s.corners_px[0].y(), 140 - 0.5, 0.6) << s.id;
  }
  std::sort(ids.begin(), ids.end());
  EXPECT_EQ(ids, (std::vector<int>{1, 5, 9, 13}));

  rig.aruco_markers[2].id = 50;  // not in DICT_4X4_50
  EXPECT_FALSE(DrawArucoSheet(rig, 120).ok());
  rig.aruco_markers.clear();
  EXPECT_FALSE(DrawArucoSheet(rig, 120).ok());
  rig.aruco_markers = FourMarkers();
  rig.aruco_dictionary = "DICT_9X9_1";
  Result<cv::Mat> bad = DrawArucoSheet(rig, 120);
  ASSERT_FALSE(bad.ok());
  EXPECT_EQ(bad.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_NE(bad.error().message.find("DICT_9X9_1"), std::string::npos);
}

// Corners of a drawn, slightly blurred marker against where its edges are:
// the black square of pixels [x0, x0 + S) has its edges at x0 - 0.5 and
// x0 + S - 0.5 in the pixel-centre convention the geometry uses.
TEST(ArucoDetect, SubpixelCornersFollowThePixelCentreConvention) {
  RigConfig rig;
  rig.aruco_markers = {{7, 0, 0, 0}};
  Result<cv::Mat> sheet = DrawArucoSheet(rig, 90);
  ASSERT_TRUE(sheet.ok());
  cv::Mat page(300, 300, CV_8UC1, cv::Scalar(230)), blurred;
  const int x0 = 101, y0 = 87, S = 90;
  sheet->copyTo(page(cv::Rect(x0, y0, S, S)));
  cv::GaussianBlur(page, blurred, cv::Size(0, 0), 0.8);  // a linear image: blurred as drawn
  ArucoDetectOptions lin_opts;
  lin_opts.srgb_photo = false;
  Result<ArucoViewDetections> d = DetectArucoMarkers(blurred, cv::Mat(), rig, nullptr, lin_opts);
  ASSERT_TRUE(d.ok());
  ASSERT_EQ(d->markers.size(), 1u);
  const double xs[4] = {x0 - 0.5, x0 + S - 0.5, x0 + S - 0.5, x0 - 0.5};
  const double ys[4] = {y0 - 0.5, y0 - 0.5, y0 + S - 0.5, y0 + S - 0.5};
  double worst = 0;
  for (int k = 0; k < 4; ++k) {
    worst = std::max(worst, (d->markers[0].corners_px[k] - Eigen::Vector2d(xs[k], ys[k])).norm());
    std::printf("corner %d: error (%.3f, %.3f) px\n", k, d->markers[0].corners_px[k].x() - xs[k],
                d->markers[0].corners_px[k].y() - ys[k]);
  }
  std::printf("drawn marker: worst corner error %.3f px\n", worst);
  EXPECT_LT(worst, 0.05);  // measured 0.006 (OpenCV's corners alone: 0.17, all inward)
  lin_opts.edge_refine = false;
  Result<ArucoViewDetections> raw = DetectArucoMarkers(blurred, cv::Mat(), rig, nullptr, lin_opts);
  ASSERT_TRUE(raw.ok() && raw->markers.size() == 1u);
  const double inward = raw->markers[0].corners_px[0].x() - xs[0];
  std::printf("OpenCV's sub-pixel corners alone: top-left %.3f px inside\n", inward);
  EXPECT_GT(inward, 0.05);  // measured 0.122: the bias the edge refinement removes
}

struct CornerFigures {
  double rms_2d_px = 0, max_2d_px = 0, max_3d_mm = 0;
  int sightings = 0;
  double detect_ms_per_view = 0;
};

// Detects the markers in every view of one side, checks the corners against
// the projected truth, and locates them.
struct ArucoSide {
  std::vector<SimView> views;
  std::vector<ArucoViewDetections> detections;
  std::vector<geom::Rigid3> poses;
  CornerFigures f;
};

ArucoSide CaptureArucoSide(const sim::SimWorld& w, sim::Renderer& r, const RigCalibration& cal,
                           const RigConfig& rig, int side, uint64_t seed, int views = 30,
                           const ArucoDetectOptions& opts = {},
                           std::vector<SimView> rendered = {}) {
  ArucoSide s;
  s.views = rendered.empty() ? RenderSide(r, side, views, seed) : std::move(rendered);
  double ss = 0;
  TimeNs detect_ns = 0;
  for (const SimView& v : s.views) {
    const TimeNs t0 = MonotonicNs();
    Result<ArucoViewDetections> d = DetectArucoMarkers(v.bgr, v.truth_mask, rig, &cal.camera, opts);
    detect_ns += MonotonicNs() - t0;
    EXPECT_TRUE(d.ok()) << d.error().ToString();
    s.detections.push_back(d.ok() ? *d : ArucoViewDetections{});
    s.poses.push_back(geom::CamFromTable(cal, v.measured_deg));
    for (const ArucoSighting& a : s.detections.back().markers) {
      for (const ArucoMarker& m : rig.aruco_markers) {
        if (m.id != a.id) continue;
        for (int k = 0; k < 4; ++k) {
          const Eigen::Vector3d c = ArucoCornerMm(m, rig.aruco_size_mm, k);
          double u = 0, vv = 0;
          w.ProjectTurntablePoint({c.x(), c.y(), c.z()}, v.true_deg, r.intrinsics(), &u, &vv);
          const double e = (a.corners_px[k] - Eigen::Vector2d(u, vv)).norm();
          ss += e * e, s.f.max_2d_px = std::max(s.f.max_2d_px, e), ++s.f.sightings;
        }
      }
    }
  }
  s.f.rms_2d_px = std::sqrt(ss / std::max(s.f.sightings, 1));
  s.f.detect_ms_per_view = static_cast<double>(detect_ns) / 1e6 / views;
  return s;
}

// 3D corners against the configured ones; prints the figures.
double Report(const ArucoScale& a, const char* what) {
  double max_3d = 0;
  for (const ArucoMarkerPoint& m : a.markers) {
    double e = 0;
    if (m.located) {
      for (int k = 0; k < 4; ++k) e = std::max(e, (m.corners[k] - m.configured[k]).norm());
      max_3d = std::max(max_3d, e);
      std::printf(
          "  id %2d: 3D corner error max %.3f mm, reprojection RMS %.2f px (max %.2f), views used "
          "%d "
          "of %d seen\n",
          m.id, e, m.rms_px, m.max_px, m.views_used, m.views_seen);
    } else {
      std::printf("  id %2d: not located (seen in %d views): %s\n", m.id, m.views_seen,
                  m.problem.c_str());
    }
  }
  std::printf(
      "%s: %d markers, scale %.6f (error %.1e), %d lengths: RMS %.4f mm max %.4f mm (edges RMS "
      "%.4f, centres RMS %.4f over %d pairs); similarity scale %.6f, residual RMS %.3f mm\n",
      what, a.markers_used, a.scale, a.scale - 1, a.lengths, a.rms_mm, a.max_mm, a.edge_rms_mm,
      a.centre_rms_mm, a.centre_pairs, a.frame_to_table.scale, a.align_rms_mm);
  return max_3d;
}

// The rig's 2016 x 1512, both sides of one rock, 30 views each.
TEST(ArucoScale, EveryMarkerLocatedAndTheScaleRightAt2016) {
  test::TempDir tmp;
  const std::string& dir = tmp.path();
  const Config cfg = ArucoConfig(dir, FourMarkers(), 5, 110.0);
  auto world = sim::SimWorld::Create(cfg);
  ASSERT_TRUE(world.ok()) << world.error().ToString();
  ASSERT_EQ((*world)->aruco_markers().size(), 4u);
  sim::Renderer r(**world, 2016, 1512);
  const RigCalibration cal = (*world)->TruthCalibration(2016, 1512);
  for (int side : {1, 2}) {
    SCOPED_TRACE(side);
    const ArucoSide s = CaptureArucoSide(**world, r, cal, cfg.rig, side, 5);
    std::printf(
        "side %d: corner 2D error RMS %.3f px, max %.3f px over %d corner sightings; detection "
        "%.1f ms "
        "per view\n",
        side, s.f.rms_2d_px, s.f.max_2d_px, s.f.sightings, s.f.detect_ms_per_view);
    EXPECT_LT(s.f.rms_2d_px, 0.1);  // measured 0.029-0.031
    EXPECT_LT(s.f.max_2d_px, 0.3);  // measured 0.090-0.093
    EXPECT_GE(s.f.sightings,
              4 * 4 * 20);  // 4 markers in most of the 30 views (measured 440-456 corners)
    EXPECT_LT(s.f.detect_ms_per_view, 500.0);  // a hang guard; measured 22 ms (2 shared cores)
    Result<ArucoScale> a = LocateArucoMarkers(s.detections, s.poses, cal.camera, cfg.rig);
    ASSERT_TRUE(a.ok()) << a.error().ToString();
    const double max_3d = Report(*a, side == 1 ? "side 1" : "side 2");
    EXPECT_EQ(a->markers_used, 4);
    for (const ArucoMarkerPoint& m : a->markers) {
      EXPECT_TRUE(m.located) << m.id << ": " << m.problem;
      EXPECT_GE(m.views_used, 15) << m.id;
    }
    EXPECT_EQ(a->lengths, 4 * 6 + 6);
    EXPECT_NEAR(a->scale, 1.0, 1e-4);  // measured |error| <= 6.2e-6 (the issue asks for 0.1 %)
    EXPECT_LT(a->rms_mm, 0.03);        // measured 0.0033-0.0052
    EXPECT_LT(a->max_mm, 0.06);        // measured 0.0074-0.0153
    EXPECT_LT(a->align_rms_mm, 0.03);  // measured 0.004-0.009
    EXPECT_NEAR(a->frame_to_table.scale, 1.0, 1e-4);
    EXPECT_LT(max_3d, 0.06);  // measured 0.006-0.023
    if (side == 2) {
      // Why the edge refinement: OpenCV's sub-pixel corners alone, same photos.
      ArucoDetectOptions raw;
      raw.edge_refine = false;
      std::vector<SimView> again = s.views;
      const ArucoSide o =
          CaptureArucoSide(**world, r, cal, cfg.rig, side, 5, 30, raw, std::move(again));
      Result<ArucoScale> b = LocateArucoMarkers(o.detections, o.poses, cal.camera, cfg.rig);
      ASSERT_TRUE(b.ok()) << b.error().ToString();
      std::printf("OpenCV corners only: 2D RMS %.3f px, scale %.6f, residual RMS %.4f mm\n",
                  o.f.rms_2d_px, b->scale, b->rms_mm);
      EXPECT_LT(std::abs(a->scale - 1), std::abs(b->scale - 1));  // measured 5e-6 vs 1.0e-3
      EXPECT_LT(a->rms_mm, b->rms_mm);                            // measured 0.003 vs 0.24 mm
    }
  }
}

// A marker the rock sits on and one configured but never laid on the disc:
// both reported, the other markers still give the scale.
TEST(ArucoScale, HiddenAndAbsentMarkersAreReportedNotFatal) {
  test::TempDir tmp;
  const std::string& dir = tmp.path();
  std::vector<ArucoMarker> drawn = FourMarkers();
  drawn.push_back({20, 0.0, 0.0, 0.0});  // under the rock
  Config cfg = ArucoConfig(dir, drawn, 6, 160.0);
  auto world = sim::SimWorld::Create(cfg);
  ASSERT_TRUE(world.ok()) << world.error().ToString();
  sim::Renderer r(**world, 1008, 756);
  const RigCalibration cal = (*world)->TruthCalibration(1008, 756);
  RigConfig rig = cfg.rig;
  rig.aruco_markers.push_back({33, 60.0, 0.0, 0.0});  // configured, not on the disc
  const ArucoSide s = CaptureArucoSide(**world, r, cal, rig, 1, 6);
  int near_rock = 0;
  for (const ArucoViewDetections& d : s.detections) near_rock += d.near_rock;
  std::printf(
      "1008x756: corner 2D error RMS %.3f px, max %.3f px; %d detections dropped next to the rock; "
      "detection %.1f ms per view\n",
      s.f.rms_2d_px, s.f.max_2d_px, near_rock, s.f.detect_ms_per_view);
  Result<ArucoScale> a = LocateArucoMarkers(s.detections, s.poses, cal.camera, rig);
  ASSERT_TRUE(a.ok()) << a.error().ToString();
  Report(*a, "hidden + absent");
  ASSERT_EQ(a->markers.size(), 6u);
  EXPECT_FALSE(a->markers[4].located);  // id 20, under the rock
  EXPECT_FALSE(a->markers[5].located);  // id 33, absent
  EXPECT_EQ(a->markers[5].views_seen, 0);
  EXPECT_FALSE(a->markers[5].problem.empty());
  EXPECT_EQ(a->markers_used, 4);
  EXPECT_GT(near_rock, 0);           // the 160 mm rock hides markers in some views (measured 3)
  EXPECT_NEAR(a->scale, 1.0, 2e-4);  // measured error 2.9e-5 at 1008 x 756
  EXPECT_LT(a->rms_mm, 0.03);        // measured 0.0055

  // None located: an error naming every marker and what to check.
  RigConfig none;
  none.aruco_markers = {{33, 60.0, 0.0, 0.0}, {34, -60.0, 0.0, 0.0}};
  Result<ArucoScale> e = LocateArucoMarkers(s.detections, s.poses, cal.camera, none);
  ASSERT_FALSE(e.ok());
  EXPECT_EQ(e.error().cls, ErrorClass::kInvalidArgument);
  EXPECT_NE(e.error().message.find("id 33 (detected in 0 of 30 views)"), std::string::npos)
      << e.error().message;
  EXPECT_NE(e.error().message.find("id 34"), std::string::npos);
  EXPECT_NE(e.error().message.find("uncovered by the rock"), std::string::npos);
}

// Poses of a model 2 % too large (an SfM model's arbitrary scale): the scale
// says by how much.
TEST(ArucoScale, MeasuresTheScaleOfTheModel) {
  test::TempDir tmp;
  const std::string& dir = tmp.path();
  const Config cfg = ArucoConfig(dir, FourMarkers(), 7, 100.0);
  auto world = sim::SimWorld::Create(cfg);
  ASSERT_TRUE(world.ok()) << world.error().ToString();
  sim::Renderer r(**world, 1008, 756);
  const RigCalibration cal = (*world)->TruthCalibration(1008, 756);
  ArucoSide s = CaptureArucoSide(**world, r, cal, cfg.rig, 1, 7, 15);
  for (geom::Rigid3& p : s.poses) p.t *= 1.02;  // every length in the model 2 % longer
  Result<ArucoScale> a = LocateArucoMarkers(s.detections, s.poses, cal.camera, cfg.rig);
  ASSERT_TRUE(a.ok()) << a.error().ToString();
  Report(*a, "model x1.02");
  EXPECT_NEAR(a->scale, 1.0 / 1.02, 2e-4);  // measured 0.980396 for 0.980392
  EXPECT_LT(a->rms_mm, 0.03);  // after the scale the lengths agree again (measured 0.0049)
}

// The stitch stage on one side written to disc: the record's "aruco_scale"
// and which reference gave the sample's scale residual.
TEST(ArucoScale, StitchStageRecordsTheArucoReference) {
  test::TempDir tmp;
  const std::string& dir = tmp.path();
  Config cfg = ArucoConfig(dir, FourMarkers(), 8, 100.0);
  auto world = sim::SimWorld::Create(cfg);
  ASSERT_TRUE(world.ok()) << world.error().ToString();
  sim::Renderer r(**world, 1008, 756);
  const RigCalibration cal = (*world)->TruthCalibration(1008, 756);
  const std::vector<SimView> views = RenderSide(r, 1, 12, 8);
  StitchStageInput in;
  in.sample_dir = dir;
  in.calibration = &cal;
  for (size_t i = 0; i < views.size(); ++i) {
    SampleView v;
    v.view = static_cast<int>(i);
    v.angle_deg = views[i].measured_deg;
    v.image = dir + "/view" + std::to_string(i) + ".png";
    v.mask = dir + "/mask" + std::to_string(i) + ".png";
    ASSERT_TRUE(cv::imwrite(v.image, views[i].bgr));
    ASSERT_TRUE(cv::imwrite(v.mask, views[i].truth_mask));
    const geom::Rigid3 p = geom::CamFromTable(cal, v.angle_deg);
    v.cam_from_table.linear() = p.R;
    v.cam_from_table.translation() = p.t;
    in.views[1].push_back(v);
  }

  // ArUco only (no colour labels configured).
  in.rig = cfg.rig;
  in.rig.markers.clear();
  Result<nlohmann::json> j = StitchJson(in);
  ASSERT_TRUE(j.ok()) << j.error().ToString();
  const nlohmann::json& side = (*j)["per_side"][0];
  const nlohmann::json& aru = side["aruco_scale"];
  std::printf("aruco only: %s\n", aru.dump().c_str());
  EXPECT_TRUE(aru["configured"].get<bool>());
  ASSERT_TRUE(aru["ok"].get<bool>()) << aru.dump();
  EXPECT_EQ(aru["markers_used"].get<int>(), 4);
  EXPECT_NEAR(aru["scale"].get<double>(), 1.0, 2e-4);  // measured 1.000004 (12 views at 1008 x 756)
  EXPECT_NEAR(aru["measured_over_configured"].get<double>() * aru["scale"].get<double>(), 1.0,
              1e-12);
  EXPECT_LT(aru["rms_mm"].get<double>(), 0.03);  // measured 0.0058
  EXPECT_GT(aru["detect_ms_per_view"].get<double>(), 0.0);
  EXPECT_FALSE(side["background_labels"]["ok"].get<bool>());
  EXPECT_EQ((*j)["scale_reference"], "aruco");
  EXPECT_DOUBLE_EQ((*j)["scale_residual_mm"].get<double>(), aru["rms_mm"].get<double>());

  // Labels and ArUco: both count, the worse residual is the sample's.
  in.rig = cfg.rig;
  j = StitchJson(in);
  ASSERT_TRUE(j.ok()) << j.error().ToString();
  const nlohmann::json& both = (*j)["per_side"][0];
  ASSERT_TRUE(both["background_labels"]["ok"].get<bool>()) << both["background_labels"].dump();
  EXPECT_EQ((*j)["scale_reference"], "labels+aruco");
  EXPECT_DOUBLE_EQ((*j)["scale_residual_mm"].get<double>(),
                   std::max(both["background_labels"]["pair_rms_mm"].get<double>(),
                            both["aruco_scale"]["rms_mm"].get<double>()));

  // Labels only: the study's default, unchanged.
  in.rig.aruco_markers.clear();
  j = StitchJson(in);
  ASSERT_TRUE(j.ok()) << j.error().ToString();
  EXPECT_FALSE((*j)["per_side"][0]["aruco_scale"]["configured"].get<bool>());
  EXPECT_EQ((*j)["scale_reference"], "labels");

  // ArUco configured but none on the disc, no labels: reported, not fatal.
  in.rig.markers.clear();
  in.rig.aruco_markers = {{40, 60.0, 0.0, 0.0}};
  j = StitchJson(in);
  ASSERT_TRUE(j.ok()) << j.error().ToString();
  const nlohmann::json& missing = (*j)["per_side"][0]["aruco_scale"];
  EXPECT_FALSE(missing["ok"].get<bool>());
  EXPECT_NE(missing["problem"].get<std::string>().find("id 40"), std::string::npos)
      << missing.dump();
  EXPECT_TRUE((*j)["scale_residual_mm"].is_null());
  EXPECT_TRUE((*j)["scale_reference"].is_null());
}

// The stitch record without its timings and the count of photos it decoded.
nlohmann::json WithoutTimings(nlohmann::json j) {
  if (j.is_object()) {
    nlohmann::json out = nlohmann::json::object();
    for (auto& [k, v] : j.items()) {
      const bool timing = k == "timings_s" || k == "stage_seconds" || k == "seconds" ||
                          k == "photos_decoded" || k == "detect_ms_per_view" ||
                          (k.size() > 2 && k.compare(k.size() - 2, 2, "_s") == 0);
      if (!timing) out[k] = WithoutTimings(v);
    }
    return out;
  }
  if (j.is_array()) {
    for (auto& v : j) v = WithoutTimings(v);
  }
  return j;
}

// Two sides whose photos an earlier stage decoded: the stitch takes their
// labels, object markers, ArUco markers and rock windows from the evidence
// cache and comes to the very same record, decoding nothing (or, when the
// cache had no room for the colour windows, only the photos its features need).
TEST(ArucoScale, StitchStageFromTheEvidenceCacheIsTheSame) {
  test::TempDir tmp;
  const std::string& dir = tmp.path();
  const Config cfg = ArucoConfig(dir, FourMarkers(), 8, 100.0);
  auto world = sim::SimWorld::Create(cfg);
  ASSERT_TRUE(world.ok()) << world.error().ToString();
  sim::Renderer r(**world, 1008, 756);
  const RigCalibration cal = (*world)->TruthCalibration(1008, 756);
  StitchStageInput in;
  in.sample_dir = dir;
  in.calibration = &cal;
  in.rig = cfg.rig;
  std::map<std::string, std::pair<cv::Mat, cv::Mat>> decoded;  // what an earlier stage held
  for (int side = 1; side <= 2; ++side) {
    const std::vector<SimView> views = RenderSide(r, side, 8, 8);
    for (size_t i = 0; i < views.size(); ++i) {
      SampleView v;
      v.view = static_cast<int>(i);
      v.angle_deg = views[i].measured_deg;
      const std::string name = std::to_string(side) + "_" + std::to_string(i);
      v.image = dir + "/view" + name + ".png";
      v.mask = dir + "/mask" + name + ".png";
      ASSERT_TRUE(cv::imwrite(v.image, views[i].bgr));
      ASSERT_TRUE(cv::imwrite(v.mask, views[i].truth_mask));
      decoded[v.image] = {views[i].bgr, views[i].truth_mask};
      const geom::Rigid3 p = geom::CamFromTable(cal, v.angle_deg);
      v.cam_from_table.linear() = p.R;
      v.cam_from_table.translation() = p.t;
      in.views[side].push_back(v);
    }
  }
  // The feature matching (FLANN's trees) and the silhouettes draw random
  // numbers: each run starts from the state a fresh worker process has.
  std::srand(1);
  cv::theRNG() = cv::RNG();
  Result<nlohmann::json> plain = StitchJson(in);
  ASSERT_TRUE(plain.ok()) << plain.error().ToString();
  for (const auto& side : (*plain)["per_side"]) EXPECT_EQ(side["photos_decoded"], 8);
  ASSERT_TRUE((*plain)["per_side"][0]["aruco_scale"]["ok"].get<bool>());
  ASSERT_TRUE((*plain)["per_side"][0]["background_labels"]["ok"].get<bool>());

  for (const size_t budget : {size_t{160} << 20, size_t{0}}) {
    SCOPED_TRACE("colour budget " + std::to_string(budget));
    ViewEvidenceCache cache(StitchEvidenceOptions(in, 40), budget);
    for (const auto& [image, pm] : decoded) cache.Add(image, pm.first, pm.second);
    ASSERT_EQ(cache.views(), decoded.size());
    in.evidence = &cache;
    std::srand(1);
    cv::theRNG() = cv::RNG();
    Result<nlohmann::json> cached = StitchJson(in);
    in.evidence = nullptr;
    ASSERT_TRUE(cached.ok()) << cached.error().ToString();
    EXPECT_EQ(WithoutTimings(*cached), WithoutTimings(*plain));
    for (const auto& side : (*cached)["per_side"]) {
      EXPECT_EQ(side["photos_decoded"].get<int>(),
                budget > 0 ? 0 : side["feature_cloud"]["viewpoints"].get<int>())
          << side.dump();
      EXPECT_GT(side["timings_s"]["markers"].get<double>(), 0.0);
    }
  }

  // Evidence gathered for another lens is not taken.
  RigCalibration other = cal;
  other.camera.fx *= 1.01;
  StitchStageInput other_in = in;
  other_in.calibration = &other;
  ViewEvidenceCache foreign(StitchEvidenceOptions(other_in, 40));
  for (const auto& [image, pm] : decoded) foreign.Add(image, pm.first, pm.second);
  in.evidence = &foreign;
  std::srand(1);
  cv::theRNG() = cv::RNG();
  Result<nlohmann::json> not_taken = StitchJson(in);
  ASSERT_TRUE(not_taken.ok()) << not_taken.error().ToString();
  for (const auto& side : (*not_taken)["per_side"]) EXPECT_EQ(side["photos_decoded"], 8);
  EXPECT_EQ(WithoutTimings(*not_taken), WithoutTimings(*plain));
}

// Black-and-white markers on the disc are not rock: the classical masks,
// which the stitch stage's detection and the surface use, stay as good as
// without them.
TEST(ArucoScale, ClassicalMaskLeavesTheMarkersOut) {
  test::TempDir tmp;
  const std::string& dir = tmp.path();
  const Config with = ArucoConfig(dir, FourMarkers(), 9, 0.0);
  Config without = with;
  without.rig.aruco_markers.clear();
  without.sim.aruco_image.clear();
  double worst[2] = {1, 1}, mean[2] = {0, 0};
  int k = 0;
  for (const Config* cfg : {static_cast<const Config*>(&without), &with}) {
    auto world = sim::SimWorld::Create(*cfg);
    ASSERT_TRUE(world.ok()) << world.error().ToString();
    sim::Renderer r(**world, 1008, 756);
    const std::vector<SimView> views = RenderSide(r, 1, 6, 9, 60.0);
    for (const SimView& v : views) {
      const cv::Mat m = ComputeForegroundMask(v.bgr);
      const double inter = cv::countNonZero(m & v.truth_mask),
                   uni = cv::countNonZero(m | v.truth_mask);
      const double iou = uni > 0 ? inter / uni : 0;
      worst[k] = std::min(worst[k], iou), mean[k] += iou / views.size();
    }
    ++k;
  }
  std::printf(
      "classical mask IoU without markers: mean %.4f min %.4f; with ArUco markers: mean %.4f min "
      "%.4f\n",
      mean[0], worst[0], mean[1], worst[1]);
  EXPECT_GE(worst[1], 0.98);            // measured 0.9941 (0.9971 without markers)
  EXPECT_GE(mean[1], mean[0] - 0.002);  // measured 0.9983 vs 0.9989
}

}  // namespace
}  // namespace aggscan
