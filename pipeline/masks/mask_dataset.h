// Training pairs for the mask network, made by the rig itself (the study's
// ~100 image-mask pairs per environment): for a reconstructed sample, the
// closed mesh is projected into every posed view, and the photo with that
// silhouette is one pair. The mesh is the visual hull of every view's mask
// refined by photo-consistency, so a leak or a bite in one view's mask is
// carved away or outvoted by the others: the projection is a better mask
// than any single view's segmentation.
//
// The simulator's truth masks (truth/) are never read here: a real rig has
// none; they only score masks (`aggscan masks eval`).
//
// Dataset layout (`aggscan masks dataset --out DIR`):
//   DIR/images/<sample>_side<N>_view_NNN.jpg  the photo as captured (a copy)
//   DIR/masks/<sample>_side<N>_view_NNN.png   the mesh's silhouette, 0/255
//   DIR/index.json  {"pairs": [{image, mask, sample, side, view, pose,
//                               agreement_iou}], "samples": [...], "skipped": [...]}
//   DIR/index.csv   the same pairs, one a line
#pragma once

#include <Eigen/Geometry>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/mesh.h"
#include "common/rig_calibration.h"

namespace aggscan {

/// The silhouette of `mesh` (object frame, mm) seen by `cam` at
/// `cam_from_object`: CV_8UC1, 0/255, the camera's size; every face filled
/// with sub-pixel vertex positions (1/16 px).
cv::Mat RenderMeshSilhouette(const Mesh& mesh, const Eigen::Isometry3d& cam_from_object,
                             const CameraModel& cam);

/// IoU of two masks (nonzero: rock) of one size, leaving out the pixels where
/// `ignore` (if given) is nonzero; 1 when both are empty.
double MaskIoUIgnoring(const cv::Mat& a, const cv::Mat& b, const cv::Mat& ignore = cv::Mat());

/// One view of a reconstructed sample: its photo and where the mesh projects.
struct ProjectedView {
  int side = 0, view = 0;
  std::string image;  // the photo's path
  std::string
      pose;  // "poses" (results/poses_sideN.json) or "turntable" (calibration + measured angle)
  cv::Mat silhouette;         // 0/255, the photo's size
  double agreement_iou = -1;  // IoU with the worker's own mask of the view (-1: it has none)
};

/// Every view of a reconstructed sample (results/morphology.json written):
/// the posed views from results/poses_side<N>.json, and on a turntable-posed
/// side also the views the worker left out (a failed mask), posed by the
/// calibration and their measured angle. kNotFound naming the missing
/// results file (and `aggscan reconstruct`) when the sample is not
/// reconstructed; kCorrupt when its results do not parse.
Result<std::vector<ProjectedView>> ProjectReconstruction(const std::string& sample_dir);

struct MaskPairRecord {
  std::string sample, image, mask, pose;  // image/mask relative to the dataset directory
  int side = 0, view = 0;
  double agreement_iou = -1;
};

struct MaskDatasetSummary {
  std::vector<MaskPairRecord> pairs;
  std::vector<std::string> samples;  // sample ids that gave pairs
  std::vector<std::string> skipped;  // "DIR: why" for each sample left out
};

/// Writes the pairs of every sample into out_dir (created; pairs of the same
/// names replaced) and its index. A sample that is not reconstructed is
/// skipped and named in `skipped`; kNotFound when no sample gives a pair.
Result<MaskDatasetSummary> MakeMaskDataset(const std::vector<std::string>& sample_dirs,
                                           const std::string& out_dir);

}  // namespace aggscan
