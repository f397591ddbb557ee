// The full-SfM poses path on simulated captures: COLMAP
// poses each side, the background labels scale it into the turntable frame,
// and the stages after the poses run unchanged. Compared with the sim's truth
// (camera centres, volume, dimensions). Small captures (12 views a side)
// keep COLMAP at about a minute a side on 2 cores. Skips when
// /usr/bin/colmap is not installed.
#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <regex>
#include <sstream>

#include "cli/reconstruct_command.h"
#include "cli/sim_capture.h"
#include "common/fsutil.h"
#include "config/config.h"
#include "drivers/sim/world.h"
#include "pipeline/core/geometry.h"
#include "pipeline/sfm/colmap_sfm.h"
#include "pipeline/worker/reconstruct.h"
#include "tests/reconstruct/sim_sample.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// 12 views 30 deg apart (the study's step) over one turn, at the rig's full
// resolution: at 1008 x 756 the rock gives ~200 SIFT features, too few for
// COLMAP's initial pair.
constexpr int kViews = 12;
constexpr int kWidth = 2016, kHeight = 1512;

#define SKIP_WITHOUT_COLMAP() \
  if (::access("/usr/bin/colmap", X_OK) != 0) GTEST_SKIP() << "/usr/bin/colmap not installed"

// A sample rendered offline with the sim's ground-truth masks where the side
// stage keeps its masks (the geometric stages under test).
std::string Capture(const std::string& dir, uint64_t seed, int sides, bool calibration,
                    int views = kViews, int width = kWidth, int height = kHeight,
                    double step_deg = 360.0 / kViews) {
  return test::CaptureSimSample(dir, seed, sides, calibration, true, views, width, height,
                                step_deg);
}

// A two-side capture reconstructed on `path`; empty when it failed.
std::string CaptureAndReconstruct(const std::string& dir, uint64_t seed, bool calibration,
                                  PosesPath path) {
  const std::string sample = Capture(dir, seed, 2, calibration);
  ReconstructOptions opts;
  opts.poses = path;
  auto st = ReconstructSample(sample, opts);
  EXPECT_TRUE(st) << (st ? "" : st.error().ToString());
  return st ? sample : std::string();
}

json ReadJsonFile(const std::string& path) {
  auto text = ReadFile(path);
  EXPECT_TRUE(text) << path;
  return text ? json::parse(*text) : json();
}

// The largest distance (mm) between a side's camera centres and the sim's
// true ones (the truth calibration at the platter's true angle).
double WorstCentreErrorMm(const std::string& sample, int side, uint64_t seed) {
  Config c;
  c.sim.seed = seed;
  sim::SimWorld world(c);
  const RigCalibration truth_cal = world.TruthCalibration(kWidth, kHeight);  // extrinsics: any size
  const json truth = ReadJsonFile(sample + "/truth.json");
  const json poses = ReadJsonFile(sample + "/results/poses_side" + std::to_string(side) + ".json");
  double worst = 0;
  int compared = 0;
  for (const auto& v : poses["views"]) {
    for (const auto& t : truth["views"]) {
      if (t["side"] != side || t["view"] != v["view"]) continue;
      std::array<double, 16> m{};
      for (int i = 0; i < 16; ++i) m[i] = v["cam_from_table_4x4"][i].get<double>();
      const geom::Rigid3 sfm = geom::Rigid3::FromRowMajor4(m);
      const geom::Rigid3 tru =
          geom::Rigid3::FromRowMajor4(truth_cal.CamFromTable(t["platter_deg"].get<double>()));
      const Eigen::Vector3d cs = -(sfm.R.transpose() * sfm.t), ct = -(tru.R.transpose() * tru.t);
      worst = std::max(worst, (cs - ct).norm());
      ++compared;
    }
  }
  EXPECT_EQ(compared, static_cast<int>(poses["views"].size()));
  return worst;
}

// What every successful SfM side must show.
void ExpectSfmSide(const std::string& sample, int side, const std::string& camera_source,
                   int views = kViews) {
  const json p = ReadJsonFile(sample + "/results/poses_side" + std::to_string(side) + ".json");
  EXPECT_EQ(p["method"], "sfm");
  const json& s = p["sfm"];
  EXPECT_EQ(s["registered_views"], views) << s.dump();
  EXPECT_TRUE(s["checks_passed"].get<bool>()) << s["checks"].dump();
  EXPECT_LT(s["mean_reprojection_px"].get<double>(), 1.0);
  EXPECT_EQ(s["camera_source"], camera_source);
  EXPECT_EQ(p["scale"]["reference"], "labels");
  EXPECT_EQ(p["scale"]["references"].size(), 4u);
  // The four labels fit their configured layout to well under a millimetre.
  EXPECT_LT(p["scale"]["residual_mm"].get<double>(), 0.5) << p["scale"].dump();
  EXPECT_EQ(p["views"].size(), static_cast<size_t>(views));
  // The exported model is metric: its camera centres are the record's.
  auto model = ReadColmapTextModel(sample + "/results/sfm/side" + std::to_string(side));
  ASSERT_TRUE(model) << model.error().ToString();
  ASSERT_EQ(model->images.size(), static_cast<size_t>(views));
  const json& v0 = p["views"][0];
  const SfmImage* img =
      model->FindImageByName(fs::path(v0["image"].get<std::string>()).filename().string());
  ASSERT_NE(img, nullptr);
  std::array<double, 16> m{};
  for (int i = 0; i < 16; ++i) m[i] = v0["cam_from_table_4x4"][i].get<double>();
  const geom::Rigid3 T = geom::Rigid3::FromRowMajor4(m);
  EXPECT_LT((img->Centre() - (-(T.R.transpose() * T.t))).norm(), 1e-3);
  std::printf("side %d: %d/%d views, %.3f px, scale residual %.3f mm, COLMAP %.1f s\n", side,
              s["registered_views"].get<int>(), s["input_views"].get<int>(),
              s["mean_reprojection_px"].get<double>(), p["scale"]["residual_mm"].get<double>(),
              s["colmap_s"].get<double>());
}

// Volume and dimensions against the truth; prints them.
void ExpectMorphology(const std::string& sample, double volume_tol, double dim_tol,
                      int views = kViews) {
  auto m = ReadMorphology(sample);
  ASSERT_TRUE(m) << m.error().ToString();
  EXPECT_EQ((*m)["methods"]["poses"], "sfm");
  const json& d = (*m)["morphology_3d"];
  const json truth = ReadJsonFile(sample + "/truth.json");
  auto rel = [&](const char* k) { return d[k].get<double>() / truth[k].get<double>() - 1.0; };
  std::printf("V %+.2f %% a %+.2f %% b %+.2f %% c %+.2f %%, iou %.4f, stitch %s\n",
              100 * rel("volume_mm3"), 100 * rel("a_mm"), 100 * rel("b_mm"), 100 * rel("c_mm"),
              (*m)["quality"]["silhouette_iou_mean"].get<double>(),
              (*m)["methods"]["stitch"].dump().c_str());
  EXPECT_TRUE(d["watertight"].get<bool>());
  EXPECT_NEAR(rel("volume_mm3"), 0.0, volume_tol);
  for (const char* k : {"a_mm", "b_mm", "c_mm"}) EXPECT_NEAR(rel(k), 0.0, dim_tol) << k;
  ASSERT_TRUE((*m)["poses"].is_array());
  for (const auto& e : (*m)["poses"]) {
    EXPECT_EQ(e["method"], "sfm");
    EXPECT_EQ(e["registered_views"], views);
  }
}

// With the rig calibration: intrinsics held fixed, poses from COLMAP, scale
// and frame from the four background labels.
TEST(SfmReconstruct, TwoSidesWithCalibrationMatchTheTruth) {
  SKIP_WITHOUT_COLMAP();
  test::TempDir tmp;
  const uint64_t seed = 1;
  const std::string sample = CaptureAndReconstruct(tmp.path(), seed, true, PosesPath::kSfm);
  ASSERT_FALSE(sample.empty());
  for (int side : {1, 2}) {
    ExpectSfmSide(sample, side, "calibration");
    const double worst = WorstCentreErrorMm(sample, side, seed);
    std::printf("side %d: worst camera centre error %.2f mm\n", side, worst);
    // The camera stands ~650 mm from the axis; the labels, in the disc plane
    // below the rock, fix the frame there: the error grows towards the
    // camera, mostly along the line of sight, where the silhouettes are
    // least sensitive (measured 6.6 and 3.3 mm, 1.0 and 0.5 %). COLMAP's
    // threads make each run a little different: one CI rehearsal in about
    // fifteen measured 11.85 mm. 15 mm (2.3 % of the distance, as for the
    // ArUco test below) still refuses a wrong model, which lands centimetres
    // off; the rock's figures are held to 3 % below.
    EXPECT_LT(worst, 15.0);
  }
  EXPECT_EQ(ReadJsonFile(sample + "/results/calibration_used.json")["method"], "sim-truth");
  // The labels are found once: the SfM step keeps what it found in the
  // sample's view evidence, and the stitch finds its labels and markers
  // there (no photo decoded again).
  const json stitch = ReadJsonFile(sample + "/results/stitch.json");
  ASSERT_EQ(stitch["per_side"].size(), 2u);
  for (const json& ps : stitch["per_side"]) EXPECT_EQ(ps["photos_decoded"], 0) << ps.dump();
  ExpectMorphology(sample, 0.03, 0.03);
}

// ArUco markers on the disc in place of the colour labels: the SfM model is
// scaled and framed by their corners (4 per marker), located with COLMAP's
// poses. One side (the scale reference is per side; two sides are the test
// above).
TEST(SfmReconstruct, ArucoMarkersScaleTheModel) {
  SKIP_WITHOUT_COLMAP();
  test::TempDir tmp;
  const uint64_t seed = 1;
  const std::string sample = test::CaptureSimSample(
      tmp.path(), seed, 1, true, true, kViews, kWidth, kHeight, 360.0 / kViews,
      "[rig]\nmarkers = []\n"
      "aruco_markers = [{id = 1, x_mm = 80.0, y_mm = 80.0},\n"
      "  {id = 5, x_mm = -80.0, y_mm = 80.0, yaw_deg = 30.0},\n"
      "  {id = 9, x_mm = -80.0, y_mm = -80.0, yaw_deg = -60.0}]\n");
  ReconstructOptions opts;
  opts.poses = PosesPath::kSfm;
  auto st = ReconstructSample(sample, opts);
  ASSERT_TRUE(st) << st.error().ToString();
  const json p = ReadJsonFile(sample + "/results/poses_side1.json");
  EXPECT_EQ(p["method"], "sfm");
  EXPECT_EQ(p["sfm"]["registered_views"], kViews) << p["sfm"].dump();
  EXPECT_EQ(p["scale"]["reference"], "aruco") << p["scale"].dump();
  EXPECT_TRUE(p["scale"]["labels"].empty()) << p["scale"].dump();  // none configured
  EXPECT_EQ(p["scale"]["aruco"]["markers_used"], 3) << p["scale"].dump();
  EXPECT_EQ(p["scale"]["references"].size(), 12u);  // 3 markers x 4 corners
  EXPECT_LT(p["scale"]["residual_mm"].get<double>(), 0.5) << p["scale"].dump();
  const double worst = WorstCentreErrorMm(sample, 1, seed);
  std::printf("aruco: scale residual %.3f mm, worst camera centre error %.2f mm\n",
              p["scale"]["residual_mm"].get<double>(), worst);
  // Measured 6.8 and 9.1 mm in two runs (COLMAP's threads make each run a
  // little different): the three markers span 160 mm of the disc, the four
  // labels 200 mm, so the frame is held less firmly than with the labels.
  EXPECT_LT(worst, 15.0);
  // One side sees no underside: the hull's thickness (a) is bounded only by
  // the disc, so a is not compared (measured +10.6 %); volume, b and c are.
  auto m = ReadMorphology(sample);
  ASSERT_TRUE(m) << m.error().ToString();
  const json& d = (*m)["morphology_3d"];
  const json truth = ReadJsonFile(sample + "/truth.json");
  auto rel = [&](const char* k) { return d[k].get<double>() / truth[k].get<double>() - 1.0; };
  std::printf("aruco: V %+.2f %% a %+.2f %% b %+.2f %% c %+.2f %%\n", 100 * rel("volume_mm3"),
              100 * rel("a_mm"), 100 * rel("b_mm"), 100 * rel("c_mm"));
  ASSERT_TRUE((*m)["poses"].is_array());
  EXPECT_EQ((*m)["poses"][0]["scale_reference"], "aruco") << (*m)["poses"].dump();
  EXPECT_NEAR(rel("volume_mm3"), 0.0, 0.03);  // measured +0.40 %
  EXPECT_NEAR(rel("b_mm"), 0.0, 0.03);        // measured -1.89 %
  EXPECT_NEAR(rel("c_mm"), 0.0, 0.03);        // measured -1.78 %
}

// Without a calibration, auto takes the SfM path (here to a missing colmap
// binary: the error is the SfM path's, with what to do); with one, the
// turntable path.
TEST(SfmReconstruct, AutoPicksSfmWithoutCalibration) {
  test::TempDir tmp;
  const std::string sample = Capture(tmp.path(), 1, 1, false, 6, 504, 378, 60.0);
  ReconstructOptions opts;
  opts.poses = PosesPath::kAuto;
  opts.sfm.colmap_binary = tmp.path() + "/no-colmap";
  auto st = ReconstructSample(sample, opts);
  ASSERT_FALSE(st);
  const std::string msg = st.error().message;
  EXPECT_NE(msg.find("poses stage (sfm), side1"), std::string::npos) << msg;
  EXPECT_NE(msg.find("install Debian's colmap package"), std::string::npos) << msg;
  EXPECT_FALSE(fs::exists(sample + "/results/calibration_used.json"));
  // The turntable path without a calibration names both ways out.
  opts.poses = PosesPath::kTurntable;
  st = ReconstructSample(sample, opts);
  ASSERT_FALSE(st);
  EXPECT_NE(st.error().message.find("aggscan calibrate"), std::string::npos) << st.error().message;
  EXPECT_NE(st.error().message.find("--poses sfm"), std::string::npos) << st.error().message;
}

// Without a calibration, side 1's COLMAP camera becomes the sample's and
// side 2 is posed with it held fixed (one camera model). The sim's nominal
// lens (sim.hfov_deg) is the focal hint, held while COLMAP poses the ring:
// refining focal and distortion from the first pair on, COLMAP never
// registered a third view (seed 1; seed 6 likewise). The lens's distortion
// (k1 -0.08) stays unmodelled, and still the rock comes out within 1 %
// (measured V +0.62 %, a/b/c +0.05 / -0.75 / -0.28 %, centres 7.2 / 3.8 mm).
TEST(SfmReconstruct, AutoWithoutCalibrationPosesWithTheLensHint) {
  SKIP_WITHOUT_COLMAP();
  test::TempDir tmp;
  const uint64_t seed =
      1;  // seed 6's side 1 breaks COLMAP's ring at 12 views (pairs without matches)
  const std::string sample = CaptureAndReconstruct(tmp.path(), seed, false, PosesPath::kAuto);
  ASSERT_FALSE(sample.empty());
  ExpectSfmSide(sample, 1, "sfm (focal hint held)");
  ExpectSfmSide(sample, 2, "sfm side1");
  const json cal = ReadJsonFile(sample + "/results/calibration_used.json");
  EXPECT_EQ(cal["method"], "sfm");
  Config c;
  c.sim.seed = seed;
  sim::SimWorld world(c);
  const RigCalibration truth = world.TruthCalibration(kWidth, kHeight);
  auto used = CalibrationFromJson(cal, "calibration_used");
  ASSERT_TRUE(used) << used.error().ToString();
  std::printf("SfM camera: focal %.1f px (truth %.1f), k1 %.4f (%.4f)\n", used->camera.fx,
              truth.camera.fx, used->camera.k1, truth.camera.k1);
  // The hint, held: the nominal lens of the sample's config.
  EXPECT_NEAR(used->camera.fx, kWidth / 2.0 / std::tan(Config{}.sim.hfov_deg * M_PI / 360.0), 1e-3);
  EXPECT_NEAR(used->camera.fx / truth.camera.fx, 1.0, 0.01);
  for (int side : {1, 2}) {
    const double worst = WorstCentreErrorMm(sample, side, seed);
    std::printf("side %d: worst camera centre error %.2f mm\n", side, worst);
    EXPECT_LT(worst, 15.0);
  }
  ExpectMorphology(sample, 0.05, 0.04);
  // Its camera is SfM's: the turntable path cannot take the sample over
  // without a rig calibration, and says what to do.
  ReconstructOptions opts;
  opts.poses = PosesPath::kTurntable;
  auto st = ReconstructSample(sample, opts);
  ASSERT_FALSE(st);
  EXPECT_NE(st.error().message.find("no rig calibration"), std::string::npos) << st.error().message;
  EXPECT_NE(st.error().message.find("aggscan calibrate"), std::string::npos) << st.error().message;
  EXPECT_NE(st.error().message.find("--poses sfm"), std::string::npos) << st.error().message;
}

// A model whose references do not fit is rejected, never reported: here the
// sample's config places the red label 30 mm from where it lies. Nothing of
// the poses is written; the error names the side and what to do. With the
// config right again the run resumes: COLMAP's finished steps are reused.
TEST(SfmReconstruct, LabelsThatDoNotFitRejectTheSideAndTheRunResumes) {
  SKIP_WITHOUT_COLMAP();
  test::TempDir tmp;
  // Seed 1: its SfM model passes every check (seed 8's fails ring_angles,
  // 6.2 deg at one view, and is refused before the labels are looked at).
  const std::string sample = Capture(tmp.path(), 1, 1, true);
  const std::string cfg_path = sample + "/config.toml";
  const std::string good = *ReadFile(cfg_path);
  const std::regex red(R"((color = "red"[^\[]*?x_mm = )120(\.0)?)");
  ASSERT_TRUE(std::regex_search(good, red)) << good;
  ASSERT_TRUE(WriteFileAtomic(cfg_path, std::regex_replace(good, red, "$01150.0")));
  ReconstructOptions opts;
  opts.poses = PosesPath::kSfm;
  auto st = ReconstructSample(sample, opts);
  ASSERT_FALSE(st);
  const std::string msg = st.error().message;
  EXPECT_NE(msg.find("side1"), std::string::npos) << msg;
  EXPECT_NE(msg.find("rejected"), std::string::npos) << msg;
  EXPECT_NE(msg.find("measure the label positions"), std::string::npos) << msg;
  EXPECT_FALSE(fs::exists(sample + "/results/poses_side1.json"));
  EXPECT_FALSE(fs::exists(sample + "/results/morphology.json"));

  ASSERT_TRUE(WriteFileAtomic(cfg_path, good));
  st = ReconstructSample(sample, opts);
  ASSERT_TRUE(st) << st.error().ToString();
  const json p = ReadJsonFile(sample + "/results/poses_side1.json");
  for (const auto& t : p["sfm"]["timings_s"]) {
    if (t["step"] == "feature_extractor" || t["step"] == "matcher" || t["step"] == "mapper") {
      EXPECT_TRUE(t["skipped"].get<bool>()) << t.dump();
    }
  }
  // A kill during the surface stage: only it and the morphology run again.
  const std::string res = sample + "/results/";
  const auto poses_time = fs::last_write_time(res + "poses_side1.json");
  const auto model_time = fs::last_write_time(res + "sfm/side1/images.txt");
  const double volume =
      ReadJsonFile(res + "morphology.json")["morphology_3d"]["volume_mm3"].get<double>();
  fs::remove(res + "surface.json");
  fs::remove(res + "morphology.json");
  st = ReconstructSample(sample, opts);
  ASSERT_TRUE(st) << st.error().ToString();
  EXPECT_EQ(fs::last_write_time(res + "poses_side1.json"), poses_time);
  EXPECT_EQ(fs::last_write_time(res + "sfm/side1/images.txt"), model_time);
  EXPECT_DOUBLE_EQ(
      ReadJsonFile(res + "morphology.json")["morphology_3d"]["volume_mm3"].get<double>(), volume);
  EXPECT_EQ(ReadJsonFile(res + "calibration_used.json")["method"], "sim-truth");
}

// Sidecar angles that contradict the photos (views 3 and 5 swapped, as if
// the photos were filed out of order): COLMAP still builds a self-consistent
// ring, but the views' places on it disagree with the angles by 60 deg; the
// ring check rejects the model and nothing is reported.
TEST(SfmReconstruct, AnglesContradictingThePhotosAreRejected) {
  SKIP_WITHOUT_COLMAP();
  test::TempDir tmp;
  const std::string sample = Capture(tmp.path(), 1, 1, true);
  ASSERT_TRUE(ProcessSample(sample, WorkerOptions{}));  // masks and the side result
  const std::string side_path = SideResultPath(sample, 1);
  json side = ReadJsonFile(side_path);
  json& views = side["views"];
  ASSERT_GT(views.size(), 5u);
  std::swap(views[3]["measured_angle_deg"], views[5]["measured_angle_deg"]);
  ASSERT_TRUE(WriteFileAtomic(side_path, side.dump(2)));
  ReconstructOptions opts;
  opts.poses = PosesPath::kSfm;
  auto st = ReconstructSample(sample, opts);
  ASSERT_FALSE(st);
  const std::string msg = st.error().message;
  std::printf("%s\n", msg.c_str());
  EXPECT_NE(msg.find("side1"), std::string::npos) << msg;
  EXPECT_NE(msg.find("SfM model rejected: check ring_"), std::string::npos) << msg;
  EXPECT_FALSE(fs::exists(sample + "/results/poses_side1.json"));
  EXPECT_FALSE(fs::exists(sample + "/results/morphology.json"));
}

// The setting: parsed names, the CLI's --poses choices, the config's
// [worker] poses validated with a clear error.
TEST(SfmReconstruct, PosesSettingIsValidated) {
  PosesPath p = PosesPath::kTurntable;
  EXPECT_TRUE(ParsePosesPath("sfm", &p));
  EXPECT_EQ(p, PosesPath::kSfm);
  EXPECT_TRUE(ParsePosesPath("auto", &p));
  EXPECT_EQ(p, PosesPath::kAuto);
  EXPECT_FALSE(ParsePosesPath("colmap", &p));
  EXPECT_EQ(p, PosesPath::kAuto);
  test::TempDir tmp;
  {
    std::ostringstream out, err;
    EXPECT_EQ(RunReconstructCommand({tmp.path(), "--poses", "colmap"}, out, err), 2);
    EXPECT_NE(err.str().find("sfm"), std::string::npos) << err.str();
  }
  const std::string cfg = tmp.path() + "/bad.toml";
  std::ofstream(cfg) << "[worker]\nposes = \"colmap\"\n";
  std::vector<ConfigProblem> problems;
  auto c = LoadConfigFile(cfg, &problems);
  ASSERT_FALSE(c);
  ASSERT_EQ(problems.size(), 1u);
  EXPECT_EQ(problems[0].key, "worker.poses");
  EXPECT_NE(problems[0].ToString().find("sfm"), std::string::npos) << problems[0].ToString();
  std::ofstream(cfg) << "[worker]\nposes = \"auto\"\n";
  problems.clear();
  auto ok = LoadConfigFile(cfg, &problems);
  ASSERT_TRUE(ok) << ok.error().ToString();
  EXPECT_EQ(ok->worker.poses, "auto");
  EXPECT_EQ(Config{}.worker.poses, "turntable+ba");
}

}  // namespace
}  // namespace aggscan
