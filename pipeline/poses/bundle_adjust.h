// Bundle adjustment of one side of a calibrated turntable capture (the
// fast path): every view's pose is cam_from_table0 * Rz(angle)
// (common/rig_calibration.h); the measured turntable angles are refined, with
// the 3D feature points, by minimising the reprojection error of feature
// tracks. The study's Eq. 2: only features inside the rock mask take part
// (ExtractRockFeatures detects them inside the mask only), so the background,
// which stands still while the platter turns, never pulls the poses.
//
// Unknowns (Ceres):
//  * per view one angle (deg), with a prior toward the measured angle whose
//    sigma is the turntable's stated accuracy: weak against the features, it
//    only holds views that few tracks constrain;
//  * optionally cam_from_table0 (6 dof, prior toward the calibration) and the
//    lens (fx, fy, cx, cy, k1, k2; off by default: the calibration measured
//    them on a board, far better than a rock's features can);
//  * the points, in the side's table frame (mm).
// Residuals in distorted pixels (the photo's keypoints) under a robust loss.
// Gauge: rotating every angle by d and the points by -d about the axis leaves
// every image unchanged; the first view taking part keeps its measured angle
// (after homing it is the best known one), which fixes that freedom.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "common/rig_calibration.h"
#include "pipeline/core/parallel_for.h"
#include "pipeline/stitch/stitch.h"

namespace aggscan {

struct BundleAdjustOptions {
  /// Feature matching and the initial triangulation. The tolerances are looser
  /// than the stitch stage's: a view whose measured angle is off by a few
  /// tenths of a degree moves its features by 1-3 px, and those observations
  /// are exactly the ones that correct it.
  FeatureCloudOptions features{
      .epipolar_px = 4.0,
      .triangulation = {.inlier_px = 4.0, .min_views = 2, .min_angle_deg = 8.0},
      .distinct_viewpoints_only = true};
  /// BundleAdjustSideImages runs SIFT on photos reduced to at most this width
  /// (features.image_scale is set per photo): at the rig's 2016 px, half size
  /// is ~4x faster and still gives hundreds of tracks on a textured rock.
  int sift_max_width = 1008;
  double angle_prior_deg = 0.1;  // 1-sigma of the measured angle (turntable's stated accuracy)
  bool refine_rig = false;       // also refine cam_from_table0 (6 dof) ...
  double rig_prior_deg = 0.2;    // ... with this 1-sigma on its rotation ...
  double rig_prior_mm = 1.0;     // ... and this on its translation
  bool refine_lens = false;      // also refine fx, fy, cx, cy, k1, k2 (no prior; needs many tracks)
  double huber_px = 1.0;         // robust loss scale on the reprojection error (px)
  /// Observations worse than this (px) after the first solve are dropped,
  /// then the problem is solved again.
  double outlier_px = 3.0;
  /// A larger correction (deg) means a wrong model: rejected, measured angles kept.
  double max_correction_deg = 2.0;
  int min_tracks = 40;           // fewer tracks (after outliers): no adjustment
  int min_views = 3;             // fewer views with observations: no adjustment
  int max_iterations = 200;      // Levenberg-Marquardt iterations per solve
  int num_threads = 1;           // Ceres threads (a side's problem is small: ~0.4 s on one core)
  int threads = kWorkerThreads;  // photos decoded and their features extracted side by side

  /// Empty when valid, else what is wrong.
  std::string Check() const;
};

struct BundleAdjustResult {
  /// True when the adjustment ran and converged; false with `reason` when the
  /// measured poses must be used as they are.
  bool refined = false;
  std::string reason;
  std::vector<double> angle_deg;  // per input view: refined, or the measured one when not adjusted
  std::vector<double> correction_deg;  // angle_deg - measured (0 when not adjusted)
  std::vector<bool> adjusted;          // the view had observations and its angle was refined
  int fixed_view = -1;                 // the gauge view (its measured angle kept)
  RigCalibration calibration;          // the input's, with the rig / lens refined when asked
  int views_used = 0;                  // views with observations
  int tracks = 0;                      // tracks (3D points) in the adjustment
  int observations = 0;                // their sightings
  int outliers_dropped = 0;            // observations over outlier_px after the first solve
  double initial_rms_px = 0;  // reprojection RMS over the final observations, measured poses
  double final_rms_px = 0;    // the same after the adjustment
  int iterations = 0;         // Ceres iterations, both solves
  double features_s = 0;      // SIFT (when BundleAdjustSideImages ran it)
  double matching_s = 0;      // pairwise matching, tracks, triangulation
  double solve_s = 0;         // Ceres
};

/// Refines one side's turntable angles from its views' features (views[i]
/// taken at measured_deg[i]; a view with no keypoints takes no part, and with
/// distinct_viewpoints_only a repeated viewpoint neither). Never fails: when
/// there is too little to adjust, `refined` is false and `reason` says why.
BundleAdjustResult BundleAdjustSide(const std::vector<ViewFeatures>& views,
                                    const std::vector<double>& measured_deg,
                                    const RigCalibration& cal,
                                    const BundleAdjustOptions& opts = {});

/// Loads view `view`'s photo (BGR) and rock mask (0/255, same size); false
/// when the view cannot be read (it then takes no part).
using BundleAdjustViewLoader = std::function<bool(int view, cv::Mat* bgr, cv::Mat* mask)>;

/// The same from photos: SIFT inside the masks of the views that take part
/// (distinct viewpoints of the measured poses unless configured otherwise; a
/// photo is loaded only while its features are extracted), then
/// BundleAdjustSide. features_s says what the extraction cost.
BundleAdjustResult BundleAdjustSideImages(int views, const BundleAdjustViewLoader& load,
                                          const std::vector<double>& measured_deg,
                                          const RigCalibration& cal,
                                          const BundleAdjustOptions& opts = {});

}  // namespace aggscan
