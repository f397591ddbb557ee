// Stitching the two sides by silhouette coherence: the motion that takes
// side 2's table frame onto side 1's is right when the rock model carved from
// BOTH sides' silhouettes still fills every silhouette of every view. A wrong
// motion carves away rock that some view saw, which shows as silhouette
// pixels no longer covered by the model's projection (the coherence criterion
// of turntable calibration from silhouettes, applied to the flip).
//
// Each side's visual hull is sampled once on a grid (a signed field in mm,
// positive inside, the side's turntable top as a floor); a motion's
// "silhouette deficit" is the mean, over a dozen views per side, of the
// fraction of the view's rock pixels that the projection of the intersection
// of the two hulls leaves uncovered. The voxel size follows the rock (about
// `target_points` voxels inside side 1's hull) and the working images are
// scaled so that a voxel is ~2 px, so the cost is about the same for an 8 cm
// and a 25 cm rock.
//
// Used by the stitch (stitch.h) to refine the marker or feature estimate
// (the markers' rotation about the line joining them is weak: 1-3 deg) and to
// rescue a stitch whose markers and features are each too few on their own:
// a partial estimate (2 marker points swept about their axis, a feature fit
// with few inliers) is refined and accepted when its deficit is small.
#pragma once

#include <Eigen/Core>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "common/error.h"
#include "common/rig_calibration.h"
#include "pipeline/core/geometry.h"

namespace aggscan {

struct SilhouetteSideInput {
  std::vector<cv::Mat> masks;                // rock masks (0/255) at the camera's resolution
  std::vector<geom::Rigid3> cam_from_table;  // each view's pose in the side's table frame
};

struct SilhouetteStitchOptions {
  int max_views = 12;         // per side, spread over the distinct viewpoints
  int target_points = 30000;  // voxels inside side 1's hull: sets the voxel size
  double voxel_px = 2.0;      // a voxel's size in the working images: sets their scale
  int max_evaluations = 400;  // per refinement (Nelder-Mead)
  /// Views whose masks alone carve away rock the side's other views hold are
  /// left out (left_out()); off where the caller already left them out.
  bool leave_out_disagreeing = true;
};

/// A search over every orientation, for a stitch with nothing to start from
/// (no marker seen on both sides, too few feature matches): where side 2's up
/// may point in side 1's frame (points spread evenly over the sphere) times
/// the turns about it, each with the hulls' centres put together. The most
/// coherent candidates, each at least `distinct_deg` from those refined before
/// and from the motions they reached, are refined: `refine` of them, more (up
/// to twice as many) until two distinct motions are found, so the best one has
/// a runner-up to be judged against.
struct SilhouetteSearchOptions {
  int directions = 72;  // about 24 deg apart
  int turns = 15;       // 24 deg apart
  int refine = 4;
  double distinct_deg = 20;
  double step_deg = 8;  // the refinements' first steps (deg and mm)
};

struct SilhouetteFit {
  geom::Rigid3 T;            // moving -> reference, refined
  double deficit_start = 1;  // deficit of the starting motion
  double deficit = 1;        // after refinement
  int evaluations = 0;
  double seconds = 0;
};

struct SilhouetteSearch {
  /// The refined candidates, the most coherent first; those that converged
  /// to the same motion (within distinct_deg / 4) merged.
  std::vector<SilhouetteFit> fits;
  int evaluations = 0;  // the whole search's
  double seconds = 0;
};

class SilhouetteStitcher {
 public:
  /// Prepares both sides (working masks, hull fields). kInvalidArgument when a
  /// side has no usable mask or the hull of a side is empty (masks or poses
  /// wrong).
  static Result<SilhouetteStitcher> Create(const SilhouetteSideInput& reference,
                                           const SilhouetteSideInput& moving,
                                           const CameraModel& camera,
                                           const SilhouetteStitchOptions& opts = {});

  /// Mean fraction of the views' rock pixels left uncovered by the two hulls'
  /// intersection under `moving_to_reference` (0 = perfectly coherent, 1 =
  /// the hulls do not meet).
  double Deficit(const geom::Rigid3& moving_to_reference) const;
  /// The deficit before the sides meet: each side's own hull in its own
  /// views. What the masks disagree on within a side (a shadow one view took
  /// for rock that the others carve away, rock a mask missed) is uncovered
  /// whatever the motion; a stitch is judged by what it leaves beyond this.
  double OwnDeficit() const;

  /// Nelder-Mead over rotation (about side 1's hull centre) and translation
  /// from `start`, initial steps step_deg and step_mm, then a finer pass.
  SilhouetteFit Refine(const geom::Rigid3& start, double step_deg = 2.0,
                       double step_mm = 2.0) const;

  /// The search from no start. Its cost is directions x turns deficits and
  /// `refine` to 2 x `refine` refinements (at 1008 x 756 on the sim, 12 views a
  /// side: 1080 deficits and about 2300 evaluations in all).
  SilhouetteSearch Search(const SilhouetteSearchOptions& opts = {}) const;

  double voxel_mm() const;
  /// Centre of side 1's hull (table frame of side 1, mm).
  Eigen::Vector3d reference_centre() const;
  /// The views of side `side` (0 reference, 1 moving; indices into its
  /// input) left out because their masks alone carved away rock the side's
  /// other views hold (median + 5 MAD of the views and over 5 % of the volume
  /// they agree on; at most a third of the views).
  const std::vector<int>& left_out(int side) const;
  /// Views used per side and the working image scale.
  int views_used() const;
  double image_scale() const;

 private:
  struct Impl;
  std::shared_ptr<const Impl> impl_;
};

/// The polish of a motion the silhouettes chose: the same deficit on a grid
/// with half the voxel (8x `coarse.target_points`), Nelder-Mead from `start`
/// with 0.5 deg / 0.5 mm steps. The coarse grid's steps leave a motion a few
/// tenths of a degree off, which shortens the rock where the sides' hulls
/// meet. `done` when the fine deficit went down (T is then the polished
/// motion, else `start`). Not done either when the finer voxel spans under
/// `voxel_px` pixels of the photos (low resolution): `problem` says so.
struct SilhouettePolish {
  bool done = false;
  geom::Rigid3 T;
  double voxel_mm = 0;
  double deficit_start = 0;  // on the fine grid
  double deficit = 0;
  double moved_deg = 0;
  int evaluations = 0;
  double seconds = 0;
  std::string problem;  // the fine grid could not be prepared, or the photos do not resolve it
};
/// `coarse` is the stitcher that chose the motion (built with `coarse_opts`):
/// its working image scale tells, before the fine grid is built, whether the
/// photos resolve half its voxel, and the views it left out stay out.
SilhouettePolish PolishSilhouetteStitch(const SilhouetteStitcher& coarse,
                                        const SilhouetteSideInput& reference,
                                        const SilhouetteSideInput& moving,
                                        const CameraModel& camera, const geom::Rigid3& start,
                                        const SilhouetteStitchOptions& coarse_opts = {});

}  // namespace aggscan
