// A view that disagrees with the others must not make a silently wrong model:
// a JPEG with 200 bytes flipped inside its entropy-coded data (same size,
// libjpeg only warns) is left out by the side job, and a mask that lost part
// of the rock without any decoder warning is found by the consistency check
// (its carving alone removes rock every other view sees) and left out. Both
// give a volume close to the unbroken run's, with the view named.
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <string>

#include "common/fsutil.h"
#include "pipeline/worker/reconstruct.h"
#include "tests/reconstruct/sim_sample.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

json ReadJsonFile(const std::string& path) {
  std::ifstream in(path);
  return json::parse(in);
}

ReconstructOptions FastOptions() {
  ReconstructOptions o;
  o.bundle_adjust = false;
  o.photo_refine = false;
  return o;
}

// Flips 200 bytes spread over a stretch in the first half of the scan data.
void FlipScanBytes(const std::string& path, uint32_t seed) {
  std::string jpeg = *ReadFile(path);
  const size_t sos = jpeg.find("\xFF\xDA");
  ASSERT_NE(sos, std::string::npos);
  const size_t start = sos + 2 +
                       ((static_cast<unsigned char>(jpeg[sos + 2]) << 8) |
                        static_cast<unsigned char>(jpeg[sos + 3]));
  const size_t at = start + (jpeg.size() - 2 - start) / 3;
  std::mt19937 rng(seed);
  for (int i = 0; i < 200; ++i) {
    const size_t k = at + static_cast<size_t>(i) * 3;
    jpeg[k] = static_cast<char>(jpeg[k] ^ (1u + rng() % 255u));
  }
  const auto size = fs::file_size(path);
  std::ofstream(path, std::ios::binary | std::ios::trunc) << jpeg;
  ASSERT_EQ(fs::file_size(path), size);
}

bool AnyContains(const json& arr, const std::string& what) {
  for (const auto& w : arr)
    if (w.is_string() && w.get<std::string>().find(what) != std::string::npos) return true;
  return false;
}

TEST(BadViews, FlippedJpegAndLostMaskAreLeftOutAndNamed) {
  test::TempDir tmp;
  // One side of 12 views 30 deg apart, segmented by the worker.
  const std::string clean =
      test::CaptureSimSample(tmp.path(), 3, 1, true, false, 12, 1008, 756, 30.0);
  // Copies keep the directory name: it is the sample id.
  const std::string flipped = tmp.path() + "/flipped/sample";
  fs::create_directories(flipped);
  fs::copy(clean, flipped, fs::copy_options::recursive);
  FlipScanBytes(flipped + "/side1/view_004.jpg", 1);

  {
    auto st = ReconstructSample(clean, FastOptions());
    ASSERT_TRUE(st) << st.error().ToString();
  }
  const json mc = ReadJsonFile(clean + "/results/morphology.json");
  const double v_clean = mc["morphology_3d"]["volume_mm3"].get<double>();
  const double truth = ReadJsonFile(clean + "/truth.json")["volume_mm3"].get<double>();
  EXPECT_TRUE(mc["warnings"].empty()) << mc["warnings"].dump();
  const json sc = ReadJsonFile(clean + "/results/surface.json");
  EXPECT_TRUE(sc["views_left_out"].empty()) << sc["consistency"].dump();
  double worst = 0;
  for (const auto& v : sc["consistency"]["views"])
    worst = std::max(worst, v["sole_carving_mm3"].get<double>());
  std::printf(
      "clean: V %.0f mm3 (truth %.0f; one side, the floor adds the underside), worst sole carving "
      "%.0f mm3 "
      "(%.2f %% of %.0f), IoU min %.4f\n",
      v_clean, truth, worst, 100 * worst / sc["consistency"]["agreed_mm3"].get<double>(),
      sc["consistency"]["agreed_mm3"].get<double>(),
      mc["quality"]["silhouette_iou_min"].get<double>());

  // The flipped photo: the side job refuses to decode it, the view is left
  // out and named, the volume is the unbroken run's within 2 %.
  {
    auto st = ReconstructSample(flipped, FastOptions());
    ASSERT_TRUE(st) << st.error().ToString();
  }
  const json mf = ReadJsonFile(flipped + "/results/morphology.json");
  const double v_flipped = mf["morphology_3d"]["volume_mm3"].get<double>();
  EXPECT_NEAR(v_flipped, v_clean, 0.02 * v_clean);
  const json side = ReadJsonFile(flipped + "/results/side1_morph2d.json");
  EXPECT_EQ(side["views_ok"].get<int>(), 11);
  EXPECT_FALSE(side["views"][4]["ok"].get<bool>());
  EXPECT_NE(side["views"][4]["error"].get<std::string>().find("damaged JPEG data"),
            std::string::npos)
      << side["views"][4].dump();
  EXPECT_NE(side["views"][4]["error"].get<std::string>().find("re-shoot the side"),
            std::string::npos);
  EXPECT_TRUE(AnyContains(
      mf["warnings"],
      "side1: the photo of view 4 cannot be used (image side1/view_004.jpg: damaged JPEG data"))
      << mf["warnings"].dump();
  EXPECT_EQ(mf["views_2d"].size(), 11u);
  std::printf("flipped view 4: V %.0f mm3 (%+.2f %% of the clean run)\n", v_flipped,
              100 * (v_flipped / v_clean - 1));

  // A mask that lost the upper half of the rock with no decoder warning
  // (what a segmentation failure or a photo decoded half grey gives): the
  // consistency check leaves the view out and carves again.
  const std::string lost = tmp.path() + "/lost/sample";
  fs::create_directories(lost);
  fs::copy(clean, lost, fs::copy_options::recursive);
  for (const char* f :
       {"surface.json", "morphology.json", "mesh.ply", "mesh.obj", "mesh.stl", "stitch.json"})
    fs::remove(lost + "/results/" + f);
  const std::string mask_path = lost + "/results/masks/side1/view_007.png";
  cv::Mat mask = cv::imread(mask_path, cv::IMREAD_GRAYSCALE);
  ASSERT_FALSE(mask.empty());
  const cv::Rect box = cv::boundingRect(mask);
  mask(cv::Rect(box.x, box.y, box.width, box.height / 2)).setTo(0);
  ASSERT_TRUE(cv::imwrite(mask_path, mask));
  {
    auto st = ReconstructSample(lost, FastOptions());
    ASSERT_TRUE(st) << st.error().ToString();
  }
  const json ml = ReadJsonFile(lost + "/results/morphology.json");
  const json sl = ReadJsonFile(lost + "/results/surface.json");
  const double v_lost = ml["morphology_3d"]["volume_mm3"].get<double>();
  ASSERT_EQ(sl["views_left_out"].size(), 1u) << sl["consistency"].dump();
  EXPECT_EQ(sl["views_left_out"][0]["view"].get<int>(), 7);
  // Carving with it would have removed a large part of the rock.
  const double carved = sl["views_left_out"][0]["sole_carving_mm3"].get<double>();
  EXPECT_GT(carved, 0.15 * v_clean);
  EXPECT_EQ(sl["views"].get<int>(), 11);
  EXPECT_NEAR(v_lost, v_clean, 0.02 * v_clean);
  EXPECT_TRUE(AnyContains(ml["warnings"], "side1 view 7 left out of the model"))
      << ml["warnings"].dump();
  std::printf(
      "mask of view 7 half lost: its sole carving %.0f mm3 (%.0f %% of the clean volume); left "
      "out, V %.0f "
      "mm3 (%+.2f %% of the clean run)\n",
      carved, 100 * carved / v_clean, v_lost, 100 * (v_lost / v_clean - 1));
}

}  // namespace
}  // namespace aggscan
