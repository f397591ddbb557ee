// 2D morphology of one silhouette (per view), as in Huang et al.: L_max is the
// longest Feret diameter, L_min the width of the silhouette perpendicular to
// the L_max direction, 2D FER = L_max / L_min, circularity = 4*pi*A / P^2
// (disc 1, square pi/4 = 0.785, equilateral triangle pi*sqrt(3)/9 = 0.605).
//
// Boundary representation: the silhouette (largest 8-connected component, holes
// filled) is blurred with a small Gaussian and its 0.5 iso-line is traced with
// marching squares. That sub-pixel contour removes the pixel staircase, which
// would otherwise inflate the perimeter of slanted edges by up to 8 %; its
// points feed the perimeter and the Feret diameters. The area is the pixel count
// of the filled component (the 0.5 iso-line of a blurred step lies on the pixel
// border, so both describe the same boundary).
#pragma once

#include <opencv2/core.hpp>
#include <vector>

#include "common/error.h"
#include "pipeline/core/stats.h"

namespace aggscan {

struct Morph2D {
  double l_max_px = 0;         // longest Feret diameter
  double l_min_px = 0;         // extent perpendicular to the L_max direction
  double fer_2d = 0;           // l_max_px / l_min_px
  double area_px = 0;          // pixel count of the largest component, holes filled
  double perimeter_px = 0;     // length of the sub-pixel outer contour
  double circularity = 0;      // 4*pi*area / perimeter^2
  double l_max_angle_deg = 0;  // direction of L_max from the image x axis (y down), in [0, 180)
  cv::Point2d l_max_p1;  // L_max end points, image pixel coordinates (pixel centres at integers)
  cv::Point2d l_max_p2;
};

/// Morphology of the largest connected silhouette of `binary_mask` (CV_8UC1,
/// non-zero = object). kInvalidArgument for a wrong type or a mask without any
/// object pixel.
Result<Morph2D> ComputeMorph2D(const cv::Mat& binary_mask);

/// Keeps the largest 8-connected non-zero component of `mask` and fills its
/// holes; returns a 0/255 CV_8UC1 image (all zero when the mask is empty).
cv::Mat LargestComponentFilled(const cv::Mat& mask);

}  // namespace aggscan
