// Full structure-from-motion through Debian's COLMAP 3.8, run as a
// subprocess: the path for captures without a rig calibration or with a
// moving camera. COLMAP there has no library and no headers, so this module
// drives its command-line steps, checks what each step wrote (COLMAP exits 0
// after silent failures, ../shared/notes/colmap-debian.md), parses the text
// model itself and refuses implausible models instead of reporting them as
// success (the notes saw focal 200 px instead of 3310 px, rotations 117° off).
//
// Workspace layout (one directory per run, e.g. samples/<id>/work/side1/sfm):
//   images/<name>            symlinks to the input images (name = file name)
//   masks/<name>.png         symlinks to the masks, named as COLMAP wants them
//   database.db              COLMAP database (features, matches)
//   pairs.txt                circular pair list (matching = kCircular)
//   sparse/<k>/              the mapper's binary sub-models
//   model_txt/<k>/           every sub-model as a COLMAP text model
//                            (cameras.txt, images.txt, points3D.txt)
//   logs/<step>.log          stdout + stderr of each COLMAP step
//   stages/<step>.json       finished-stage markers holding the fingerprint of
//                            everything the stage depends on
//   result.json              summary of the last run (registered views,
//                            reprojection error, checks, per-step times)
// Resumable like COLMAP's own workspace: a stage whose marker matches the
// current inputs and whose output is still valid is skipped; a stage whose
// inputs changed is redone with everything after it.
//
// How the worker calls it (per side, after masks):
//
//   ColmapSfmOptions o;
//   o.workspace = sample_dir + "/work/side1/sfm";
//   o.images = {.../side1/view_000.jpg, ...};          // capture order
//   o.masks = {.../results/masks/side1/view_000.png, ...};  // 0 = ignore
//   if (calibration) o.fixed_camera = calibration->camera;   // else
//   // o.expected_focal_px = EXIF or nominal lens focal in pixels
//   o.expect_ring = true;                               // turntable capture
//   o.angles_deg = {sidecar measured angles ...};       // give them: measured on the dino,
//   // a focal 0.3x wrong gave a self-consistent ring (0.62 px, centres on a
//   // circle, cameras facing the axis) that only ring_angles rejected.
//   o.cancel = &cancel_flag;
//   Result<SfmResult> r = RunColmapSfm(o);
//   if (!r) { record r.error().ToString(); the message names the failed
//             step or plausibility check and what to do }
//   // r->model: poses (cam_from_world), points with tracks, camera;
//   // r->model_dir: the text export. Scale it later with
//   // EstimateSimilarity(marker points in the model frame, known mm
//   // positions) and ApplySimilarity(sim, &r->model); WriteColmapTextModel.
#pragma once

#include <Eigen/Core>
#include <array>
#include <atomic>
#include <cstdint>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"

namespace aggscan {

// ---------------------------------------------------------------- the model

/// One COLMAP camera: model name and parameters in COLMAP's convention
/// (pixel centres at +0.5: the top-left pixel's centre is (0.5, 0.5)).
struct SfmCamera {
  int id = 0;
  std::string model;           // "PINHOLE", "SIMPLE_RADIAL", "OPENCV", ...
  int width = 0, height = 0;   // px
  std::vector<double> params;  // as in cameras.txt
  /// Mean focal length in px (fx and fy averaged where the model has two).
  double FocalPx() const;
};

/// One registered image. x_cam = R_cam_world * x_world + t_cam_world.
struct SfmImage {
  int id = 0;
  int camera_id = 0;
  std::string name;      // file name in the workspace's images/
  int input_index = -1;  // index into ColmapSfmOptions::images, -1 if unknown
  Eigen::Matrix3d R_cam_world = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t_cam_world = Eigen::Vector3d::Zero();
  std::vector<Eigen::Vector2d> points2d;  // px, COLMAP convention (+0.5)
  std::vector<int64_t> point3d_ids;       // per point2d, -1 when not triangulated
  /// Camera centre in the world frame: -R^T t.
  Eigen::Vector3d Centre() const { return -R_cam_world.transpose() * t_cam_world; }
};

struct SfmTrackElement {
  int image_id = 0;
  int point2d_idx = 0;
};

struct SfmPoint {
  int64_t id = 0;
  Eigen::Vector3d xyz = Eigen::Vector3d::Zero();
  std::array<uint8_t, 3> rgb{0, 0, 0};
  double error_px = 0;  // COLMAP's mean reprojection error of the point
  std::vector<SfmTrackElement> track;
};

struct SfmModel {
  std::vector<SfmCamera> cameras;
  std::vector<SfmImage> images;  // registered images only
  std::vector<SfmPoint> points;

  const SfmCamera* FindCamera(int id) const;
  const SfmImage* FindImage(int id) const;
  const SfmImage* FindImageByName(const std::string& name) const;
};

/// Reads cameras.txt, images.txt and points3D.txt of a COLMAP text model.
/// kNotFound when a file is missing, kCorrupt naming file and line when a
/// line cannot be parsed or a track refers to an unknown image / point2d.
Result<SfmModel> ReadColmapTextModel(const std::string& dir);
/// Writes the three files atomically (e.g. after ApplySimilarity).
Status WriteColmapTextModel(const std::string& dir, const SfmModel& model);

/// Projects a camera-frame point with a COLMAP camera (SIMPLE_PINHOLE,
/// PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV); false when the point
/// is behind the camera or the model is not supported.
bool ProjectColmap(const SfmCamera& cam, const Eigen::Vector3d& p_cam, Eigen::Vector2d* px);

/// Mean reprojection error over every observation (px), recomputed from the
/// poses, points and cameras; falls back to the mean of the points' own
/// errors for camera models ProjectColmap does not know. 0 when no points.
double MeanReprojectionErrorPx(const SfmModel& model);

// ------------------------------------------------------- camera conversion

/// A COLMAP camera for an OpenCV lens (rig_calibration.h): PINHOLE without
/// distortion, RADIAL for k1/k2 only with fx == fy, OPENCV for k1 k2 p1 p2,
/// FULL_OPENCV when k3 != 0. Principal point shifted by +0.5 px.
SfmCamera ColmapCameraFromOpenCv(const CameraModel& cam);
/// The inverse; kInvalidArgument for models with no OpenCV equivalent
/// (e.g. FULL_OPENCV with k4..k6 != 0, fisheye models).
Result<CameraModel> OpenCvCameraFromColmap(const SfmCamera& cam);

// ------------------------------------------------------ similarity (Umeyama)

/// dst = scale * R * src + t.
struct Similarity3 {
  double scale = 1;
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
  Eigen::Vector3d Apply(const Eigen::Vector3d& p) const { return scale * (R * p) + t; }
};

/// Least-squares similarity (Umeyama 1991, with scale unless with_scale is
/// false) mapping src[i] onto dst[i]. kInvalidArgument with fewer than 3
/// pairs, different sizes, or points (nearly) collinear. `rms` (optional):
/// RMS of |Apply(src[i]) - dst[i]| in dst units.
Result<Similarity3> EstimateSimilarity(const std::vector<Eigen::Vector3d>& src,
                                       const std::vector<Eigen::Vector3d>& dst,
                                       bool with_scale = true, double* rms = nullptr);

/// Moves a model into another frame (e.g. metric mm from the background
/// markers): points and camera centres mapped by `sim`, rotations rotated.
/// Intrinsics and 2D observations are unchanged.
void ApplySimilarity(const Similarity3& sim, SfmModel* model);

// ----------------------------------------------------------- plausibility

/// Tolerances of the plausibility checks. A check that cannot apply (no
/// expected focal, not a ring) is reported as not applicable, never failed.
struct SfmCheckOptions {
  double min_registered_fraction = 0.8;   // registered / input images
  int min_registered = 3;                 // absolute floor
  int min_points = 50;                    // 3D points in the model
  double max_mean_reprojection_px = 2.0;  // over all observations
  double max_focal_rel_error = 0.25;      // |f - expected| / expected, when not fixed
  double fixed_param_rel_tol = 1e-6;      // fixed intrinsics must come back unchanged
  double min_points_in_front = 0.99;      // fraction of observations with positive depth
  // Turntable ring (expect_ring): camera centres on a circle in a plane.
  double max_ring_plane_rms = 0.05;   // out-of-plane RMS / radius
  double max_ring_radius_rms = 0.05;  // radial RMS / radius
  double max_axis_miss = 0.5;         // optical axis distance to the ring axis / radius, per view
  double max_angle_error_deg = 3.0;   // position on the ring vs expected angles, per view
  double max_points_off_axis = 1.0;   // median point distance from the axis / radius
};

/// One check's outcome. `name` is stable (tests and logs key on it).
struct SfmCheck {
  std::string name;  // registered_fraction, point_count, reprojection_error, focal_length,
                     // fixed_intrinsics, points_in_front, ring_plane, ring_circle,
                     // ring_facing, ring_direction, ring_angles, ring_points
  bool applicable = true;
  bool passed = true;
  double value = 0;  // measured figure (units in `detail`)
  double limit = 0;
  std::string detail;  // "0.31 px (limit 2.00)"
  std::string advice;  // what to do when it fails
};

struct SfmCheckReport {
  std::vector<SfmCheck> checks;
  bool ok() const;
  /// The first failed check, or nullptr.
  const SfmCheck* FirstFailure() const;
  const SfmCheck* Find(const std::string& name) const;
  /// kCorrupt: "SfM model rejected: check <name> failed: <detail>. <advice>",
  /// detail: every failed check.
  Error ToError() const;
  nlohmann::json ToJson() const;
};

/// What the capture says the model should look like.
struct SfmExpectations {
  int num_input_images = 0;                 // for the registered fraction
  std::optional<CameraModel> fixed_camera;  // intrinsics that were fixed
  std::optional<double> expected_focal_px;  // focal hint when not fixed (px, full resolution)
  bool ring = false;                        // turntable capture: centres on a circle
  /// Per input image (index = SfmImage::input_index): turntable angle in
  /// degrees (commanded or measured); empty when unknown. Only differences
  /// matter, the sense of rotation is free.
  std::vector<double> angles_deg;
};

/// Runs every applicable check on `model` (input_index must be set for the
/// ring direction/angle checks; images in capture order).
SfmCheckReport CheckSfmModel(const SfmModel& model, const SfmExpectations& expect,
                             const SfmCheckOptions& opts = {});

// ------------------------------------------------------------- the runner

/// SIFT extraction. Defaults are COLMAP's except the image size; LowTexture()
/// is what registered the textureless plaster dino (the notes).
struct SiftOptions {
  int max_image_size = 1600;    // px, longer side used for extraction (keypoints in full-res px)
  int max_num_features = 8192;  // per image
  double peak_threshold = 0.02 / 3;  // DoG contrast threshold; lower = more features on low texture
  double edge_threshold = 10;
  bool estimate_affine_shape = false;  // affine-covariant features (slower on CPU)
  bool domain_size_pooling = false;    // DSP-SIFT descriptors (slower on CPU)
  /// peak_threshold 0.002, affine shape and domain-size pooling on.
  static SiftOptions LowTexture();
};

enum class SfmMatching {
  kCircular,    // each image with its k successors in capture order, wrapping (turntable ring)
  kExhaustive,  // every pair
};

struct SfmMatchingOptions {
  SfmMatching mode = SfmMatching::kCircular;
  int circular_neighbours = 3;  // k for kCircular (pairs per image)
  double max_ratio = 0.8;       // Lowe ratio test
  double max_distance = 0.7;    // descriptor distance
  bool guided_matching = false;
  int min_num_inliers = 15;  // a pair with fewer verified matches is dropped
};

struct SfmMapperOptions {
  int min_num_matches = 15;  // pairs with fewer inliers are not used
  double init_min_tri_angle_deg = 16;
  int init_min_num_inliers = 100;  // verified matches of the initial pair (COLMAP's default)
  int abs_pose_min_num_inliers = 30;
  bool multiple_models = true;  // let COLMAP start new sub-models; the largest is used
  /// Sub-models with fewer views are dropped. COLMAP's default (10) drops a
  /// model that stalls part-way round a ring, and its next tries restart from
  /// the same well-matched views and stall at the same weak link; kept, the
  /// next try starts from the views it left out and can go round the other
  /// way. The largest model is used either way.
  int min_model_size = 3;
  /// When the largest model leaves views out, the mapper runs once more with
  /// abs_pose_min_num_inliers this low (0: never) and the larger model is
  /// kept, for the checks to judge: past a ring's weak link (pairs 30 deg
  /// apart that COLMAP takes for planar) the next view sees a few of the
  /// model's points, under 15 on the sim's seed 1, side 2.
  int retry_abs_pose_min_num_inliers = 10;
};

struct ColmapSfmOptions {
  std::string colmap_binary = "/usr/bin/colmap";
  std::string workspace;            // created if missing; reused (resumable)
  std::vector<std::string> images;  // in capture order; file names must be unique
  std::vector<std::string> masks;   // empty, or one PNG per image (0 = ignore features there)
  std::optional<CameraModel> fixed_camera;  // known intrinsics: one camera, held fixed in BA
  std::optional<double> expected_focal_px;  // focal hint when not fixed: prior + plausibility check
  /// Hold the hint (and zero distortion) while mapping instead of refining
  /// them: for a hint that is the lens's true nominal focal (the sim's). A
  /// rough hint (oxford_dino's, from skewed projection matrices) must be
  /// refined: held, the dino ring came out wrong in one CI rehearsal of two.
  bool hold_focal_hint = false;
  std::string free_camera_model =
      "SIMPLE_RADIAL";  // COLMAP model when not fixed (one shared camera)
  SiftOptions sift;
  /// Extract features on the masks' union window only (every image cut to
  /// the same window, the camera's principal point moved by its corner, the
  /// model put back into whole-frame pixels): the rock fills a few per cent
  /// of a turntable photo, and SIFT's cost is the pixels it reads. Done when
  /// masks are given and the camera is fixed or has a focal hint (without
  /// one COLMAP's focal guess is from the image size, which a window would
  /// change), and when the window is under half the frame.
  bool crop_to_masks = true;
  SfmMatchingOptions matching;
  SfmMapperOptions mapper;
  bool expect_ring = false;        // turntable capture: run the ring checks
  std::vector<double> angles_deg;  // per image: turntable angle, optional
  SfmCheckOptions checks;
  int num_threads = 2;           // every COLMAP step
  double step_timeout_s = 1800;  // per COLMAP step
  const std::atomic<bool>* cancel =
      nullptr;  // set: the running step is killed, kCancelled "interrupted"

  /// Every problem, one per line; empty when valid.
  std::vector<std::string> Check() const;
};

struct SfmStepTiming {
  std::string step;  // feature_extractor, matcher, mapper, model_converter, parse_check
  double wall_s = 0;
  bool skipped = false;  // finished in an earlier run, reused
};

struct SfmResult {
  SfmModel model;         // the largest sub-model, input_index set
  std::string model_dir;  // its text export (workspace/model_txt/<k>)
  int model_index = 0;    // <k>
  int num_input_images = 0;
  int num_registered = 0;
  double mean_reprojection_px = 0;
  std::vector<int> other_models_registered;  // registered images of the other sub-models
  std::vector<std::string> unregistered;     // names of the input images not in the model
  int num_verified_pairs = 0;                // image pairs with verified matches
  /// The window (x, y, width, height; px) the features were found in
  /// (crop_to_masks); width 0: the whole photos.
  std::array<int, 4> window{};
  SfmCheckReport checks;
  std::vector<SfmStepTiming> timings;
  /// The camera (intrinsics) the model used for input image i, nullptr if not registered.
  const SfmImage* ImageForInput(int input_index) const;
};

/// Runs (or resumes) feature extraction, matching, mapping and the text
/// export in opts.workspace, parses the largest sub-model and checks it.
/// Errors: kInvalidArgument (options; every problem listed), kNotFound (colmap
/// binary or an input missing), kIo / kTimeout (a step failed or hung; the
/// message names the step and its log), kCancelled "interrupted"
/// (cancelled), kCorrupt (a step wrote nothing usable, or the model failed a
/// plausibility check: "SfM model rejected: check <name> failed ...").
/// result.json is written in both the success and the rejected case.
Result<SfmResult> RunColmapSfm(const ColmapSfmOptions& opts);

/// The circular pair list for n images: (i, i+d mod n) for d = 1..k, no
/// duplicates (k is capped at (n-1)/2 … n-1 so each unordered pair appears once).
std::vector<std::pair<int, int>> CircularPairs(int n, int k);

/// The pair list by turntable angle: every pair whose angles lie within k
/// turntable steps of each other (the step: the median non-zero difference
/// between consecutive views' angles), so views of the same angle on later
/// turns (the paper profile's 30 views at 30 deg go round 2.5 times) are
/// matched with each other as well as with their neighbours. For one turn of
/// equal steps it is CircularPairs(n, k). Empty when the angles are not one
/// finite value per image or show no step.
std::vector<std::pair<int, int>> AnglePairs(const std::vector<double>& angles_deg, int k);

}  // namespace aggscan
