#include "pipeline/masks/mask_net.h"

#include <filesystem>
#include <opencv2/imgproc.hpp>
#include <string>
#include <vector>

namespace aggscan {
namespace {

std::string ShapeText(const cv::Mat& m) {
  std::string s;
  for (int i = 0; i < m.dims; ++i) s += (i ? "x" : "") + std::to_string(m.size[i]);
  return s.empty() ? "empty" : s;
}

constexpr const char* kFixConfig = "fix mask.model or set mask.method = \"classical\"";

}  // namespace

MaskNetOptions MaskNetOptionsFromConfig(const MaskConfig& c) {
  MaskNetOptions o;
  o.model_path = c.model;
  o.input_size = cv::Size(c.input_width, c.input_height);
  o.mean_rgb = cv::Scalar(c.mean_r, c.mean_g, c.mean_b);
  o.std_rgb = cv::Scalar(c.std_r, c.std_g, c.std_b);
  o.logits = c.output == "logits";
  o.threshold = c.threshold;
  return o;
}

Result<std::unique_ptr<MaskNet>> MaskNet::Load(const MaskNetOptions& opts) {
  const std::string& path = opts.model_path;
  std::error_code ec;
  if (path.empty())
    return MakeError(ErrorClass::kInvalidConfig,
                     "mask network: no model file given; " + std::string(kFixConfig));
  if (!std::filesystem::is_regular_file(path, ec))
    return MakeError(ErrorClass::kInvalidConfig,
                     "mask network " + path +
                         " does not exist or is not a file; put the .onnx file there, " +
                         kFixConfig);
  if (opts.input_size.width < 1 || opts.input_size.height < 1)
    return MakeError(ErrorClass::kInvalidConfig, "mask network " + path +
                                                     ": input size must be positive; fix "
                                                     "mask.input_width / mask.input_height");
  cv::dnn::Net net;
  try {
    net = cv::dnn::readNetFromONNX(path);
  } catch (const cv::Exception& e) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "mask network " + path +
                         " cannot be read as an ONNX model (corrupt, truncated, or ops "
                         "OpenCV DNN does not support); re-export it or " +
                         kFixConfig,
                     e.what());
  }
  if (net.empty())
    return MakeError(ErrorClass::kInvalidConfig,
                     "mask network " + path + " holds no layers; re-export it or " + kFixConfig);
  net.setPreferableBackend(cv::dnn::DNN_BACKEND_OPENCV);
  net.setPreferableTarget(cv::dnn::DNN_TARGET_CPU);
  std::unique_ptr<MaskNet> m(new MaskNet(opts, net));
  // One pass on a blank photo: the model must take the configured input and
  // give one map.
  auto out = m->Forward(cv::Mat(opts.input_size, CV_8UC3, cv::Scalar(128, 128, 128)));
  if (!out.ok()) return out.error();
  return {std::move(m)};
}

Result<cv::Mat> MaskNet::Forward(const cv::Mat& bgr) {
  const std::string& path = opts_.model_path;
  cv::Mat rgb;
  cv::resize(bgr, rgb, opts_.input_size, 0, 0, cv::INTER_AREA);
  cv::cvtColor(rgb, rgb, cv::COLOR_BGR2RGB);
  rgb.convertTo(rgb, CV_32FC3, 1.0 / 255.0);
  cv::subtract(rgb, opts_.mean_rgb, rgb);
  cv::divide(rgb, opts_.std_rgb, rgb);
  const cv::Mat blob =
      cv::dnn::blobFromImage(rgb, 1.0, cv::Size(), cv::Scalar(), false, false, CV_32F);
  cv::Mat out;
  {
    std::lock_guard<std::mutex> lock(mu_);
    try {
      net_.setInput(blob);
      out = net_.forward();
    } catch (const cv::Exception& e) {
      return MakeError(
          ErrorClass::kInvalidConfig,
          "mask network " + path + " does not run on a 1x3x" +
              std::to_string(opts_.input_size.height) + "x" +
              std::to_string(opts_.input_size.width) +
              " RGB input; check mask.input_width / mask.input_height against the model, or " +
              kFixConfig,
          e.what());
    }
  }
  // 1x1xhxw, 1xhxw or hxw: one map.
  int lead = 1;
  for (int i = 0; i + 2 < out.dims; ++i) lead *= out.size[i];
  if (out.empty() || out.dims < 2 || out.dims > 4 || lead != 1 || out.size[out.dims - 2] < 2 ||
      out.size[out.dims - 1] < 2)
    return MakeError(ErrorClass::kInvalidConfig,
                     "mask network " + path + " gives an output of shape " + ShapeText(out) +
                         "; a mask network must give one map (1x1xHxW, 1xHxW or HxW): "
                         "export a salient-object model with a single-channel output, or " +
                         kFixConfig);
  cv::Mat map(out.size[out.dims - 2], out.size[out.dims - 1], CV_32F);
  out.reshape(1, map.rows).convertTo(map, CV_32F);
  return map;
}

Result<cv::Mat> MaskNet::Probability(const cv::Mat& bgr) {
  if (bgr.empty() || bgr.type() != CV_8UC3)
    return MakeError(ErrorClass::kInvalidArgument,
                     "mask network: the photo must be a non-empty 8-bit BGR image");
  auto map = Forward(bgr);
  if (!map.ok()) return map.error();
  cv::Mat p = *map;
  if (opts_.logits) {
    cv::exp(-p, p);
    p = 1.0 / (1.0 + p);
  }
  cv::resize(p, p, bgr.size(), 0, 0, cv::INTER_LINEAR);
  return cv::Mat(cv::min(cv::max(p, 0.0), 1.0));
}

Result<cv::Mat> MaskNet::Mask(const cv::Mat& bgr, const MaskOptions& refine, const cv::Mat& empty) {
  auto p = Probability(bgr);
  if (!p.ok()) return p.error();
  const cv::Mat rough = *p > opts_.threshold;
  return RefineForegroundMask(bgr, empty, rough, refine);
}

Result<std::shared_ptr<MaskNet>> LoadMaskNet(const MaskConfig& c) {
  if (c.method != "onnx") return std::shared_ptr<MaskNet>();
  auto net = MaskNet::Load(MaskNetOptionsFromConfig(c));
  if (!net.ok()) return net.error();
  return std::shared_ptr<MaskNet>(std::move(*net));
}

}  // namespace aggscan
