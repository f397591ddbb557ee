// `aggscan import`: a folder written as a phone writes it (pixels stored
// sideways with EXIF orientation 6, the focal length and its 35 mm
// equivalent, the time each photo was taken, a pause while the rock was
// flipped) becomes a sample the worker measures; and what cannot work is
// refused before anything is written, naming the photo and what to do.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "cli/import_command.h"
#include "common/fsutil.h"
#include "config/config.h"
#include "drivers/sim/world.h"
#include "pipeline/core/exif.h"
#include "pipeline/worker/reconstruct.h"
#include "tests/reconstruct/sim_sample.h"
#include "tests/reconstruct/truth_check.h"
#include "tests/util/exif_write.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr int kW = 1008, kH = 756;

json ReadJsonFile(const std::string& path) {
  auto text = ReadFile(path);
  EXPECT_TRUE(text) << path;
  return text ? json::parse(*text) : json();
}

struct Outcome {
  int rc = 0;
  std::string out, err;
};

Outcome Import(const std::vector<std::string>& args) {
  std::ostringstream out, err;
  Outcome r;
  r.rc = RunImportCommand(args, out, err);
  r.out = out.str();
  r.err = err.str();
  return r;
}

std::string Stamp(int seconds) {
  // 2026-12-05 10:00:00 plus seconds (within the hour is enough here).
  char b[32];
  std::snprintf(b, sizeof b, "2026:12:05 10:%02d:%02d", seconds / 60, seconds % 60);
  return b;
}

// Writes photo `bgr` (upright) as a phone held in portrait stores it: the
// sensor's pixels a quarter turn off, EXIF orientation 6 to turn them back.
void WritePhonePhoto(const std::string& path, const cv::Mat& bgr, int seconds, int focal_35mm) {
  cv::Mat stored;
  cv::rotate(bgr, stored, cv::ROTATE_90_COUNTERCLOCKWISE);
  std::vector<unsigned char> jpeg;
  ASSERT_TRUE(cv::imencode(".jpg", stored, jpeg, {cv::IMWRITE_JPEG_QUALITY, 95}));
  test::PhoneExif x;
  x.orientation = 6;
  x.focal_mm = 4.25;
  x.focal_35mm = focal_35mm;
  x.pixel_x = stored.cols;
  x.pixel_y = stored.rows;
  x.datetime_original = Stamp(seconds);
  x.subsec = "250";
  x.exposure_s = 1.0 / 120;
  x.iso = 100;
  const std::vector<unsigned char> with = test::JpegWithExif(jpeg, x);
  ASSERT_TRUE(WriteFileAtomic(path, std::string(with.begin(), with.end())));
}

// A sim capture (a hand-turned table, 2 x 12 views) rewritten as a phone's
// camera roll: IMG_0001.JPG ... in the order taken, 3 s apart, a 90 s pause
// for the flip. Returns the sim sample (its truth) and fills `roll`.
std::string PhoneRoll(const std::string& dir, const std::string& roll, double* fx) {
  fs::create_directories(dir);
  const std::string sample = test::CaptureSimSample(dir, 1, 2, true, false, 12, kW, kH, 30.0,
                                                    "[turntable]\nbackend = \"manual\"\n");
  fs::create_directories(roll);
  Config c;
  sim::SimWorld world(c);
  *fx = world.TruthCalibration(kW, kH).camera.fx;
  // The 35 mm equivalent of the sim lens, as a phone rounds it (whole mm).
  const int f35 = static_cast<int>(std::lround(*fx * 43.2666 / std::hypot(kW, kH)));
  int n = 0, t = 0;
  for (int side = 1; side <= 2; ++side) {
    for (int v = 0; v < 12; ++v) {
      char name[64];
      std::snprintf(name, sizeof name, "/side%d/view_%03d.jpg", side, v);
      const cv::Mat bgr = cv::imread(sample + name);
      EXPECT_FALSE(bgr.empty()) << name;
      std::snprintf(name, sizeof name, "/IMG_%04d.JPG", ++n);
      WritePhonePhoto(roll + name, bgr, t, f35);
      t += 3;
    }
    t += 90;
  }
  return sample;
}

TEST(Exif, ReadsWhatAPhoneWrites) {
  test::TempDir tmp;
  const cv::Mat img(40, 60, CV_8UC3, cv::Scalar(90, 120, 150));
  WritePhonePhoto(tmp.path() + "/p.jpg", img, 75, 48);
  auto x = ReadExif(tmp.path() + "/p.jpg");
  ASSERT_TRUE(x) << x.error().ToString();
  EXPECT_EQ(x->Camera(), "Simphone S1");
  EXPECT_EQ(x->orientation, 6);
  ASSERT_TRUE(x->focal_mm);
  EXPECT_NEAR(*x->focal_mm, 4.25, 1e-9);
  EXPECT_EQ(x->focal_35mm, 48.0);
  EXPECT_EQ(x->pixel_x, 40);  // stored sideways
  ASSERT_TRUE(x->time_s);
  ASSERT_TRUE(ExifTimeSeconds("2026:12:05 10:00:00"));
  EXPECT_NEAR(*x->time_s - *ExifTimeSeconds("2026:12:05 10:00:00"), 75.25, 1e-9);
  ASSERT_TRUE(x->exposure_s);
  EXPECT_NEAR(*x->exposure_s, 1.0 / 120, 1e-5);
  EXPECT_EQ(x->iso, 100);
  // OpenCV turns it upright.
  const cv::Mat up = cv::imread(tmp.path() + "/p.jpg");
  EXPECT_EQ(up.cols, 60);
  EXPECT_EQ(up.rows, 40);
  // No EXIF is no error; no file is.
  std::vector<unsigned char> plain;
  ASSERT_TRUE(cv::imencode(".jpg", img, plain));
  ASSERT_TRUE(WriteFileAtomic(tmp.path() + "/plain.jpg", std::string(plain.begin(), plain.end())));
  auto none = ReadExif(tmp.path() + "/plain.jpg");
  ASSERT_TRUE(none);
  EXPECT_FALSE(none->orientation);
  EXPECT_EQ(none->Camera(), "");
  EXPECT_EQ(ReadExif(tmp.path() + "/missing.jpg").error().cls, ErrorClass::kNotFound);
  EXPECT_FALSE(ExifTimeSeconds("2026-12-05 10:00:00"));
}

// The phone's roll with a calibration of that phone: upright views, two
// sides found by the pause, and the rock measured through the labels.
TEST(Import, APhonesCameraRollIsMeasured) {
  test::TempDir tmp;
  double fx = 0;
  const std::string roll = tmp.path() + "/DCIM";
  const std::string truth_sample = PhoneRoll(tmp.path() + "/sim", roll, &fx);
  const std::string out = tmp.path() + "/rock-7";
  const Outcome r = Import(
      {roll, "--id", "rock-7", "--out", out, "--calibration", truth_sample + "/calibration.json"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_NE(r.out.find("2 side(s) by EXIF time"), std::string::npos) << r.out;
  const json rec = ReadJsonFile(out + "/sample.json");
  EXPECT_EQ(rec["state"], "captured");
  ASSERT_EQ(rec["sides"].size(), 2u);
  EXPECT_EQ(ReadJsonFile(out + "/import.json")["focal"], "EXIF FocalLengthIn35mmFilm");
  const json car = ReadJsonFile(out + "/side2/view_000.json");
  EXPECT_EQ(car["source_file"], "IMG_0013.JPG");
  EXPECT_EQ(car["exif_orientation"], 6);
  EXPECT_EQ(car["width"], kW);
  EXPECT_EQ(car["height"], kH);
  EXPECT_FALSE(car.contains("measured_angle_deg"));
  const cv::Mat v = cv::imread(out + "/side1/view_004.jpg");
  EXPECT_EQ(v.cols, kW);
  EXPECT_EQ(v.rows, kH);
  // The focal from the rounded 35 mm equivalent: within a mm in 48.
  auto cfg = LoadConfigFile(out + "/config.toml", nullptr);
  ASSERT_TRUE(cfg) << cfg.error().ToString();
  const double f_px = cfg->camera.lens_focal_mm / cfg->camera.sensor_width_mm * kW;
  EXPECT_NEAR(f_px / fx, 1.0, 0.012) << f_px << " vs " << fx;
  EXPECT_FALSE(PathExists(tmp.path() + "/.aggscan-import-rock-7")) << "the staging area goes";

  auto st = ReconstructSample(out, ReconstructOptions{});
  ASSERT_TRUE(st) << st.error().ToString();
  test::ExpectRockMatchesTruth(out, ReadJsonFile(truth_sample + "/truth.json"), "imported roll");
  auto m = ReadMorphology(out);
  ASSERT_TRUE(m) << m.error().ToString();
  EXPECT_EQ((*m)["methods"]["poses"].get<std::string>().rfind("turntable", 0), 0u)
      << (*m)["methods"].dump();
}

// A small folder of textured photos with the disc's labels drawn in, for
// the refusals (no reconstruction).
void TexturedPhotos(const std::string& dir, int n, bool labels, int width = 640) {
  fs::create_directories(dir);
  for (int i = 0; i < n; ++i) {
    cv::Mat img(width * 3 / 4, width, CV_8UC3);
    cv::randu(img, 40, 200);
    cv::GaussianBlur(img, img, cv::Size(0, 0), 1.2);
    if (labels) {
      // Saturated squares of the labels' colours, as on the disc.
      const cv::Scalar colours[] = {{40, 40, 220}, {60, 180, 60}, {200, 90, 30}, {40, 210, 230}};
      for (int k = 0; k < 4; ++k) {
        const int x = 60 + 140 * k, y = width * 3 / 4 - 80;
        cv::rectangle(img, cv::Rect(x, y, 34, 30), colours[k], cv::FILLED);
      }
    }
    char name[32];
    std::snprintf(name, sizeof name, "/p%02d.png", i);
    ASSERT_TRUE(cv::imwrite(dir + name, img));
  }
}

TEST(Import, WhatCannotWorkIsRefusedBeforeAnythingIsWritten) {
  test::TempDir tmp;
  // Too few views, and no scale reference.
  TexturedPhotos(tmp.path() + "/few", 5, false);
  Outcome r = Import({tmp.path() + "/few", "--id", "r1", "--out", tmp.path() + "/r1"});
  EXPECT_EQ(r.rc, 1);
  EXPECT_NE(r.err.find("side 1 has 5 usable photo(s); at least 8 are needed"), std::string::npos)
      << r.err;
  EXPECT_NE(r.err.find("a scale reference"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("--no-scale"), std::string::npos) << r.err;
  EXPECT_FALSE(PathExists(tmp.path() + "/r1"));
  const std::string out = tmp.path() + "/r2";

  // Out of focus and over-exposed photos are named; --skip-bad leaves them out.
  TexturedPhotos(tmp.path() + "/bad", 10, false);
  cv::Mat blurred = cv::imread(tmp.path() + "/bad/p03.png");
  cv::GaussianBlur(blurred, blurred, cv::Size(0, 0), 4.0);
  ASSERT_TRUE(cv::imwrite(tmp.path() + "/bad/p03.png", blurred));
  cv::Mat blown = cv::imread(tmp.path() + "/bad/p07.png");
  blown(cv::Rect(0, 0, blown.cols, blown.rows / 4)).setTo(cv::Scalar(255, 255, 255));
  ASSERT_TRUE(cv::imwrite(tmp.path() + "/bad/p07.png", blown));
  r = Import({tmp.path() + "/bad", "--id", "r2", "--out", out, "--no-scale"});
  EXPECT_EQ(r.rc, 1);
  EXPECT_NE(r.err.find("p03.png is out of focus"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("p07.png is over-exposed"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("--skip-bad"), std::string::npos) << r.err;
  EXPECT_FALSE(PathExists(out));
  r = Import({tmp.path() + "/bad", "--id", "r2", "--out", out, "--no-scale", "--skip-bad"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_NE(r.out.find("left out: p03.png is out of focus"), std::string::npos) << r.out;
  const json imp = ReadJsonFile(out + "/import.json");
  EXPECT_EQ(imp["left_out"].size(), 2u);
  EXPECT_TRUE(PathExists(out + "/side1/view_007.jpg"));
  EXPECT_FALSE(PathExists(out + "/side1/view_008.jpg"));
  EXPECT_EQ(imp["focal"], "none: the worker estimates it (SfM)");
  // Nothing is overwritten.
  r = Import({tmp.path() + "/bad", "--id", "r2", "--out", out, "--no-scale", "--skip-bad"});
  EXPECT_EQ(r.rc, 1);
  EXPECT_NE(r.err.find("exists; nothing is overwritten"), std::string::npos) << r.err;

  // Two sizes (two cameras) without a calibration.
  TexturedPhotos(tmp.path() + "/mixed", 9, true);
  TexturedPhotos(tmp.path() + "/mixed2", 1, true, 800);
  fs::rename(tmp.path() + "/mixed2/p00.png", tmp.path() + "/mixed/z.png");
  r = Import({tmp.path() + "/mixed", "--id", "r3", "--out", tmp.path() + "/r3"});
  EXPECT_EQ(r.rc, 1);
  EXPECT_NE(r.err.find("more than one camera or size"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("640x480"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("800x600"), std::string::npos) << r.err;
  EXPECT_FALSE(PathExists(tmp.path() + "/r3"));

  // Sub-folders and loose photos together; a lone focal hint; a bad id.
  TexturedPhotos(tmp.path() + "/both/side1", 8, true);
  TexturedPhotos(tmp.path() + "/both", 1, true);
  r = Import({tmp.path() + "/both", "--id", "r4", "--out", tmp.path() + "/r4"});
  EXPECT_EQ(r.rc, 1);
  EXPECT_NE(r.err.find("both in sub-folders and beside them"), std::string::npos) << r.err;
  EXPECT_EQ(Import({tmp.path() + "/both", "--id", "r4", "--focal-mm", "4.2"}).rc, 2);
  EXPECT_EQ(Import({tmp.path() + "/both", "--id", "../r4"}).rc, 2);
  EXPECT_EQ(Import({tmp.path() + "/both"}).rc, 2);
  // The worker knows a sample by its directory's name.
  r = Import({tmp.path() + "/both/side1", "--id", "r6", "--out", tmp.path() + "/elsewhere"});
  EXPECT_EQ(r.rc, 2);
  EXPECT_NE(r.err.find("named after its id"), std::string::npos) << r.err;
}

// One side per sub-folder, PNG photos, the focal from the user's hint.
TEST(Import, SidesFromSubFoldersAndTheFocalFromAHint) {
  test::TempDir tmp;
  TexturedPhotos(tmp.path() + "/rock/a-first", 8, true);
  TexturedPhotos(tmp.path() + "/rock/b-flipped", 9, true);
  const std::string out = tmp.path() + "/r5";
  const Outcome r = Import({tmp.path() + "/rock", "--id", "r5", "--out", out, "--focal-mm", "6",
                            "--sensor-mm", "7.2", "--no-scale"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_NE(r.out.find("2 side(s), one per sub-folder: 8 9 views"), std::string::npos) << r.out;
  EXPECT_EQ(ReadJsonFile(out + "/import.json")["focal"], "--focal-mm and --sensor-mm");
  EXPECT_EQ(ReadJsonFile(out + "/side2/view_008.json")["source_file"], "b-flipped/p08.png");
  auto cfg = LoadConfigFile(out + "/config.toml", nullptr);
  ASSERT_TRUE(cfg);
  EXPECT_DOUBLE_EQ(cfg->camera.lens_focal_mm, 6.0);
  EXPECT_DOUBLE_EQ(cfg->camera.sensor_width_mm, 7.2);
  EXPECT_EQ(cfg->capture.sides, 2);
  EXPECT_EQ(cfg->capture.views_per_side, 9);
}

// A phone walked round a rock: --moving-camera makes the sample one the
// worker poses by SfM alone, and says so in its config, sidecars and
// import.json.
TEST(Import, AWalkedCameraIsRecordedAsSuch) {
  test::TempDir tmp;
  TexturedPhotos(tmp.path() + "/walk/1", 8, true);
  const std::string out = tmp.path() + "/w1";
  const Outcome r = Import({tmp.path() + "/walk", "--id", "w1", "--out", out, "--focal-mm", "6",
                            "--sensor-mm", "7.2", "--no-scale", "--moving-camera"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_NE(r.out.find("SfM (a camera walked round the rock)"), std::string::npos) << r.out;
  auto cfg = LoadConfigFile(out + "/config.toml", nullptr);
  ASSERT_TRUE(cfg);
  EXPECT_EQ(cfg->capture.mode, "moving_camera");
  EXPECT_EQ(cfg->turntable.backend, "manual");
  EXPECT_EQ(cfg->worker.poses, "auto");
  EXPECT_EQ(ReadJsonFile(out + "/side1/view_003.json")["capture_mode"], "moving_camera");
  EXPECT_EQ(ReadJsonFile(out + "/import.json")["capture_mode"], "moving_camera");
}

// Real photos: Oxford VGG's dino, 37 frames of a figure on a turntable
// (720x576 PNG, no EXIF, no scale reference). Imported without a focal (its
// P matrices' intrinsics are not a pinhole's: a hint taken from them, held,
// bent the ring out of its plane), the worker masks it (the figure's head
// crosses the frame's top edge in five views: posed, not carved) and COLMAP
// registers the views; the run then stops at the scale, as it says.
TEST(Import, TheOxfordDinoRegistersItsViews) {
  const std::string images = std::string(AGGSCAN_SHARED_DATA) + "/multiview/oxford_dino/images";
  if (!fs::is_directory(images)) GTEST_SKIP() << "no data at " << images;
  if (!PathExists("/usr/bin/colmap")) GTEST_SKIP() << "needs Debian's colmap";
  test::TempDir tmp;
  const std::string out = tmp.path() + "/dino";
  const Outcome r = Import({images, "--id", "dino", "--out", out, "--no-scale"});
  ASSERT_EQ(r.rc, 0) << r.err;
  ReconstructOptions opts;
  opts.poses = PosesPath::kAuto;  // the sample's config says so; aggscan reconstruct reads it
  auto st = ReconstructSample(out, opts);
  ASSERT_FALSE(st) << "no scale reference in these photos";
  EXPECT_NE(st.error().message.find("no metric scale"), std::string::npos) << st.error().message;
  const json res = ReadJsonFile(out + "/work/side1/sfm/result.json");
  ASSERT_TRUE(res.is_object());
  EXPECT_TRUE(res.value("accepted", false)) << res["checks"].dump();
  const int registered = res.value("num_registered", 0);
  const int input = res.value("num_input_images", 0);
  std::printf("dino: %d of %d views registered, camera %s\n", registered, input,
              res["camera"].dump().c_str());
  EXPECT_EQ(input, 37);
  EXPECT_GE(registered, 34) << "90 % of 37";
  // The five views whose figure reaches the frame's edge were left out of
  // the 2D figures, not of the poses.
  const json side = ReadJsonFile(out + "/results/side1_morph2d.json");
  int cut = 0;
  for (const json& v : side["views"]) cut += v.value("cut_by_frame", false) ? 1 : 0;
  EXPECT_GE(cut, 1);
}

}  // namespace
}  // namespace aggscan
