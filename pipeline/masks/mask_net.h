// Foreground mask from a salient-object network (ONNX, run by OpenCV DNN on
// the CPU), the optional first stage of the study's method (U2-Net trained on
// ~100 image-mask pairs of the rig). The network only gives the rough mask:
// its output, resized to the photo and thresholded, goes through the same
// RefineForegroundMask as the classical segmentation (cleaning, graph cut,
// full-resolution band, object markers attached).
//
// Contract of the network: one input 1x3xHxW float, RGB, each channel
// (value/255 - mean) / std; one output map, 1x1xhxw, 1xhxw or hxw (any h, w;
// it is resized to the photo), a probability or a logit per pixel.
#pragma once

#include <memory>
#include <mutex>
#include <opencv2/core.hpp>
#include <opencv2/dnn.hpp>
#include <string>

#include "common/error.h"
#include "config/config.h"
#include "pipeline/masks/mask.h"

namespace aggscan {

struct MaskNetOptions {
  std::string model_path;                    // the .onnx file
  cv::Size input_size{320, 320};             // network input, pixels
  cv::Scalar mean_rgb{0.485, 0.456, 0.406};  // subtracted from value/255, per channel
  cv::Scalar std_rgb{0.229, 0.224, 0.225};   // then divided by this
  bool logits = false;                       // the output needs a sigmoid
  double threshold = 0.5;                    // probability above which a pixel is rock
};

/// The network options of a [mask] section (method is not looked at).
MaskNetOptions MaskNetOptionsFromConfig(const MaskConfig& c);

class MaskNet {
 public:
  /// Reads the model and runs it once on a blank input to check the output's
  /// shape. kInvalidConfig naming the file and what to do when it is missing,
  /// is not an ONNX network OpenCV can run, or gives no single-channel map.
  static Result<std::unique_ptr<MaskNet>> Load(const MaskNetOptions& opts);

  /// Rock probability per pixel (CV_32F, 0..1, the photo's size) of a CV_8UC3
  /// BGR photo.
  Result<cv::Mat> Probability(const cv::Mat& bgr);

  /// 0/255 rock mask: Probability > threshold, refined by
  /// RefineForegroundMask(bgr, empty, rough, refine) (`empty`: the empty
  /// turntable at this view, or none).
  Result<cv::Mat> Mask(const cv::Mat& bgr, const MaskOptions& refine = {},
                       const cv::Mat& empty = cv::Mat());

  const MaskNetOptions& options() const { return opts_; }

 private:
  // cv::dnn::Net has no move constructor: a copy shares the loaded network.
  MaskNet(MaskNetOptions opts, const cv::dnn::Net& net) : opts_(std::move(opts)), net_(net) {}
  // The output map of one forward pass (CV_32F hxw, as the network gives it).
  Result<cv::Mat> Forward(const cv::Mat& bgr);

  MaskNetOptions opts_;
  std::mutex mu_;  // cv::dnn::Net::forward is not re-entrant
  cv::dnn::Net net_;
};

/// The worker's mask network from its [mask] section: null for method
/// "classical", the loaded network for "onnx", or Load's error.
Result<std::shared_ptr<MaskNet>> LoadMaskNet(const MaskConfig& c);

}  // namespace aggscan
