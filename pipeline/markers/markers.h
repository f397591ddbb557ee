// Markers, found automatically in every view (the study labels them by hand in
// about 3 views):
//
//  * Background labels: the four coloured squares on the turntable disc (config
//    rig.markers: colour, centre x_mm/y_mm in the table frame, side
//    rig.marker_size_mm, on the disc's top surface z = 0). Each view: saturated
//    pixels of the label's hue (HSV hue and saturation do not change with
//    shading or the rock's shadow), square-ish blobs of the expected apparent
//    size lying outside the rock mask, untouched by it and by the image border.
//    The centre is the intersection of the diagonals of the quadrilateral
//    fitted to the blob's edges in undistorted pixels: the exact image of the
//    square's centre under perspective (a blob centroid is off by ~0.2 px at
//    the rig's 35 deg tilt). All views together -> each label's 3D centre ->
//    the metric scale from the configured label distances.
//
//  * Object markers: the purple and the red head-tail patterns painted on the
//    rock (short head segment, gap, long tail segment). Each view: saturated
//    pixels of the marker's hue inside the rock mask (the red label lies
//    outside it), split into connected segments; when both segments show, the
//    smaller is the head. A segment cut by the silhouette (it wraps round the
//    rock) is flagged truncated, its centroid being biased. Per side (the rock
//    rests still on the table, so head and tail are fixed points in the table
//    frame) head and tail are triangulated robustly; segments seen alone are
//    then assigned by where the head and the tail project.
//
// Colour names are the config's: red, green, blue, yellow, purple.
#pragma once

#include <Eigen/Core>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/core/geometry.h"

namespace aggscan {

/// A colour class in HSV (hue in degrees [0, 360), saturation and value in [0, 1]).
struct ColorClass {
  std::string name;
  double hue_deg = 0;
  double hue_tol_deg = 22;  // accepted hue distance from hue_deg
};

/// The study's five paint colours as the sim and the rig's print show them
/// (hues measured on sim renders; red and purple are 70 deg apart).
std::vector<ColorClass> DefaultColorClasses();

struct MarkerDetectOptions {
  std::vector<ColorClass> colors = DefaultColorClasses();
  double min_saturation = 0.35;  // HSV S below this is not paint (the rock stays below ~0.3)
  double min_chroma = 0.08;      // (max - min) of RGB in [0,1]: drops noisy dark pixels
  // Background labels:
  double label_min_side_frac = 0.012;  // sqrt(area) of a label blob, fraction of the image width
  double label_max_side_frac = 0.12;
  double expected_label_side_px = 0;  // > 0: also require sqrt(area) within x0.4..x2.5 of this
  double label_min_solidity = 0.90;   // blob area / its convex hull area
  double label_min_fill = 0.85;       // blob area / area of the fitted quadrilateral
  int rock_clearance_px = 3;          // a label blob this close to the rock mask is partly hidden
  // Object markers:
  double segment_min_area_frac = 1e-5;  // segment area, fraction of width^2 (40 px at 2016 x 1512)
  int marker_mask_dilate_px = 2;        // marker pixels may lie this far outside the rock mask
  double head_tail_min_ratio = 1.5;     // tail area / head area when both show (nominal ~3)

  /// Empty when valid, else what is wrong.
  std::string Check() const;
};

/// One background label in one view.
struct LabelSighting {
  std::string color;
  Eigen::Vector2d center_px = Eigen::Vector2d::Zero();  // distorted pixel of the square's centre
  std::array<Eigen::Vector2d, 4> corners_px{};          // fitted corners, distorted pixels
  double area_px = 0;
  double edge_rms_px = 0;  // RMS distance of the blob's edge points to the fitted sides
};

/// One painted segment in one view.
struct SegmentBlob {
  Eigen::Vector2d center_px = Eigen::Vector2d::Zero();  // centroid of the paint pixels
  double area_px = 0;
  double length_px = 0;  // extent along the principal axis (4 sigma)
  double width_px = 0;   // extent across
  Eigen::Vector2d axis = Eigen::Vector2d::UnitX();
  bool truncated = false;  // touches the silhouette: part of it may be round the edge
};

/// One object marker in one view: head and tail when told apart, else the
/// segments seen (assigned later from the triangulated points).
struct ObjectMarkerSighting {
  std::string color;
  std::optional<SegmentBlob> head, tail;
  std::vector<SegmentBlob> unassigned;
  bool seen() const { return head || tail || !unassigned.empty(); }
};

/// Everything found in one view.
struct ViewMarkers {
  std::vector<LabelSighting> labels;          // at most one per label colour
  std::vector<ObjectMarkerSighting> objects;  // one per object colour asked (maybe unseen)
};

/// Detects the background labels `label_colors` and the object markers
/// `object_colors` in a BGR photo with its rock mask (0/255, same size). The
/// camera model, when given, removes the lens distortion from the label edges
/// (the centre stays exact); without it the image is taken as undistorted.
/// kInvalidArgument for wrong image types or sizes, or an unknown colour.
Result<ViewMarkers> DetectViewMarkers(const cv::Mat& bgr, const cv::Mat& rock_mask,
                                      const std::vector<std::string>& label_colors,
                                      const std::vector<std::string>& object_colors,
                                      const CameraModel* camera,
                                      const MarkerDetectOptions& opts = {});

/// The colour class image: per pixel 0 (none) or 1 + index into opts.colors.
cv::Mat ClassifyColors(const cv::Mat& bgr, const MarkerDetectOptions& opts);

/// Apparent side (px) of a rig label seen from the calibrated camera (focal
/// length x size / distance to the disc centre), for expected_label_side_px.
double ExpectedLabelSidePx(const RigCalibration& cal, const RigConfig& rig);

/// Pixels per mm of something at the disc centre, seen from the calibrated
/// camera (focal length / distance); 0 for a camera at the centre.
double PxPerMmAtDisc(const RigCalibration& cal);

// --- background labels: 3D and scale ---

struct LabelLocateOptions {
  geom::TriangulationOptions triangulation{.inlier_px = 1.5, .min_views = 2, .min_angle_deg = 5.0};
  int min_labels = 3;  // fewer located labels: no scale
};

/// One label's 3D centre.
struct LabelPoint {
  std::string color;
  Eigen::Vector3d configured =
      Eigen::Vector3d::Zero();  // rig.markers position (table frame, z = 0)
  bool located = false;
  Eigen::Vector3d position = Eigen::Vector3d::Zero();  // triangulated, in the poses' frame
  double rms_px = 0, max_px = 0;                       // reprojection over the views used
  int views_seen = 0;                                  // views where it was detected
  int views_used = 0;                                  // of those, inliers of the triangulation
  std::string problem;                                 // why not located
};

/// The labels located and the scale they give.
struct LabelScale {
  std::vector<LabelPoint> labels;  // rig.markers order
  int labels_used = 0;
  /// Configured / reconstructed distance, least squares over all label pairs.
  /// The calibrated rig measures in mm already: ~1 (a check); an SfM model
  /// multiplies its coordinates by this to become metric.
  double scale = 1.0;
  double pair_rms_mm = 0, pair_max_mm = 0;  // |scale * d_rec - d_conf| over the pairs (mm)
  /// Similarity (Umeyama, with scale) from the poses' frame onto the
  /// configured positions (the table frame at angle 0), and its residual.
  geom::Similarity3 frame_to_table;
  double align_rms_mm = 0, align_max_mm = 0;
};

/// Triangulates every configured label from its sightings in all views
/// (views[i] taken with cam_from_frame[i]) and compares the label distances
/// with the configured ones. kInvalidArgument when fewer than min_labels are
/// located, naming each missing label and in how many views it was seen.
Result<LabelScale> LocateLabels(const std::vector<ViewMarkers>& views,
                                const std::vector<geom::Rigid3>& cam_from_frame,
                                const CameraModel& camera, const RigConfig& rig,
                                const LabelLocateOptions& opts = {});

// --- object markers: 3D head and tail per side ---

struct MarkerLocateOptions {
  geom::TriangulationOptions triangulation{.inlier_px = 2.0, .min_views = 2, .min_angle_deg = 5.0};
  double assign_px = 6.0;           // a lone segment within this of a projected head/tail is it
  double assign_length_frac = 0.3;  // plus this fraction of its own length
  double min_head_tail_mm = 6.0;    // plausible 3D head-tail distances (14-21 mm on the sim)
  double max_head_tail_mm = 40.0;
  int min_clean_views = 3;     // use the other segments only when fewer clean views
  double min_area_frac = 0.4;  // clean: area at least this fraction of the segment's largest view
};

/// One triangulated segment centre.
struct MarkerPoint {
  std::string color;    // purple | red
  std::string segment;  // head | tail
  bool located = false;
  Eigen::Vector3d position =
      Eigen::Vector3d::Zero();  // in the poses' frame (table frame of the side)
  double rms_px = 0, max_px = 0;
  int views_seen = 0;   // views where this segment was identified
  int views_used = 0;   // inliers of the triangulation
  std::string problem;  // why not located
  std::string Name() const { return color + " " + segment; }
};

/// Head and tail of every object marker of one side.
struct SideMarkers {
  std::vector<MarkerPoint> points;     // per colour: head, tail
  int views = 0;                       // views of the side
  std::vector<int> views_with_marker;  // per colour: views where any of its paint was seen
  int located() const;
  const MarkerPoint* Find(const std::string& color, const std::string& segment) const;
};

/// Triangulates head and tail of each object marker in `colors` over the views
/// of one side. Never fails: points that cannot be located say why.
SideMarkers LocateObjectMarkers(const std::vector<ViewMarkers>& views,
                                const std::vector<geom::Rigid3>& cam_from_frame,
                                const CameraModel& camera, const std::vector<std::string>& colors,
                                const MarkerLocateOptions& opts = {});

}  // namespace aggscan
