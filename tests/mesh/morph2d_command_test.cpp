#include "cli/morph2d_command.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "tests/util/synth_scene.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;

std::string TempPath(const std::string& name) {
  return (fs::temp_directory_path() / ("aggscan_cli_" + std::to_string(::getpid()) + "_" + name))
      .string();
}

TEST(Morph2dCli, BinaryMaskJson) {
  cv::Mat m = cv::Mat::zeros(400, 400, CV_8UC1);
  cv::circle(m, {200, 200}, 100, cv::Scalar(255), cv::FILLED);
  const std::string p = TempPath("disc.png");
  ASSERT_TRUE(cv::imwrite(p, m));
  std::ostringstream out, err;
  ASSERT_EQ(RunMorph2dCommand(p, true, out, err), 0) << err.str();
  const auto j = nlohmann::json::parse(out.str());
  EXPECT_EQ(j["input"], "mask");
  EXPECT_NEAR(j["l_max_px"].get<double>(), 200, 3);
  EXPECT_NEAR(j["circularity"].get<double>(), 1.0, 0.02);
  for (const char* k : {"l_min_px", "fer_2d", "area_px", "perimeter_px"})
    EXPECT_TRUE(j[k].is_number()) << k;

  // Same mask as 3 identical channels: still a mask; text output.
  cv::Mat m3;
  cv::cvtColor(m, m3, cv::COLOR_GRAY2BGR);
  ASSERT_TRUE(cv::imwrite(p, m3));
  std::ostringstream text;
  ASSERT_EQ(RunMorph2dCommand(p, false, text, err), 0);
  EXPECT_NE(text.str().find("binary mask"), std::string::npos);
  EXPECT_NE(text.str().find("circularity"), std::string::npos);
  fs::remove(p);
}

TEST(Morph2dCli, PhotoIsSegmented) {
  testing::SceneParams sp;
  sp.size = {640, 480};
  const auto sc = testing::MakeScene(sp);
  const std::string p = TempPath("photo.jpg");
  std::ofstream(p, std::ios::binary)
      .write(reinterpret_cast<const char*>(sc.jpeg.data()),
             static_cast<std::streamsize>(sc.jpeg.size()));
  std::ostringstream out, err;
  ASSERT_EQ(RunMorph2dCommand(p, true, out, err), 0) << err.str();
  const auto j = nlohmann::json::parse(out.str());
  EXPECT_EQ(j["input"], "image");
  EXPECT_GT(j["area_px"].get<double>(), 0.8 * cv::countNonZero(sc.truth));
  fs::remove(p);
}

TEST(Morph2dCli, UnreadableInputReturns2) {
  std::ostringstream out, err;
  EXPECT_EQ(RunMorph2dCommand("/nonexistent/x.png", true, out, err), 2);
  EXPECT_NE(err.str().find("cannot read"), std::string::npos);
  const std::string p = TempPath("junk.png");
  std::ofstream(p) << "not an image";
  EXPECT_EQ(RunMorph2dCommand(p, false, out, err), 2);
  fs::remove(p);
  // An empty mask: readable, but nothing to measure.
  ASSERT_TRUE(cv::imwrite(p, cv::Mat::zeros(100, 100, CV_8UC1)));
  EXPECT_EQ(RunMorph2dCommand(p, false, out, err), 1);
  fs::remove(p);
}

}  // namespace
}  // namespace aggscan
