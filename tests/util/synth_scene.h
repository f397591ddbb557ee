// Synthetic turntable scenes for the mask and side-job tests: a white table, a
// light-grey turntable disc seen at ~35 deg, four saturated colour labels on
// the disc, a textured Lambert-shaded brown rock with a purple and a red object
// marker painted on it, a soft cast shadow, sensor noise and a JPEG round trip.
// Ground truth comes with it. (Stand-in until the sim renderer exists.)
#pragma once

#include <cstdint>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

namespace aggscan::testing {

struct SceneParams {
  cv::Size size{2016, 1512};
  uint64_t seed = 1;
  double albedo = 0.4;             // rock base albedo, 0.25..0.6
  double rock_radius_frac = 0.14;  // mean rock radius as a fraction of the image width
  double turntable_deg = 0;        // rotates the labels around the disc
  double light_azimuth_deg = 135;  // light from the upper left
  bool marker_on_edge = false;     // one stroke runs out to the silhouette border
  double noise_sigma = 2.0;        // 8-bit levels
  int jpeg_quality = 92;
};

struct Scene {
  cv::Mat bgr;                      // the photo (after the JPEG round trip)
  std::vector<unsigned char> jpeg;  // its encoded bytes
  cv::Mat truth;                    // rock silhouette, 0/255
  cv::Mat labels;                   // visible colour-label pixels, 0/255
  cv::Mat markers;                  // object-marker pixels on the rock, 0/255
};

Scene MakeScene(const SceneParams& p);

// A stone on a light-grey disc that stands on a pebbled quarry floor: the
// border of the frame shows only the floor, so the border's colours do not
// describe the disc, and the floor's pebbles are as textured as the stone.
// `empty` = the same scene without the stone (independent noise, the light
// 8 % brighter, as between two photos a while apart). 1008 x 756.
struct FloorScene {
  cv::Mat photo, empty, truth;  // BGR after a JPEG round trip; truth 0/255
};
FloorScene MakeFloorScene(uint64_t seed);

/// Intersection over union of two 0/255 masks; pixels where `ignore` is
/// non-zero (optional) are excluded.
double MaskIoU(const cv::Mat& a, const cv::Mat& b, const cv::Mat& ignore = cv::Mat());

}  // namespace aggscan::testing
