// `aggscan masks dataset | train | eval` on a small reconstructed sim sample
// (aggscan validate --keep at 1008 x 756, 12 views a side): the projected-mesh
// pairs match the renderer's silhouettes, two epochs of training export an
// ONNX model that MaskNet loads and runs, and bad input gets errors that say
// what to do. The training needs Debian's python3-torch and python3-opencv
// (skipped without them).
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>

#include "pipeline/masks/mask_dataset.h"
#include "pipeline/masks/mask_net.h"
#include "tests/util/shell.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

const std::string kAggscan = std::string(AGGSCAN_BINARY_DIR) + "/cli/aggscan";

using test::Shell;

bool TorchAvailable() {
  return std::system("/usr/bin/python3 -c 'import torch, cv2' >/dev/null 2>&1") == 0;
}

class MasksTrainTest : public ::testing::Test {
 protected:
  // One reconstructed sample for the whole suite (~1 min on 2 cores).
  static void SetUpTestSuite() {
    root_ = fs::temp_directory_path() / ("aggscan_masks_" + std::to_string(getpid()));
    fs::create_directories(root_);
    std::string out;
    const std::string cmd = kAggscan + " validate --count 1 --seed 1 --keep " +
                            (root_ / "sim").string() +
                            " --width 1008 --height 756 --views 12 --calibration truth";
    validate_rc_ = Shell(cmd, &out);
    validate_out_ = cmd + "\n" + out;
  }
  static void TearDownTestSuite() {
    std::error_code ec;
    fs::remove_all(root_, ec);
  }
  void SetUp() override {
    ASSERT_EQ(validate_rc_, 0) << validate_out_;
    sample_ = (root_ / "sim" / "seed-1").string();
    ASSERT_TRUE(fs::exists(sample_ + "/results/morphology.json")) << validate_out_;
  }
  static fs::path root_;
  static int validate_rc_;
  static std::string validate_out_;
  std::string sample_;
};
fs::path MasksTrainTest::root_;
int MasksTrainTest::validate_rc_ = -1;
std::string MasksTrainTest::validate_out_;

// The pairs come from the reconstruction alone: with the truth masks moved
// away the dataset is the same, and the projected silhouettes agree with the
// renderer's (the visual hull's excess is the only difference).
TEST_F(MasksTrainTest, DatasetIsTheMeshProjectedWithoutTheTruth) {
  const std::string ds = (root_ / "ds_projection").string();
  fs::rename(sample_ + "/truth", sample_ + "/truth.away");
  std::string out;
  const int rc = Shell(kAggscan + " masks dataset --out " + ds + " " + sample_, &out);
  fs::rename(sample_ + "/truth.away", sample_ + "/truth");
  ASSERT_EQ(rc, 0) << out;
  std::ifstream f(ds + "/index.json");
  const auto index = nlohmann::json::parse(f);
  ASSERT_EQ(index["pairs"].size(), 24u) << out;  // 2 sides x 12 views
  EXPECT_TRUE(fs::exists(ds + "/index.csv"));
  double lo = 1;
  for (const auto& p : index["pairs"]) {
    const cv::Mat mask = cv::imread(ds + "/" + p["mask"].get<std::string>(), cv::IMREAD_GRAYSCALE);
    const cv::Mat photo = cv::imread(ds + "/" + p["image"].get<std::string>(), cv::IMREAD_COLOR);
    char truth[64];
    std::snprintf(truth, sizeof truth, "/truth/side%d/view_%03d_mask.pgm", p["side"].get<int>(),
                  p["view"].get<int>());
    const cv::Mat t = cv::imread(sample_ + truth, cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(mask.empty());
    ASSERT_EQ(mask.size(), photo.size());
    ASSERT_EQ(mask.size(), t.size());
    cv::Mat nonbinary = (mask != 0) & (mask != 255);
    EXPECT_EQ(cv::countNonZero(nonbinary), 0);
    lo = std::min(lo, MaskIoUIgnoring(mask, t));
  }
  std::printf("projected mesh vs the renderer's silhouettes: IoU min %.4f\n", lo);
  EXPECT_GT(lo, 0.9);
}

TEST_F(MasksTrainTest, TrainsExportsAndTheWorkerRunsIt) {
  if (!TorchAvailable())
    GTEST_SKIP()
        << "/usr/bin/python3 lacks torch or cv2 (apt-get install python3-torch python3-opencv)";
  const std::string ds = (root_ / "ds_train").string();
  const std::string model = (root_ / "m.onnx").string();
  std::string out;
  ASSERT_EQ(Shell(kAggscan + " masks dataset --out " + ds + " " + sample_, &out), 0) << out;
  // An environment to teach: empty-turntable photos (here the sample's own
  // photos with the rock blurred away stand in for them).
  const fs::path empty = root_ / "empty";
  fs::create_directories(empty);
  for (int v = 0; v < 3; ++v) {
    char name[64];
    std::snprintf(name, sizeof name, "/side1/view_%03d.jpg", v);
    cv::Mat photo = cv::imread(sample_ + name, cv::IMREAD_COLOR), smooth;
    ASSERT_FALSE(photo.empty());
    cv::GaussianBlur(photo, smooth, cv::Size(0, 0), 40);
    ASSERT_TRUE(cv::imwrite((empty / ("empty_" + std::to_string(v) + ".jpg")).string(), smooth));
  }
  ASSERT_EQ(Shell(kAggscan + " masks train --dataset " + ds + " --out " + model +
                      " --epochs 2 --backgrounds " + empty.string(),
                  &out),
            0)
      << out;
  EXPECT_THAT(out, HasSubstr("method = \"onnx\""));
  EXPECT_TRUE(fs::exists(root_ / "m.mask.toml"));
  {
    std::ifstream f(model + ".json");
    const auto rep = nlohmann::json::parse(f);
    EXPECT_EQ(rep["background_photos"].get<int>(), 3);
    EXPECT_GT(rep["composite_share"].get<double>(), 0);
    ASSERT_EQ(rep["backgrounds"].size(), 1u);
    EXPECT_EQ(rep["backgrounds"][0].get<std::string>(), empty.string());
  }
  // Loaded and run as the worker does.
  MaskNetOptions o;
  o.model_path = model;
  auto net = MaskNet::Load(o);
  ASSERT_TRUE(net.ok()) << net.error().message;
  const cv::Mat photo = cv::imread(sample_ + "/side1/view_000.jpg", cv::IMREAD_COLOR);
  auto p = (*net)->Probability(photo);
  ASSERT_TRUE(p.ok()) << p.error().message;
  ASSERT_EQ(p->size(), photo.size());
  double lo, hi;
  cv::minMaxLoc(*p, &lo, &hi);
  EXPECT_GE(lo, 0.0);
  EXPECT_LE(hi, 1.0);
  EXPECT_TRUE(cv::checkRange(*p));
  auto m = (*net)->Mask(photo);
  ASSERT_TRUE(m.ok()) << m.error().message;
  EXPECT_EQ(m->type(), CV_8UC1);
  // The evaluation scores both methods on the same views.
  ASSERT_EQ(Shell(kAggscan + " masks eval --json --model " + model + " " + sample_ + " 2>/dev/null",
                  &out),
            0)
      << out;
  const auto report = nlohmann::json::parse(out.substr(out.find('{')));
  EXPECT_EQ(report["summary"]["all_simulated"]["classical"]["views"].get<int>(), 24);
  EXPECT_EQ(report["summary"]["all_simulated"]["trained"]["views"].get<int>(), 24);
  EXPECT_EQ(report["summary"]["by_split"]["trained on"]["classical"]["views"].get<int>(), 24);
  // --save writes every mask it scored.
  const std::string saved = (root_ / "saved").string();
  ASSERT_EQ(Shell(kAggscan + " masks eval --summary --model " + model + " --save " + saved + " " +
                      sample_,
                  &out),
            0)
      << out;
  for (const char* what : {"classical", "trained", "network"}) {
    const cv::Mat m =
        cv::imread(saved + "/seed-1/side2/view_011_" + what + ".png", cv::IMREAD_GRAYSCALE);
    ASSERT_EQ(m.size(), photo.size()) << what;
    EXPECT_EQ(cv::countNonZero((m != 0) & (m != 255)), 0) << what;
  }
  EXPECT_GT(cv::countNonZero(
                cv::imread(saved + "/seed-1/side2/view_011_classical.png", cv::IMREAD_GRAYSCALE)),
            1000);
}

TEST_F(MasksTrainTest, BadInputSaysWhatToDo) {
  std::string out;
  // A sample that was never reconstructed.
  const fs::path bare = root_ / "bare";
  fs::create_directories(bare / "side1");
  EXPECT_EQ(
      Shell(kAggscan + " masks dataset --out " + (root_ / "ds_bad").string() + " " + bare.string(),
            &out),
      1);
  EXPECT_THAT(out, HasSubstr("aggscan reconstruct"));
  // No dataset.
  EXPECT_EQ(Shell(kAggscan + " masks train --dataset " + (root_ / "none").string() + " --out " +
                      (root_ / "x.onnx").string(),
                  &out),
            1);
  EXPECT_THAT(out, HasSubstr("aggscan masks dataset"));
  // Backgrounds that are not there.
  EXPECT_EQ(Shell(kAggscan + " masks train --dataset " + (root_ / "none").string() + " --out " +
                      (root_ / "x.onnx").string() + " --backgrounds " +
                      (root_ / "no-such-folder").string(),
                  &out),
            2);
  EXPECT_THAT(out, HasSubstr("empty-turntable photos"));
  // A model file that is not ONNX.
  std::ofstream(root_ / "junk.onnx") << "not a network";
  EXPECT_EQ(
      Shell(kAggscan + " masks eval --model " + (root_ / "junk.onnx").string() + " " + sample_,
            &out),
      1);
  EXPECT_THAT(out, HasSubstr("cannot be read as an ONNX model"));
  // A threshold that is not a probability.
  EXPECT_EQ(Shell(kAggscan + " masks eval --threshold 1.5 " + sample_, &out), 2);
  EXPECT_THAT(out, HasSubstr("--threshold needs a probability between 0 and 1"));
  // No python with torch (a dataset of its own: ctest runs each test alone).
  fs::create_directories(root_ / "ds_nopython");
  std::ofstream(root_ / "ds_nopython" / "index.json") << "{\"pairs\": []}";
  EXPECT_EQ(Shell(kAggscan + " masks train --python /nonexistent/python3 --dataset " +
                      (root_ / "ds_nopython").string() + " --out " + (root_ / "y.onnx").string(),
                  &out),
            1);
  EXPECT_THAT(out, HasSubstr("python3-torch"));
  EXPECT_EQ(Shell(kAggscan + " masks frobnicate", &out), 2);
}

}  // namespace
}  // namespace aggscan
