// Foreground (rock) mask of one turntable photo, by classical segmentation.
//
// The scene: a white table and a light-grey turntable disc (both bright,
// neutral and smooth), the rock's soft cast shadow (darker but still neutral
// and smooth), four saturated colour labels on the disc (not rock), and two
// saturated object markers painted on the rock (rock). The rock is textured and
// grey-brown. Steps:
//   1. At reduced resolution (work_long_side): Lab colour, local texture
//      (standard deviation of L) and chroma. Evidence of rock = textured or
//      moderately coloured; saturated pixels (labels, markers) are set aside.
//   2. Open (drops thin edge responses such as the disc rim), close, keep the
//      largest component, fill holes (brings back the object markers inside).
//   3. At full resolution, in a band around that boundary, each pixel goes to
//      the nearer of the local rock and local background mean colours
//      (normalised convolution over the sure regions on both sides).
//   4. Saturated blobs that mostly touch the rock (a marker crossing the
//      silhouette edge) join it; blobs lying on the disc (labels) do not.
#pragma once

#include <opencv2/core.hpp>

namespace aggscan {

struct MaskOptions {
  int work_long_side = 1008;       // coarse stage runs at this long side (px); 0 = full resolution
  double texture_sigma = 1.5;      // coarse px, scale of the texture high-pass and of its local RMS
  double texture_threshold = 0.02;  // RMS of high-passed ln(gray + 8) above which a pixel is textured
  double chroma_threshold = 7.0;   // Lab chroma above which a pixel is coloured (rock is brown)
  double saturated_chroma = 38.0;  // Lab chroma above which a pixel is a label/marker colour
  int open_radius = 3;             // coarse px; removes edge lines thinner than 2r+1
  int close_radius = 4;            // coarse px; bridges gaps in the textured rock region
  int band_inner_px = 14;          // full-res refinement band reaches this far inside the coarse boundary
  int band_outer_px = 6;           // and this far outside (the texture cue reaches past the edge)
  double local_sigma_px = 10.0;    // full-res Gaussian of the local mean colours
  double chroma_weight = 2.0;      // weight of a,b against L in the local colour distance
  double texture_weight = 0.0;     // weight of the texture cue (RMS of log-brightness high-pass) there
  double refine_texture_sigma_px = 1.5;  // full-res scale of that texture cue
  double marker_touch_fraction = 0.75;  // a saturated blob joins the rock if this much of its rim is rock
};

/// 0/255 CV_8UC1 mask of the rock in a CV_8UC3 BGR photo (same size). An
/// all-zero mask when nothing rock-like is found; never throws on content.
cv::Mat ComputeForegroundMask(const cv::Mat& bgr, const MaskOptions& opts = {});

/// The texture cue alone (CV_32F, same size as `bgr`), exposed for diagnostics
/// and tests: local RMS of the high-passed log brightness.
cv::Mat TextureMap(const cv::Mat& bgr, const MaskOptions& opts = {});

}  // namespace aggscan
