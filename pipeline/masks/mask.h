// Foreground (rock) mask of one turntable photo, by classical segmentation.
//
// The rig's scene: a table and a turntable disc (smooth surfaces of one or a
// few colours; white and light grey in the study, but not necessarily), the
// rock's soft cast shadow (a darker version of the surface under it), four
// saturated colour labels on the disc (not rock) and two saturated object
// markers painted on the rock (rock). The rock sits in the middle of the frame
// and never touches the image border. Steps:
//   1. At reduced resolution (work_long_side): a background colour model from
//      a strip along the image border (k-means clusters), with a shading-
//      tolerant distance (Horprasert-style: a pixel is explained by a cluster
//      when it is that colour scaled by a brightness factor in
//      [shade_min, shade_max], so shadows and disc shading stay background).
//   2. Evidence of rock = colour not explained by the background model, or
//      local texture above what the border shows (the texture cue switches
//      itself off on a busy background). Colour uses hysteresis: regions
//      above a lower threshold join where they hold a pixel above the upper
//      one, since a busy background's wide clusters compress all distances.
//      Saturated pixels the background does not explain (labels, markers)
//      are set aside.
//   3. Open (drops thin edge responses such as the disc rim), close, keep the
//      largest component, fill holes (brings back the object markers inside).
//   4. Refinement (refine): kGrabCut runs cv::grabCut seeded with that mask
//      (sure rock well inside, sure background well outside, the labels forced
//      to background) on the rock's neighbourhood at refine_long_side; then,
//      for images larger than the working resolution, the band step below in
//      a narrow band (graphcut_band_px). kBand: only the band step, in a wide
//      band around the coarse mask. The band step: at full resolution, in a
//      band around the boundary, each pixel goes to the nearer of the local
//      rock and local background mean colours (normalised convolution over the
//      sure regions on both sides).
//   5. Thin saturated blobs touching the rock (a marker along or across the
//      silhouette edge) join it; label-thick blobs (labels on the disc, even
//      when the rock touches or partly hides them) do not.
//
// With a photo of the empty turntable at the same angle (same camera, same
// settings, shot before the rock was put on) the background model of step 1
// is that photo pixel by pixel, brought to the rock photo's lighting by a gain
// per channel, and the texture cue of step 2 is that of the ratio of the two
// photos: a wooden disc, a dark rubber mat or a gravel floor, whose colours
// and grain the border cannot describe, drop out. A pixel brighter than the
// empty photo by more than reference_shade_max is rock (light the rock throws
// onto the disc brightens it by less).
#pragma once

#include <opencv2/core.hpp>

namespace aggscan {

enum class MaskRefine {
  kNone,      // the working-resolution mask, upsampled
  kBand,      // full-resolution band step only
  kGraphCut,  // colour + texture graph cut at refine_long_side, then the band step
};

struct MaskOptions {
  int work_long_side = 1008;  // coarse stage runs at this long side (px); 0 = full resolution
  // Background model (working resolution):
  double border_fraction = 0.03;  // width of the border strip sampled, fraction of the short side
  int background_clusters = 6;    // k-means clusters of the border colours
  double shade_min = 0.3;         // brightness factors of a background colour still taken as it
  double shade_max = 1.3;         //   (shadow .. highlight)
  double color_threshold =
      4.0;  // normalised distance to the nearest cluster above which a pixel is rock
  double noise_levels = 3.0;  // 8-bit levels of colour noise added to every cluster's spread
  double color_weak_ratio =
      0.5;  // hysteresis: pixels above this times color_threshold join a rock region
  double color_border_factor =
      1.5;  //   when also above this times the border's 99th percentile distance
  // Texture cue:
  double texture_sigma = 1.5;  // coarse px, scale of the texture high-pass and of its local RMS
  double texture_threshold =
      0.02;  // RMS of high-passed ln(gray + 8) above which a pixel is textured
  double texture_border_factor = 1.5;  // and above this times the border's 99th percentile
  double saturated_chroma =
      38.0;              // Lab chroma above which an unexplained pixel is a label/marker colour
  int open_radius = 3;   // coarse px; removes edge lines thinner than 2r+1
  int close_radius = 4;  // coarse px; bridges gaps in the textured rock region
  // Refinement:
  MaskRefine refine = MaskRefine::kGraphCut;
  int refine_long_side =
      512;  // the graph cut runs on the rock's neighbourhood scaled to at most this (px)
  int graphcut_iterations = 3;  // model re-estimation rounds of the graph cut
  double graphcut_texture_weight =
      1.0;  // texture against colour in its data term (0 = plain GrabCut)
  double label_thickness =
      0.4;  // a paint blob this thick relative to the thickest one clear of the rock is a label
  int paint_fringe_px = 2;  // coarse px of mixed colour around paint, neutral in the graph cut too
  double graphcut_band =
      0.06;  // uncertain band half-width around the seed mask, fraction of the rock's size
  int band_inner_px = 14;  // kBand: the full-res band reaches this far inside the coarse boundary
  int band_outer_px = 6;   //   and this far outside
  int graphcut_band_px =
      2;  // kGraphCut: the band reaches this far on both sides of the cut's boundary
          // (when the cut was seeded by the coarse mask; after a network's seed the
          // band is band_inner_px / band_outer_px wide).
          // The cut is good to ~1.5 px; a wider band lets the local-mean rule take
          // rock faces as bright as the table or as dark as the shadow (sim 2016 x 1512,
          // 20 rocks: worst view 2.5 px of rock lost per px of outline at 14/6, 0.36 at 2)
  double local_sigma_px = 10.0;  // full-res Gaussian of the local mean colours
  double chroma_weight = 2.0;    // weight of a,b against L in the local colour distance
  double marker_touch_fraction =
      0.1;  // a thin paint blob (not label-thick) joins the rock if this much of its rim is rock
            // (a marker along the silhouette has the background on most of its rim)
  double reference_shade_max = 1.1;  // with an empty-turntable photo: brightness factor above which
                                     // a pixel is not explained by it (shade_min: below which)
};

/// 0/255 CV_8UC1 mask of the rock in a CV_8UC3 BGR photo (same size). An
/// all-zero mask when nothing rock-like is found; never throws on content.
cv::Mat ComputeForegroundMask(const cv::Mat& bgr, const MaskOptions& opts = {});

/// The same against `empty`, the photo of the empty turntable at this view's
/// angle (CV_8UC3, the photo's size); an empty Mat is the call above.
cv::Mat ComputeForegroundMask(const cv::Mat& bgr, const cv::Mat& empty, const MaskOptions& opts);

/// The shared tail of every mask method: `rough` (0/255 CV_8UC1, any size; it
/// is resized to the photo's) is cleaned (largest component, holes filled),
/// refined against the photo as opts.refine says, and markers crossing its
/// edge are attached. Used by the classical method and by the network.
cv::Mat RefineForegroundMask(const cv::Mat& bgr, const cv::Mat& rough,
                             const MaskOptions& opts = {});
cv::Mat RefineForegroundMask(const cv::Mat& bgr, const cv::Mat& empty, const cv::Mat& rough,
                             const MaskOptions& opts);

/// The texture cue alone (CV_32F, same size as `bgr`), exposed for diagnostics
/// and tests: local RMS of the high-passed log brightness (of its ratio to
/// `empty32`, the empty turntable as CV_32FC3 of the same size, when given).
cv::Mat TextureMap(const cv::Mat& bgr, const MaskOptions& opts = {},
                   const cv::Mat& empty32 = cv::Mat());

/// The colour cue alone (CV_32F, same size as `bgr`): normalised distance of
/// each pixel to the background model fitted on the border strip (step 1);
/// exposed for diagnostics and tests. With `empty` (CV_8UC3, the photo's
/// size): the distance to that photo pixel by pixel.
cv::Mat BackgroundColorDistance(const cv::Mat& bgr, const MaskOptions& opts = {},
                                const cv::Mat& empty = cv::Mat());

}  // namespace aggscan
