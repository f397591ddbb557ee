// What the sample job learns from one view's photo and rock mask the first
// time it decodes them, kept for the stages after it.
//
// A sample's photos are decoded by several stages (bundle adjustment, the
// stitch, the surface): each full frame of 2016 x 1512 costs ~20 ms to
// decode and 9 MB to hold, and every stage but the stitch's label search
// looks only at the rock. So whichever stage decodes a view first hands the
// photo and mask to a ViewEvidenceCache, which keeps the rock's window of
// both (a few per cent of the frame) and the markers the stitch needs (the
// background labels, which lie outside the window, the object markers and
// the ArUco markers). Later stages take the window and the detections from
// the cache and decode only what it does not hold. What is kept is exactly
// what the stages would compute from the decoded frame, so the results do not
// depend on whether a view was cached.
#pragma once

#include <cstddef>
#include <map>
#include <memory>
#include <mutex>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/markers/aruco_scale.h"
#include "pipeline/markers/markers.h"

namespace aggscan {

/// `m` inside `roi`, zero where `roi` reaches past m's edge (by at most one
/// pixel: a window's even side over a frame of odd size).
cv::Mat CropPadded(const cv::Mat& m, const cv::Rect& roi);

/// The rock's window in a frame: the bounding box of the mask's non-zero
/// pixels grown by `margin` pixels each way, with even corners and sides (a
/// half-size decode crops it exactly), clipped to the frame's size rounded up
/// to even; the whole (even-rounded) frame when the mask is empty. Outside
/// the window the mask is zero.
cv::Rect RockWindow(const cv::Mat& full_mask, int margin);

/// What to find in each view.
struct EvidenceOptions {
  CameraModel camera;  // the lens the labels and markers are undistorted with
  std::vector<std::string> label_colors;
  std::vector<std::string> object_colors;
  MarkerDetectOptions markers;
  /// The rig whose ArUco markers are searched for; none when it lists none.
  RigConfig rig;
  int window_margin = 0;  // px around the rock's box (RockWindow)

  bool want_aruco() const { return !rig.aruco_markers.empty(); }
  /// Equal keys find the same things with the same parameters.
  std::string Key() const;
};

struct ViewEvidence {
  cv::Size frame;              // the photo's (and mask's) size
  cv::Rect window;             // RockWindow of the mask
  cv::Mat mask;                // the mask inside `window`
  cv::Mat bgr;                 // the photo inside `window`; empty when the cache was full
  bool markers_found = false;  // false: DetectViewMarkers failed on this view
  ViewMarkers markers;
  bool aruco_found = false;  // false: not asked for, or DetectArucoMarkers failed
  ArucoViewDetections aruco;
  double markers_s = 0, aruco_s = 0;  // what the detections cost (thread time)

  /// The whole-frame mask: `mask` put back into a frame of zeros.
  cv::Mat FullMask() const;
  size_t bytes() const { return mask.total() * mask.elemSize() + bgr.total() * bgr.elemSize(); }
};

/// Detects what `o` asks for in a decoded photo (BGR) and its rock mask (0/255,
/// the same size); `keep_colour` false leaves ViewEvidence::bgr empty.
ViewEvidence GatherViewEvidence(const cv::Mat& bgr, const cv::Mat& mask, const EvidenceOptions& o,
                                bool keep_colour = true);

/// One sample's evidence, by photo path. Thread-safe: stages fill it from
/// their parallel loops. The colour windows are kept up to a byte budget
/// (beyond it a view keeps its mask and detections only, and the colouring
/// decodes that photo again): a rock filling the frame would otherwise hold
/// every photo whole.
class ViewEvidenceCache {
 public:
  explicit ViewEvidenceCache(EvidenceOptions options, size_t colour_budget_bytes = 160u << 20);

  const EvidenceOptions& options() const { return options_; }
  /// True when the evidence kept is what `wanted` asks for: the same lens,
  /// colours, detector options and ArUco set (the window margin aside, which
  /// only the surface's windows depend on).
  bool Serves(EvidenceOptions wanted) const;
  /// Gathers and keeps the view's evidence unless it is kept already.
  void Add(const std::string& image, const cv::Mat& bgr, const cv::Mat& mask);
  /// The view's evidence, or null when no stage has decoded it yet.
  std::shared_ptr<const ViewEvidence> Find(const std::string& image) const;
  size_t views() const;
  size_t bytes() const;

 private:
  EvidenceOptions options_;
  size_t colour_budget_;
  mutable std::mutex mu_;
  std::map<std::string, std::shared_ptr<const ViewEvidence>> by_image_;
  size_t colour_bytes_ = 0, bytes_ = 0;
};

}  // namespace aggscan
