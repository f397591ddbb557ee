// Writes the image target's seed corpus (tests/fuzz/corpus/image/): small
// rig-like views (synthetic_view.h) in the formats a view or a mask can come
// in, and edge cases of size and layout. Not part of the build; run once:
//   g++ -std=c++20 -w -I. -I/usr/include/opencv4 tests/fuzz/tools/make_image_seeds.cpp \
//       -lopencv_imgcodecs -lopencv_imgproc -lopencv_core -o /tmp/make_image_seeds
//   /tmp/make_image_seeds tests/fuzz/corpus/image
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include "tests/fuzz/synthetic_view.h"

namespace {

void Write(const std::string& path, const std::vector<unsigned char>& bytes) {
  std::ofstream(path, std::ios::binary)
      .write(reinterpret_cast<const char*>(bytes.data()), bytes.size());
  std::printf("%s %zu bytes\n", path.c_str(), bytes.size());
}

std::vector<unsigned char> Encode(const char* ext, const cv::Mat& m,
                                  const std::vector<int>& params = {}) {
  std::vector<unsigned char> out;
  cv::imencode(ext, m, out, params);
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) return 2;
  const std::string dir = argv[1];
  using aggscan::fuzz::SyntheticView;
  const cv::Mat v160 = SyntheticView(160, 120, 1);
  Write(dir + "/view_160x120.jpg", aggscan::fuzz::SyntheticViewJpeg(160, 120, 1));
  Write(dir + "/view_320x240_q75.jpg", aggscan::fuzz::SyntheticViewJpeg(320, 240, 2, 75));
  Write(dir + "/view_96x72_progressive.jpg",
        Encode(".jpg", SyntheticView(96, 72, 3),
               {cv::IMWRITE_JPEG_PROGRESSIVE, 1, cv::IMWRITE_JPEG_QUALITY, 85}));
  cv::Mat gray;
  cv::cvtColor(v160, gray, cv::COLOR_BGR2GRAY);
  Write(dir + "/view_gray.jpg", Encode(".jpg", gray));
  Write(dir + "/view_160x120.png", Encode(".png", v160, {cv::IMWRITE_PNG_COMPRESSION, 9}));
  cv::Mat mask;
  cv::threshold(gray, mask, 150, 255, cv::THRESH_BINARY_INV);
  Write(dir + "/mask_160x120.png", Encode(".png", mask, {cv::IMWRITE_PNG_COMPRESSION, 9}));
  cv::Mat v16;
  SyntheticView(64, 48, 4).convertTo(v16, CV_16U, 257.0);
  Write(dir + "/view_16bit.png", Encode(".png", v16));
  cv::Mat bgra;
  cv::cvtColor(SyntheticView(64, 48, 5), bgra, cv::COLOR_BGR2BGRA);
  Write(dir + "/view_alpha.png", Encode(".png", bgra));
  Write(dir + "/view_64x48.bmp", Encode(".bmp", SyntheticView(64, 48, 6)));
  Write(dir + "/view_32x24.ppm", Encode(".ppm", SyntheticView(32, 24, 7)));
  // Sizes the masks and figures must survive: one pixel, one row, one column.
  Write(dir + "/edge_1x1.jpg", Encode(".jpg", cv::Mat(1, 1, CV_8UC3, cv::Scalar(60, 80, 100))));
  Write(dir + "/edge_200x1.jpg", Encode(".jpg", SyntheticView(200, 2, 8).rowRange(0, 1).clone()));
  Write(dir + "/edge_1x200.png", Encode(".png", cv::Mat(200, 1, CV_8UC3, cv::Scalar(70, 95, 120))));
  // A JPEG cut short (a view whose write was interrupted before the store was durable).
  auto cut = aggscan::fuzz::SyntheticViewJpeg(160, 120, 9);
  cut.resize(cut.size() / 2);
  Write(dir + "/truncated.jpg", cut);
  return 0;
}
