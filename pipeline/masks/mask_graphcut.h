// Seeded graph-cut segmentation with colour and texture (internal to the mask
// code; pipeline/masks/mask.h is the interface).
//
// GrabCut (Rother, Kolmogorov, Blake 2004) with one more cue: each pixel's
// data term adds the likelihood of its texture value under a rock and a
// background texture histogram, learned from the seeds like the colour
// mixtures. On the rig a dark shaded facet of a grey rock and the cast shadow
// next to it have the same colour and differ only in texture; on a busy
// background both histograms look alike and the term fades out by itself.
//
// Energy: sum over pixels of -log p(colour | side) - texture_weight *
// log p(texture | side), plus gamma * exp(-beta |dI|^2) / distance for every
// 8-neighbour pair labelled differently (beta from the image's mean contrast).
// Minimised exactly for fixed models by a max-flow (OpenCV's GCGraph), models
// re-estimated from the labelling, `iterations` times.
#pragma once

#include <opencv2/core.hpp>

namespace aggscan::mask_detail {

struct GraphCutOptions {
  int iterations = 3;           // model re-estimation rounds
  double gamma = 50.0;          // smoothness weight (GrabCut's value)
  double texture_weight = 1.0;  // weight of the texture log-likelihood against colour's
  int components = 5;           // Gaussians per colour mixture
  double neutral_rock_cost =
      1.0;  // data cost of calling a neutral pixel rock (a slight lean to background)
};

/// `bgr` CV_8UC3, `texture` CV_32F (same size; empty = colour only), `trimap`
/// CV_8UC1 with cv::GC_BGD / GC_FGD / GC_PR_BGD / GC_PR_FGD. Uncertain pixels
/// non-zero in `neutral` (CV_8UC1, may be empty) get no data term and teach the
/// models nothing: the smoothness term alone decides them (used for paint,
/// whose colour says nothing about rock or background). Returns the 0/255 rock
/// mask. Deterministic. Returns the trimap's FGD|PR_FGD when one side has no
/// pixels.
cv::Mat SegmentGraphCut(const cv::Mat& bgr, const cv::Mat& texture, const cv::Mat& trimap,
                        const cv::Mat& neutral, const GraphCutOptions& opts);

}  // namespace aggscan::mask_detail
