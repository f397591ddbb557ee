// The Blender validation renderer: looks parsed and cycled; a small simulated
// capture redrawn by Blender (a few low-resolution views) keeps the sample
// format (manifests, decodable photos) and the geometry (Blender's
// silhouettes against the sim's for the same poses); a board capture drawn by
// Blender calibrates the rig; bad input is refused with what to do. Skips
// where Debian's blender is not installed.
#include "cli/blender_render.h"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <set>
#include <sstream>

#include "cli/sim_capture.h"
#include "common/fsutil.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "drivers/sim/world.h"
#include "pipeline/calib/calibrate.h"
#include "pipeline/core/image_io.h"
#include "pipeline/masks/mask.h"
#include "pipeline/masks/mask_dataset.h"
#include "pipeline/worker/side_job.h"
#include "store/empty_turntable.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

TEST(BlenderLook, ParsesAndNamesWhatIsWrong) {
  auto l = ParseBlenderLook("surface=wood,light=low-sun,stone=dolomite,seed=7");
  ASSERT_TRUE(l) << l.error().ToString();
  EXPECT_EQ(l->Name(), "wood/low-sun/dolomite");
  EXPECT_EQ(l->seed, 7u);
  auto d = ParseBlenderLook("stone=basalt");
  ASSERT_TRUE(d);
  EXPECT_EQ(d->Name(), "light-grey/softbox/basalt");
  auto bad = ParseBlenderLook("surface=carpet");
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find(
                "surface 'carpet' is not one of white, light-grey, wood, rubber-mat, gravel"),
            std::string::npos)
      << bad.error().message;
  bad = ParseBlenderLook("colour=red");
  ASSERT_FALSE(bad);
  EXPECT_NE(bad.error().message.find("unknown key 'colour'"), std::string::npos)
      << bad.error().message;
  EXPECT_FALSE(ParseBlenderLook("seed=x"));
}

TEST(BlenderLook, TwentyRocksSeeEverySurfaceWithEveryLightAndEveryStoneOnFourSurfaces) {
  std::set<std::string> pairs;
  std::map<std::string, std::set<std::string>> stone_surfaces;
  for (int i = 0; i < 20; ++i) {
    const BlenderLook l = BatchLook(i, 1);
    pairs.insert(l.surface + "+" + l.light);
    stone_surfaces[l.stone].insert(l.surface);
  }
  EXPECT_EQ(pairs.size(), 20u);
  ASSERT_EQ(stone_surfaces.size(), 4u);
  for (const auto& [stone, surfaces] : stone_surfaces) EXPECT_GE(surfaces.size(), 4u) << stone;
  // The first ten (a benchmark's minimum) already have every value of each.
  std::set<std::string> s, li, st;
  for (int i = 0; i < 10; ++i) {
    const BlenderLook l = BatchLook(i, 1);
    s.insert(l.surface), li.insert(l.light), st.insert(l.stone);
  }
  EXPECT_EQ(s.size(), 5u);
  EXPECT_EQ(li.size(), 4u);
  EXPECT_EQ(st.size(), 4u);
  // The hard cases among them: dark on dark, yellow on wood.
  std::set<std::string> looks;
  for (int i = 0; i < 10; ++i) looks.insert(BatchLook(i, 1).surface + "+" + BatchLook(i, 1).stone);
  EXPECT_TRUE(looks.count("rubber-mat+basalt"));
  EXPECT_TRUE(looks.count("wood+dolomite"));
}

// A sim capture of `views` views on one side, lens distortion off.
std::string Capture(const std::string& dir, const std::string& scene, int views,
                    bool distortion = false) {
  const std::string cfg = dir + "/capture.toml";
  std::ofstream(cfg) << "[capture]\nprofile = \"custom\"\nsides = 1\nviews_per_side = " << views
                     << "\nstep_deg = " << (views >= 8 ? 360.0 / views : 30.0) << "\n"
                     << (distortion ? "" : "[sim]\nk1 = 0.0\nk2 = 0.0\n");
  SimCaptureOptions o;
  o.seed = 5;
  o.out = dir + "/" + scene;
  o.config_path = cfg;
  o.width = 640;
  o.height = 480;
  o.scene = scene;
  std::ostringstream out, err;
  EXPECT_EQ(RunSimCapture(o, out, err), 0) << err.str();
  return o.out;
}

BlenderOptions Fast() {
  BlenderOptions b;
  b.samples = 4;
  b.denoise = false;  // Cycles' frames as they come: the geometry checks need no camera
  b.frame_timeout_s = 300;
  return b;
}

TEST(BlenderRender, RedrawnViewsKeepTheSampleFormatAndTheSimsGeometry) {
  if (!BlenderAvailable())
    GTEST_SKIP() << "Debian's blender is not installed (scripts/install-deps.sh)";
  test::TempDir tmp;
  const std::string sample = Capture(tmp.path(), "rock", 3);
  std::map<std::string, std::string> before;
  for (int v = 0; v < 3; ++v) {
    char name[64];
    std::snprintf(name, sizeof name, "/side1/view_%03d.jpg", v);
    before[name] = ReadFile(sample + name).value();
  }
  std::ostringstream log;
  auto look = ParseBlenderLook("surface=rubber-mat,light=low-sun,stone=basalt");
  ASSERT_TRUE(look);
  auto rep = RerenderWithBlender(sample, *look, Fast(), log);
  ASSERT_TRUE(rep) << rep.error().ToString() << "\n" << log.str();
  std::printf(
      "%s: %d frames of 640x480 at 4 samples/px, %.2f s a frame (%.2f max), %.1f s in all; "
      "silhouettes vs "
      "the sim's IoU min %.4f mean %.4f\n",
      rep->renderer.c_str(), rep->frames, rep->mean_frame_s, rep->max_frame_s, rep->wall_s,
      rep->silhouette_iou_min, rep->silhouette_iou_mean);
  EXPECT_EQ(rep->frames, 3);
  EXPECT_GT(rep->mean_frame_s, 0);
  // Same camera, poses and mesh: the path tracer's silhouettes are the sim's
  // up to the pixels the outline crosses.
  EXPECT_GT(rep->silhouette_iou_min, 0.98);

  // Every photo replaced, decodable, its manifest entry's size matching.
  const json manifest = json::parse(ReadFile(sample + "/side1/manifest.json").value());
  ASSERT_EQ(manifest["views"].size(), 3u);
  for (const json& v : manifest["views"]) {
    const std::string path = sample + "/side1/" + v["image"].get<std::string>();
    EXPECT_EQ(v["bytes"].get<uint64_t>(), fs::file_size(path)) << path;
    const std::string bytes = ReadFile(path).value();
    EXPECT_NE(bytes, before["/side1/" + v["image"].get<std::string>()])
        << path << " was not redrawn";
    auto img = LoadImage(path, ImageMode::kColor);
    ASSERT_TRUE(img) << img.error().ToString();
    EXPECT_EQ(img->cols, 640);
    EXPECT_EQ(img->rows, 480);
  }
  // The truth: the renderer's silhouettes, the renderer and the look recorded.
  const json truth = json::parse(ReadFile(sample + "/truth.json").value());
  EXPECT_EQ(truth["renderer"]["look"]["name"], "rubber-mat/low-sun/basalt");
  EXPECT_EQ(truth["renderer"]["frames"], 3);
  EXPECT_TRUE(truth.contains("volume_mm3"));
  const cv::Mat mask = cv::imread(sample + "/truth/side1/view_000_mask.pgm", cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(mask.empty());
  EXPECT_GT(cv::countNonZero(mask), 2000);
  // A dark stone on a dark mat in a low sun: the photo is not blank, and the
  // rock is darker than the sim's grey granite would be but not black.
  const cv::Mat photo = cv::imread(sample + "/side1/view_000.jpg", cv::IMREAD_GRAYSCALE);
  const double rock_mean = cv::mean(photo, mask)[0];
  EXPECT_GT(rock_mean, 5) << "rock mean level";
  EXPECT_LT(rock_mean, 150) << "rock mean level";
}

// The environment's empty-turntable photos: side 1's views drawn again with
// the rock taken away, stored as the sample's own set (SAMPLE/empty/) at the
// angles the turntable measured. Away from the rock and its shadow they are
// the view's photo; where the rock stood they show the disc, not the rock;
// and the mask made against them holds the dolomite on the wooden disc.
TEST(BlenderRender, EmptyTurntablePhotosAreTheViewsWithoutTheRock) {
  if (!BlenderAvailable())
    GTEST_SKIP() << "Debian's blender is not installed (scripts/install-deps.sh)";
  test::TempDir tmp;
  const std::string sample = Capture(tmp.path(), "rock", 2);
  std::ostringstream log;
  auto look = ParseBlenderLook("surface=wood,light=two-lights,stone=dolomite");
  ASSERT_TRUE(look);
  BlenderOptions o = Fast();
  o.empty_plates = true;
  auto rep = RerenderWithBlender(sample, *look, o, log);
  ASSERT_TRUE(rep) << rep.error().ToString() << "\n" << log.str();
  EXPECT_EQ(rep->frames, 2);
  auto set = LoadEmptyTurntableSet(sample + "/empty");
  ASSERT_TRUE(set) << set.error().ToString();
  ASSERT_EQ(set->views.size(), 2u);
  const json rec = json::parse(*ReadFile(sample + "/sample.json"));
  EXPECT_EQ(rec["empty_turntable"]["set"], set->id);
  for (int v = 0; v < 2; ++v) {
    char name[64];
    std::snprintf(name, sizeof name, "view_%03d", v);
    const std::string side_dir = sample + "/side1";
    EXPECT_DOUBLE_EQ(set->views[static_cast<size_t>(v)].angle_deg,
                     MeasuredAngle(side_dir, std::string(name) + ".json"));
    const cv::Mat color = cv::imread(side_dir + "/" + name + ".jpg", cv::IMREAD_COLOR);
    const cv::Mat empty_color =
        cv::imread(sample + "/empty/" + set->views[static_cast<size_t>(v)].image, cv::IMREAD_COLOR);
    const cv::Mat rock =
        cv::imread(sample + "/truth/side1/" + name + "_mask.pgm", cv::IMREAD_GRAYSCALE) > 127;
    ASSERT_FALSE(empty_color.empty()) << "no empty-turntable photo for " << name;
    ASSERT_EQ(empty_color.size(), color.size());
    ASSERT_GT(cv::countNonZero(rock), 2000);
    cv::Mat photo, empty, near_rock, diff;
    cv::cvtColor(color, photo, cv::COLOR_BGR2GRAY);
    cv::cvtColor(empty_color, empty, cv::COLOR_BGR2GRAY);
    cv::dilate(rock, near_rock, cv::Mat(), cv::Point(-1, -1), 60);
    cv::absdiff(photo, empty, diff);
    const double far_diff = cv::mean(diff, ~near_rock)[0], rock_diff = cv::mean(diff, rock)[0];
    const double plain = MaskIoUIgnoring(ComputeForegroundMask(color), rock);
    const double with =
        MaskIoUIgnoring(ComputeForegroundMask(color, empty_color, MaskOptions{}), rock);
    std::printf(
        "%s: photo vs empty turntable, mean |difference| %.2f levels away from the rock, "
        "%.1f where it stood; masks vs truth IoU %.4f without it, %.4f with it\n",
        name, far_diff, rock_diff, plain, with);
    EXPECT_LT(far_diff, 3.0) << name << ": the rest of the scene changed";
    EXPECT_GT(rock_diff, 10.0) << name << ": the rock is still there";
    // The masks' trouble on these renders is the shadow, with or without the
    // empty turntable (docs/validation.md); a photo matched to the wrong
    // angle or view would lose the rock.
    EXPECT_GE(with, 0.6) << name;
  }
  // No stray compositor output left next to the frames.
  for (const auto& e : fs::recursive_directory_iterator(sample + "/blender/empty"))
    EXPECT_EQ(e.path().string().find("frame0001"), std::string::npos) << e.path();
}

// The denoiser (scripts/blender/denoise.py): a view at 4 samples per pixel,
// as it comes and denoised, against the same view at 32. Around the rock (its
// soft shadow's penumbra, the disc) the denoised frame is nearer the
// 32-sample one; on the rock the stone's grain is still there (its
// pixel-to-pixel detail within x0.67..x1.5 of the 32-sample frame's: not
// smoothed away, not the aliasing of a texture sampled at 4 points a pixel).
TEST(BlenderRender, DenoisedFramesLoseThePathTracersNoiseAndKeepTheGrain) {
  if (!BlenderAvailable())
    GTEST_SKIP() << "Debian's blender is not installed (scripts/install-deps.sh)";
  test::TempDir tmp;
  auto look = ParseBlenderLook("surface=light-grey,light=softbox,stone=granite");
  ASSERT_TRUE(look);
  auto render = [&](const std::string& name, int samples, bool denoise) {
    const std::string dir = tmp.path() + "/" + name;
    fs::create_directories(dir);
    const std::string sample = Capture(dir, "rock", 1);
    BlenderOptions o = Fast();
    o.samples = samples;
    o.denoise = denoise;
    std::ostringstream log;
    auto rep = RerenderWithBlender(sample, *look, o, log);
    EXPECT_TRUE(rep) << (rep ? "" : rep.error().ToString()) << "\n" << log.str();
    if (rep) std::printf("%s: %.2f s a frame\n", name.c_str(), rep->mean_frame_s);
    cv::Mat g = cv::imread(sample + "/side1/view_000.jpg", cv::IMREAD_GRAYSCALE), f;
    if (!g.empty()) g.convertTo(f, CV_32F);
    return f;
  };
  const cv::Mat noisy = render("noisy", 4, false);
  const cv::Mat clean = render("denoised", 4, true);
  const cv::Mat ref = render("converged", 32, false);
  ASSERT_FALSE(noisy.empty());
  ASSERT_FALSE(clean.empty());
  ASSERT_FALSE(ref.empty());
  ASSERT_EQ(clean.size(), ref.size());
  const cv::Mat rock = cv::imread(tmp.path() + "/converged/rock/truth/side1/view_000_mask.pgm",
                                  cv::IMREAD_GRAYSCALE) > 127;
  ASSERT_GT(cv::countNonZero(rock), 2000);
  cv::Mat near_rock, inner;
  cv::dilate(rock, near_rock, cv::Mat(), cv::Point(-1, -1), 40);
  near_rock &= ~rock;
  cv::erode(rock, inner, cv::Mat(), cv::Point(-1, -1), 3);
  auto rms = [](const cv::Mat& a, const cv::Mat& b, const cv::Mat& sel) {
    cv::Mat d = a - b;
    return std::sqrt(cv::mean(d.mul(d), sel)[0]);
  };
  // Fine detail: the RMS of a 1-px high-pass (the photo minus its 3x3 blur).
  auto detail = [](const cv::Mat& a, const cv::Mat& sel) {
    cv::Mat b;
    cv::blur(a, b, cv::Size(3, 3));
    cv::Mat d = a - b;
    return std::sqrt(cv::mean(d.mul(d), sel)[0]);
  };
  const double e_noisy = rms(noisy, ref, near_rock), e_clean = rms(clean, ref, near_rock);
  const double d_ref = detail(ref, inner), d_clean = detail(clean, inner);
  std::printf(
      "around the rock: RMS %.2f levels from the 32-sample frame as rendered, %.2f denoised; "
      "the stone's fine detail %.2f levels denoised, %.2f converged\n",
      e_noisy, e_clean, d_clean, d_ref);
  EXPECT_LT(e_clean, 0.7 * e_noisy);
  EXPECT_GT(d_clean, 0.67 * d_ref);
  EXPECT_LT(d_clean, 1.5 * d_ref);
  const json truth = json::parse(ReadFile(tmp.path() + "/denoised/rock/truth.json").value());
  EXPECT_EQ(truth["renderer"]["denoise"], true);
  EXPECT_FALSE(fs::exists(tmp.path() + "/denoised/rock/blender/passes"))
      << "pass files left behind";
}

TEST(BlenderRender, BoardDrawnByBlenderCalibratesTheRig) {
  if (!BlenderAvailable())
    GTEST_SKIP() << "Debian's blender is not installed (scripts/install-deps.sh)";
  test::TempDir tmp;
  const std::string sample = Capture(tmp.path(), "charuco", 8);
  std::ostringstream log;
  auto rep = RerenderWithBlender(sample, BlenderLook{}, Fast(), log);
  ASSERT_TRUE(rep) << rep.error().ToString();
  EXPECT_EQ(rep->frames, 8);
  Config c;
  auto cal = CalibrateSampleSide(sample, 1, c.calibration);
  ASSERT_TRUE(cal) << cal.error().ToString();
  c.camera.width = 640;
  c.camera.height = 480;
  c.sim.k1 = c.sim.k2 = 0;
  sim::SimWorld world(c);
  const RigCalibration truth = world.TruthCalibration(640, 480);
  const auto cc = cal->cal.CameraCentreTable0(), ct = truth.CameraCentreTable0();
  const double centre_mm =
      std::sqrt((cc[0] - ct[0]) * (cc[0] - ct[0]) + (cc[1] - ct[1]) * (cc[1] - ct[1]) +
                (cc[2] - ct[2]) * (cc[2] - ct[2]));
  std::printf(
      "Blender board capture, 8 views at 640x480: RMS %.3f px, fx %.2f (truth %.2f), camera centre "
      "%.2f mm "
      "from the truth\n",
      cal->cal.reprojection_rms_px, cal->cal.camera.fx, truth.camera.fx, centre_mm);
  EXPECT_LT(cal->cal.reprojection_rms_px, 0.5);
  EXPECT_NEAR(cal->cal.camera.fx, truth.camera.fx, 0.01 * truth.camera.fx);
  EXPECT_LT(centre_mm, 10.0);
}

TEST(BlenderRender, RefusesWhatItCannotDrawAndSaysWhatToDo) {
  test::TempDir tmp;
  std::ostringstream log;
  // No truth: not a simulated capture.
  fs::create_directories(tmp.path() + "/real");
  auto r = RerenderWithBlender(tmp.path() + "/real", BlenderLook{}, Fast(), log);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("has no truth.json"), std::string::npos) << r.error().message;
  // Lens distortion on: Blender's camera is a pinhole.
  const std::string distorted = Capture(tmp.path(), "rock", 1, /*distortion=*/true);
  r = RerenderWithBlender(distorted, BlenderLook{}, Fast(), log);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("k1 = 0 and k2 = 0"), std::string::npos) << r.error().message;
  // Blender missing.
  fs::create_directories(tmp.path() + "/b");
  const std::string sample = Capture(tmp.path() + "/b", "rock", 1);
  BlenderOptions none = Fast();
  none.blender = tmp.path() + "/no-such-blender";
  r = RerenderWithBlender(sample, BlenderLook{}, none, log);
  ASSERT_FALSE(r);
  EXPECT_NE(r.error().message.find("install Debian's blender"), std::string::npos)
      << r.error().message;
  // The photos are untouched after a failed run.
  const json m = json::parse(ReadFile(sample + "/side1/manifest.json").value());
  EXPECT_EQ(m["views"][0]["bytes"].get<uint64_t>(), fs::file_size(sample + "/side1/view_000.jpg"));
}

}  // namespace
}  // namespace aggscan
