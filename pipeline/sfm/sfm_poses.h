// The full-SfM poses path of the reconstruction. One side's
// views posed by Debian's COLMAP (colmap_sfm.h) instead of the calibrated
// turntable, for captures without a rig calibration or with a moving camera.
//
// Per side:
//   1. RunColmapSfm on the side's photos with the rock masks (only features on
//      the rock: the backdrop does not turn with it), a circular pair list, the
//      intrinsics fixed when known (calibration, or an earlier side's SfM
//      camera so that every side ends in one camera model), the sidecars'
//      measured angles as plausibility input (the ring checks).
//   2. The background colour labels (rig.markers, on the disc, so fixed in the
//      SfM frame) and the ArUco scale markers (rig.aruco_markers, if any) are
//      detected outside the rock mask and triangulated with the SfM poses; a
//      similarity (Umeyama) maps them onto their configured positions in the
//      turntable frame. Fewer than 3 reference points, or an RMS residual
//      above max_scale_residual_mm, rejects the side: the scale and frame would
//      be wrong.
//   3. The model is moved into the metric turntable frame; each registered
//      view gets its cam_from_table pose (mm), so the stitch, surface and
//      morphology stages run unchanged. Unregistered views are left out and
//      listed.
//   4. The scaled model is exported as a COLMAP text model
//      (results/sfm/side<N>/{cameras,images,points3D}.txt, atomically).
// The COLMAP workspace is samples/<id>/work/side<N>/sfm (resumable stage by
// stage, colmap_sfm.h).
#pragma once

#include <atomic>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/core/records.h"
#include "pipeline/core/view.h"
#include "pipeline/markers/view_evidence.h"

namespace aggscan {

struct SfmPosesOptions {
  std::string colmap_binary = "/usr/bin/colmap";
  /// SIFT on at most this many px along the longer side: the rig's 2016 x
  /// 1512 stills at full size (the rock fills a small part of the photo:
  /// ~1000 SIFT features inside its mask on the sim at 2016 px, ~200 at
  /// 1008 px, too few for COLMAP's initial pair); a 12 MP photo is reduced
  /// (the notes: ~1-2 s and ~1.5 GB a photo at 1600-2000 px on 2 cores).
  int max_image_size = 2016;
  int circular_neighbours =
      3;  // pairs per view in the ring's pair list (~4x cheaper than exhaustive)
  /// COLMAP camera model when the intrinsics are not known: k1 and k2 like
  /// the rig calibration's lens.
  std::string free_camera_model = "RADIAL";
  /// COLMAP's mapper on a small rock: ~1000 SIFT features a view, adjacent
  /// views 30 deg apart share 30-300. With COLMAP's defaults (initial pair
  /// 100 inliers and 16 deg, 30 inliers to register a view) sim seed 1 side
  /// 2 stopped at 7 of 12 views and the model was dropped; with these all 12
  /// register. The plausibility checks still judge the model.
  int init_min_num_inliers = 50;
  double init_min_tri_angle_deg = 8;
  int abs_pose_min_num_inliers = 15;
  int num_threads = 2;
  /// SIFT on the masks' union window only (ColmapSfmOptions::crop_to_masks);
  /// false: on the whole photos, as COLMAP alone does (for comparison).
  bool crop_to_masks = true;
  /// RMS of the label/ArUco similarity fit (mm) above which the side is
  /// rejected: the located references do not fit the configured layout.
  double max_scale_residual_mm = 2.0;
};

struct SfmPosesInput {
  std::string sample_dir;
  int side = 1;
  std::vector<SampleView> views;  // capture order; the views with a rock mask, not yet posed
  /// False when nothing measured the views' angles (a hand-turned table, an
  /// import): their angle_deg is the plan's, which orders them but is no
  /// check of the model's camera ring (ring_angles is then not applied).
  bool angles_measured = true;
  /// The camera was walked round a still rock (capture.mode =
  /// "moving_camera"): the views come in any order, so every pair is matched,
  /// and there is no camera ring to check; the angles are not used.
  bool moving_camera = false;
  /// Known intrinsics (full image size), held fixed; nullopt: COLMAP
  /// estimates them (free_camera_model).
  std::optional<CameraModel> fixed_camera;
  std::string camera_source;  // recorded: "calibration", "sfm side 1", "sfm (estimated)",
                              // "sfm (focal hint held)"
  std::optional<double> expected_focal_px;  // focal hint when not fixed (px, full size)
  std::string focal_hint_source;            // recorded with it
  /// For the expected apparent label size (ExpectedLabelSidePx); may be null.
  const RigCalibration* calibration = nullptr;
  RigConfig rig;  // labels and ArUco markers (the sample's config)
  const std::atomic<bool>* cancel = nullptr;
  /// The sample's view evidence (view_evidence.h); may be null. When it was
  /// gathered with this side's lens and label options (a calibrated rig), the
  /// labels and ArUco markers are taken from it where an earlier stage found
  /// them, and what is found here is kept in it: the stitch then finds them
  /// again in no view. Without a rig calibration the SfM camera has no metric
  /// pose yet, so the labels are searched without their expected size here
  /// and with it by the stitch: two searches of different kinds.
  ViewEvidenceCache* evidence = nullptr;
};

/// The focal hint for a rig without calibration, from the sample's config:
/// the lens's nominal focal (camera.lens_focal_mm over camera.sensor_width_mm,
/// times the image width) when set, else the sim lens (camera.backend "sim":
/// sim.hfov_deg). nullopt when the config names no lens.
struct FocalHint {
  double focal_px = 0;
  std::string
      source;  // recorded with it, e.g. "camera.lens_focal_mm 6 / camera.sensor_width_mm 6.287"
};
std::optional<FocalHint> FocalHintFromConfig(const Config& cfg, int image_width);

/// Runs the path above and returns the side's poses record: {"side",
/// "method": "sfm", "method_detail", "sfm" (registered views, reprojection
/// error, checks, timings, workspace, model export), "scale" (reference,
/// factor, residual_mm, per-reference residuals), "calibration" (the camera
/// the views were posed with and a turntable pose derived from the SfM
/// poses, method "sfm": CalibrationFromJson reads it), "views" (view, image,
/// mask, angle_deg, cam_from_table_4x4 per registered view),
/// "unregistered_views"}. Errors name the side, the failed step or check and
/// what to do; nothing is written to results/ then except COLMAP's workspace.
Result<records::PosesRecord> RunSfmPoses(const SfmPosesInput& in, const SfmPosesOptions& opts);

/// The results-relative directory of a side's exported model: "sfm/side<N>".
std::string SfmModelDirName(int side);

}  // namespace aggscan
