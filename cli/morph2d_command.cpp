#include "cli/morph2d_command.h"

#include <cstdio>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "pipeline/core/image_io.h"
#include "pipeline/masks/mask.h"
#include "pipeline/morph/morph2d.h"

namespace aggscan {
namespace {

// Single-channel 0/255 view of `img` if it is a binary mask, else empty.
cv::Mat AsBinaryMask(const cv::Mat& img) {
  if (img.depth() != CV_8U) return {};
  cv::Mat gray;
  if (img.channels() == 1) {
    gray = img;
  } else {
    std::vector<cv::Mat> ch;
    cv::split(img, ch);
    for (size_t i = 1; i < std::min<size_t>(ch.size(), 3); ++i)
      if (cv::countNonZero(ch[i] != ch[0]) > 0) return {};
    gray = ch[0];
  }
  if (cv::countNonZero((gray != 0) & (gray != 255)) > 0) return {};
  return gray;
}

int Morph2d(const std::string& path, bool json, std::ostream& out, std::ostream& err,
            const ImageLimits& limits);

}  // namespace

int RunMorph2dCommand(const std::string& path, bool json, std::ostream& out, std::ostream& err,
                      const ImageLimits& limits) {
  // Any library exception is this file's error, never the end of the process.
  try {
    return Morph2d(path, json, out, err, limits);
  } catch (const std::exception& e) {
    err << "morph2d: " << path << ": cannot be measured (" << e.what() << ")\n";
    return 2;
  }
}

namespace {

int Morph2d(const std::string& path, bool json, std::ostream& out, std::ostream& err,
            const ImageLimits& limits) {
  auto loaded = LoadImage(path, ImageMode::kUnchanged, limits);
  if (!loaded) {
    err << "morph2d: " << loaded.error().ToString() << "\n";
    return 2;
  }
  cv::Mat img = std::move(*loaded);
  if (img.depth() == CV_16U) img.convertTo(img, CV_8U, 1.0 / 257.0);
  cv::Mat mask = AsBinaryMask(img);
  const bool segmented = mask.empty();
  if (segmented) {
    cv::Mat bgr;
    if (img.channels() == 1)
      cv::cvtColor(img, bgr, cv::COLOR_GRAY2BGR);
    else if (img.channels() == 4)
      cv::cvtColor(img, bgr, cv::COLOR_BGRA2BGR);
    else
      bgr = img;
    if (bgr.depth() != CV_8U) {
      err << "morph2d: unsupported pixel format in " << path << "\n";
      return 2;
    }
    mask = ComputeForegroundMask(bgr);
  }
  auto m = ComputeMorph2D(mask);
  if (!m.ok()) {
    err << "morph2d: " << path << ": "
        << (segmented ? "no rock found in the image" : m.error().message) << "\n";
    return 1;
  }
  if (json) {
    nlohmann::json j = {{"l_max_px", m->l_max_px},
                        {"l_min_px", m->l_min_px},
                        {"fer_2d", m->fer_2d},
                        {"area_px", m->area_px},
                        {"perimeter_px", m->perimeter_px},
                        {"circularity", m->circularity},
                        {"input", segmented ? "image" : "mask"}};
    out << j.dump(2) << "\n";
  } else {
    char buf[512];
    std::snprintf(buf, sizeof buf,
                  "%s (%s)\n  L_max        %.2f px (at %.1f deg)\n  L_min        %.2f px\n  FER 2D "
                  "      %.4f\n"
                  "  area         %.0f px\n  perimeter    %.2f px\n  circularity  %.4f\n",
                  path.c_str(), segmented ? "segmented image" : "binary mask", m->l_max_px,
                  m->l_max_angle_deg, m->l_min_px, m->fer_2d, m->area_px, m->perimeter_px,
                  m->circularity);
    out << buf;
  }
  return 0;
}

}  // namespace

}  // namespace aggscan
