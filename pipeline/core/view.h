// One view of a sample as the stages after the masks hand it on: which photo
// and which mask, the turntable angle it was shot at and, once posed, where
// the camera was. The poses stage makes them from the side results, the
// stitch, the surface and the morphology take them as they are.
#pragma once

#include <string>

#include "pipeline/core/pose.h"

namespace aggscan {

struct SampleView {
  int side = 1;
  int view = 0;
  double angle_deg = 0;   // turntable angle: as measured, or as refined once posed
  std::string image;      // the photo, path
  std::string mask;       // its rock mask (PNG), path
  std::string image_rel;  // as the records name them: relative to the side directory
  std::string mask_rel;   // ... and to results/
  Pose cam_from_table = Pose::Identity();  // mm; identity until posed
  /// The rock reaches the photo's edge: SfM poses the view with the rest (its
  /// features are sound) but its cut silhouette carves nothing.
  bool pose_only = false;
};

}  // namespace aggscan
