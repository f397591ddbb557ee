// A small picture like the rig's: a grey-brown rock with shading on a white
// background, the four colour labels in the corners, sensor noise. Drawn the
// same on every call for the same arguments (fixed-seed RNG), so the worker
// target's views have a known size in bytes.
#pragma once

#include <cmath>
#include <cstdint>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

namespace aggscan::fuzz {

inline cv::Mat SyntheticView(int w, int h, uint32_t seed) {
  cv::Mat img(h, w, CV_8UC3, cv::Scalar(235, 238, 240));
  cv::RNG rng(seed);
  const cv::Point c(w / 2, h / 2);
  std::vector<cv::Point> rock;
  const int n = 11;
  for (int i = 0; i < n; ++i) {
    const double a = 2 * M_PI * i / n;
    const double r = std::min(w, h) * (0.22 + 0.08 * rng.uniform(0.0, 1.0));
    rock.emplace_back(c.x + static_cast<int>(1.3 * r * std::cos(a)),
                      c.y + static_cast<int>(r * std::sin(a)));
  }
  cv::ellipse(img, c + cv::Point(w / 40, h / 12), cv::Size(w / 4, h / 10), 0, 0, 360,
              cv::Scalar(190, 192, 195),
              cv::FILLED);  // soft shadow on the disc
  cv::fillPoly(img, std::vector<std::vector<cv::Point>>{rock}, cv::Scalar(70, 95, 120),
               cv::LINE_AA);
  cv::circle(img, c - cv::Point(w / 16, h / 16), std::min(w, h) / 8, cv::Scalar(95, 120, 145),
             cv::FILLED,
             cv::LINE_AA);  // lit face
  const int s = std::max(2, std::min(w, h) / 16);
  const cv::Scalar labels[4] = {
      {40, 40, 210}, {60, 170, 40}, {200, 80, 30}, {30, 200, 220}};  // R G B Y (BGR)
  const cv::Point corners[4] = {{s, s}, {w - 2 * s, s}, {s, h - 2 * s}, {w - 2 * s, h - 2 * s}};
  for (int i = 0; i < 4; ++i)
    cv::rectangle(img, cv::Rect(corners[i], cv::Size(s, s)), labels[i], cv::FILLED);
  cv::Mat noise(img.size(), CV_8UC3);
  rng.fill(noise, cv::RNG::NORMAL, cv::Scalar::all(0), cv::Scalar::all(3));
  img += noise;
  return img;
}

inline std::vector<unsigned char> SyntheticViewJpeg(int w, int h, uint32_t seed, int quality = 90) {
  std::vector<unsigned char> out;
  cv::imencode(".jpg", SyntheticView(w, h, seed), out, {cv::IMWRITE_JPEG_QUALITY, quality});
  return out;
}

}  // namespace aggscan::fuzz
