// Stitching the two sides of a rock: the rigid motion that takes the table
// frame of side 2 (the rock after the flip) onto the table frame of side 1.
// Each side's geometry is in its own table frame because the rock lies still
// on the platter during a side.
//
// Two independent estimates:
//  * markers: the heads and tails of the purple and red object markers
//    triangulated on both sides (pipeline/markers/markers.h), 3 or 4 correspondences,
//    least-squares rigid fit (Kabsch/Umeyama) with its residual;
//  * features: SIFT features inside the rock masks, matched between views of
//    one side with the calibrated poses (epipolar check), merged into tracks
//    and triangulated per side; the two sides' points are matched by their
//    descriptors (every view's descriptor of a point takes part, so a point
//    seen from a similar angle on both sides can match) and a RANSAC rigid
//    fit on the 3D-3D pairs keeps the consistent ones.
// Choice: when both exist and agree (rotation within agree_deg + 3 sigma of
// the marker fit's weak axis, displacement over the rock within agree_mm) the
// feature estimate, which is the more precise (sim: 0.08-0.35 deg against
// 0.7-2.9 deg for the markers, whose head and tail lie only ~20 mm apart);
// the markers are then its independent check. Markers alone when there is no
// feature estimate (small rocks: few SIFT matches survive the flip), or when 4
// fitting marker points contradict the features. Features alone when the
// markers are insufficient (a marker under the rock on one side). An error
// saying what was seen and what to do when neither is enough.
#pragma once

#include <Eigen/Core>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"
#include "pipeline/core/geometry.h"
#include "pipeline/markers/markers.h"
#include "pipeline/stitch/silhouette_stitch.h"

namespace aggscan {

// --- per-side feature cloud ---

struct FeatureCloudOptions {
  int max_features = 4000;   // SIFT keypoints kept per view (strongest)
  double image_scale = 1.0;  // SIFT runs on the photo resized by this (0.5: ~4x faster)
  int mask_erode_px = 4;     // keypoints this close to the silhouette are dropped (mixed pixels)
  double ratio = 0.8;        // Lowe's ratio test within a side
  double min_pair_deg = 15;  // view pairs whose turntable angles differ by this ...
  double max_pair_deg =
      65;  // ... up to this are matched (views at the same angle mod 360 are one viewpoint)
  double epipolar_px = 2.0;  // Sampson distance allowed for a match, undistorted px
  geom::TriangulationOptions triangulation{.inlier_px = 1.5, .min_views = 2, .min_angle_deg = 8.0};
  /// Only the first view of each viewpoint takes part (DistinctViewpoints);
  /// false: every view with keypoints does (bundle adjustment of every view's
  /// angle needs each view's own observations).
  bool distinct_viewpoints_only = true;
};

/// SIFT keypoints and descriptors of one view, inside its rock mask; keypoint
/// coordinates in the full-resolution (distorted) photo.
struct ViewFeatures {
  std::vector<cv::KeyPoint> keypoints;
  cv::Mat descriptors;  // CV_32F, one row per keypoint
};

/// Features of a BGR photo inside the rock mask (0/255, same size). `origin`:
/// where the photo's top-left pixel lies in the full frame when it is a
/// window of it (the keypoints come out in full-frame pixels).
ViewFeatures ExtractRockFeatures(const cv::Mat& bgr, const cv::Mat& rock_mask,
                                 const FeatureCloudOptions& opts = {}, cv::Point origin = {});

/// Triangulated feature points of one side with every descriptor they were seen with.
struct FeatureCloud {
  std::vector<Eigen::Vector3d> points;  // table frame of the side (mm)
  std::vector<double> rms_px;           // reprojection RMS per point
  cv::Mat descriptors;                  // CV_32F, one row per (point, view) sighting
  std::vector<int> point_of_row;        // descriptors row -> index into points
  /// Per point, its inlier sightings as (view index, keypoint index into that
  /// view's ViewFeatures): the tracks bundle adjustment refines.
  std::vector<std::vector<std::pair<int, int>>> tracks;
  int views = 0, view_pairs = 0;  // viewpoints used and pairs matched
};

/// Indices of the views that are distinct viewpoints: a view taken from the
/// same pose as an earlier one (within 1 deg and 2 mm: the paper profile turns
/// 2.4 times, so 30 views are 12 viewpoints) adds no baseline. Features are
/// only needed for these.
std::vector<int> DistinctViewpoints(const std::vector<geom::Rigid3>& cam_from_table);

/// Matches the views' features pairwise with the poses' epipolar geometry,
/// merges the matches into tracks and triangulates each (views[i] taken with
/// cam_from_table[i]; a view with no keypoints is skipped). An empty cloud
/// when nothing can be triangulated.
FeatureCloud BuildFeatureCloud(const std::vector<ViewFeatures>& views,
                               const std::vector<geom::Rigid3>& cam_from_table,
                               const CameraModel& camera, const FeatureCloudOptions& opts = {});

// --- stitching ---

struct StitchOptions {
  int reference_side = 1;  // for messages only
  int moving_side = 2;
  double marker_max_rms_mm =
      0.8;  // a marker fit worse than this is inconsistent (sim: 0.2-0.7 when right)
  double marker_max_mm = 1.5;   // and so is one with any residual above this
  double feature_ratio = 0.85;  // Lowe's ratio across the sides (points of different ids)
  geom::RansacRigidOptions ransac{
      .inlier_mm = 2.0, .iterations = 4000, .seed = 1, .min_spread_mm = 10};
  int min_feature_inliers = 12;  // fewer consistent matches: no feature estimate
  /// Guided matching: once a motion is roughly known (a feature fit with few
  /// inliers, the marker fit), each moving point is matched only among the
  /// reference points within this distance of where the motion puts it, the
  /// ratio test among those alone. Across the flip a surface patch is seen
  /// from far apart, its descriptors change, and a ratio test over the whole
  /// rock loses most true matches to look-alike grain elsewhere; among a few
  /// neighbours the true one still stands out. A start a few degrees off
  /// converges in a round or two; a far one finds too few consistent matches
  /// to pass min_feature_inliers (docs/validation.md has the figures).
  double guided_radius_mm = 8.0;
  int guided_rounds = 4;  // match, fit, match again with the new motion
  /// A guided fit whose inliers' residual RMS exceeds this is a chance
  /// alignment: with matches taken near where a wrong motion puts the points,
  /// some always fall inside the RANSAC gate, spread over it (RMS near
  /// 0.55 x ransac.inlier_mm), where a true fit's residuals are the
  /// triangulation's noise (0.3-0.6 mm on the sim and on Blender renders).
  double guided_max_rms_mm = 0.8;
  double marker_sigma_mm =
      0.5;  // typical marker point error (sim: 0.05-1.4 mm), for the rotation uncertainty
  double agree_deg =
      2.0;  // estimates closer than this in rotation (plus 3 sigma of the markers') ...
  double agree_mm = 3.0;  // ... and this in displacement over the rock agree
  /// Silhouette coherence (silhouette_stitch.h): a stitch refined by the
  /// silhouettes is accepted when the mean fraction of rock pixels its model
  /// leaves uncovered is at most this above what each side's own hull
  /// leaves in its own views (OwnDeficit: the masks' disagreement within a
  /// side, whatever the motion), and a feature fit leaving more is replaced
  /// by its refinement. Sim, computed masks (own deficit about 0.0015): 0.003
  /// at the true motion at 1008 x 756, 0.013-0.025 at 3 deg off, 0.05-0.09
  /// at 8 deg off; at 2016 x 1512 a right feature fit left 0.0045-0.011 (83
  /// inliers: 0.0109, its refinement 0.0102) and a wrong one 0.0156 (12
  /// inliers, volume -5.2 %). Masks that take shadows in raise the own
  /// deficit to 0.01-0.03 (docs/validation.md).
  double silhouette_accept = 0.011;
  double sweep_deg = 15;  // 2 marker points: trial rotations about their axis this far apart
  /// With nothing to start from, or no start the silhouettes accept: their
  /// search over every orientation (SilhouetteStitcher::Search). Its best
  /// motion is taken when accepted as above and the next-best distinct one
  /// leaves, beyond the own deficit, at least search_unique_ratio times as
  /// much and search_unique_margin more: a rock whose silhouettes two
  /// motions explain alike (a near-symmetric stone, masks too poor to tell)
  /// is refused, not stitched by chance.
  bool search = true;
  SilhouetteSearchOptions search_options;
  double search_unique_ratio = 2.0;
  double search_unique_margin = 0.005;
  /// A feature estimate the silhouettes accept is refined by them too, and
  /// replaced when the refinement leaves under 0.9 of its deficit within
  /// agree_deg / agree_mm of it: a fit of few matches can be a degree off
  /// (docs/validation.md) where sound masks pin the motion down; with masks
  /// as poor as the fit, no motion is clearly better and the fit is kept.
  /// Off: the features are only checked.
  bool refine_features = true;
};

/// One estimate of the motion moving side -> reference side.
struct StitchEstimate {
  bool valid = false;
  geom::Rigid3 T;   // p_ref = T.Apply(p_moving)
  int pairs = 0;    // correspondences offered (marker points, putative feature matches)
  int inliers = 0;  // used in the fit
  double rms_mm = 0, max_mm = 0;    // residual over the inliers
  std::vector<std::string> points;  // markers: names of the points used
  /// Markers: 1-sigma rotation uncertainty about the worst-determined axis for
  /// marker_sigma_mm point errors. Head and tail of each marker are only ~20
  /// mm apart and the two markers' axes are parallel, so the rotation about
  /// the line joining the markers is weak: 1-3 deg on the sim.
  double rotation_sigma_deg = 0;
  /// Features: what guided the matching ("" none: the global ratio test's
  /// RANSAC fit stood; "features": its own first fit; "markers": the marker
  /// fit, the global matches having no consistent fit), and the inliers the
  /// global matching had.
  std::string guided_from;
  int unguided_inliers = 0;
  std::string note;  // why not valid, or what was dropped
};

/// What the silhouettes did to the stitch.
struct SilhouetteRefinement {
  bool tried = false;        // a silhouette stitcher was given and there was a start
  bool used = false;         // the refined motion was taken
  std::string start;         // what the refinement started from
  double own_deficit = 0;    // SilhouetteStitcher::OwnDeficit: the floor of the deficits below
  double deficit_start = 0;  // silhouette deficit of the start, and after refinement
  double deficit = 0;
  double moved_deg = 0;  // refined vs start: rotation, and displacement RMS over the rock
  double moved_mm = 0;
  int evaluations = 0;
  double seconds = 0;
  /// The search over every orientation, when it ran: its candidates after
  /// refinement, and the next-best distinct motion's deficit and angle from
  /// the best (-1 / 0 without one).
  bool searched = false;
  int search_fits = 0;
  double search_runner_up = -1;
  double search_runner_up_deg = 0;
  double search_seconds = 0;
  std::string note;
};

struct StitchResult {
  geom::Rigid3 T;  // the chosen moving -> reference motion
  /// "features" when both estimates exist and agree (the more precise one;
  /// the markers are its check) or the markers are insufficient; "markers"
  /// without a feature estimate, or when 4 fitting marker points contradict
  /// it; "markers+silhouettes" when a marker estimate was refined by the
  /// silhouettes (its weak axis); "silhouettes" when neither estimate was
  /// sufficient alone but a partial one (2 marker points, a feature fit with
  /// few inliers) refined by the silhouettes explains every view.
  std::string source;
  SilhouetteRefinement silhouettes;
  StitchEstimate markers, features;

  bool cross_checked = false;   // both estimates exist
  double disagreement_deg = 0;  // rotation between the two estimates
  double disagreement_mm =
      0;  // their displacement difference at the rock (RMS over the moving side's points)
  bool consistent = true;  // within agree_deg / agree_mm (true when not cross-checked)
  std::string warning;     // set when the estimates disagree
};

/// Rigid fit of the marker points located on both sides (3 needs agreeing
/// distances; with 4 and a bad fit, the point whose removal fixes it is dropped
/// and named). Never fails: an invalid estimate says why.
StitchEstimate StitchFromMarkers(const SideMarkers& reference, const SideMarkers& moving,
                                 const StitchOptions& opts = {});

/// RANSAC rigid fit of descriptor matches between the two sides' clouds.
StitchEstimate StitchFromFeatures(const FeatureCloud& reference, const FeatureCloud& moving,
                                  const StitchOptions& opts = {});

/// Feature estimate by guided matching from `start` (moving -> reference):
/// opts.guided_rounds rounds of matching each moving point among the
/// reference points within opts.guided_radius_mm of start's image of it (one
/// to one, the ratio test among those candidates), then a RANSAC rigid fit,
/// whose motion guides the next round. Valid with min_feature_inliers.
StitchEstimate GuidedFeatureFit(const FeatureCloud& reference, const FeatureCloud& moving,
                                const geom::Rigid3& start, const StitchOptions& opts = {});

/// Both estimates, compared, and the choice. `reference_features` and
/// `moving_features` may be null (no cross-check). With `silhouettes`, a
/// marker-only estimate is refined by silhouette coherence, a feature
/// estimate is checked by it, and when neither estimate is sufficient the
/// partial evidence is refined and accepted if the silhouettes confirm it.
/// kInvalidArgument, with what was seen on each side and what to do, when
/// nothing is sufficient.
Result<StitchResult> StitchSides(const SideMarkers& reference, const SideMarkers& moving,
                                 const FeatureCloud* reference_features,
                                 const FeatureCloud* moving_features,
                                 const StitchOptions& opts = {},
                                 const SilhouetteStitcher* silhouettes = nullptr);

}  // namespace aggscan
