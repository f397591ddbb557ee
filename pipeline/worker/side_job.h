// The worker's first stages on a durable sample directory (store/layout.h):
// per side, a foreground mask and the 2D morphology of every view; per sample,
// the statistics over all sides.
//
// Outputs (all written atomically, fsutil.h):
//   results/masks/side<N>/view_NNN.png   0/255 rock mask of each view
//   results/side<N>_morph2d.json         per-view figures + per-side stats; the
//                                        side stage is finished iff it exists
//   results/morph2d.json                 per-side and overall stats (sample stage)
//
// Resumable: a finished side (its result file) is skipped; within a side, a view
// whose mask PNG already exists reuses it instead of segmenting again.
// Temporary files (.tmp-*) left by a crash are ignored and cleaned up.
#pragma once

#include <atomic>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/error.h"
#include "pipeline/core/image_io.h"
#include "pipeline/core/parallel_for.h"
#include "pipeline/core/records.h"
#include "pipeline/core/stage_runner.h"
#include "pipeline/masks/mask.h"
#include "pipeline/masks/mask_net.h"
#include "store/empty_turntable.h"

namespace aggscan {

struct WorkerOptions {
  MaskOptions mask;                   // segmentation parameters (and the network's refinement)
  std::shared_ptr<MaskNet> mask_net;  // set ([mask] method = "onnx"): its output seeds the mask
  bool reuse_masks = true;            // reuse results/masks/... PNGs written by an earlier attempt
  ImageLimits image_limits;           // photos outside these are refused before decoding
  double empty_turntable_max_angle_deg =
      0.5;  // [mask]: the empty-turntable photo's angle within this of the view's
  const std::atomic<bool>* cancel =
      nullptr;                   // checked between views; set -> kCancelled "interrupted"
  int threads = kWorkerThreads;  // views masked side by side
};

/// Masks and 2D morphology of side `side` (>= 1) of the sample at `sample_dir`.
/// kNotFound if side<N>/manifest.json is missing (the side is not captured),
/// kCorrupt if the manifest or a listed image is inconsistent or unreadable.
Status ProcessSide(const std::string& sample_dir, int side, const WorkerOptions& opts = {});

/// results/morph2d.json from every side<N> directory of the sample: sides with a
/// manifest but no result yet are processed first. kNotFound when no side has
/// been captured or a side directory has no manifest.
Status ProcessSample(const std::string& sample_dir, const WorkerOptions& opts = {});

/// The captured sides of a sample (its side<N> directories), ascending;
/// kNotFound naming the sample when there is none.
Result<std::vector<int>> CapturedSides(const std::string& sample_dir);

/// The fingerprint of side `side`'s masks (pipeline/core/stage_runner.h): the
/// side's manifest, the mask options, the network's options and file, the
/// sample's empty-turntable set and how near its photos must be.
Result<std::string> MasksFingerprint(const std::string& sample_dir, int side,
                                     const WorkerOptions& opts);

/// The stage "masks side N" (masks and every view's 2D figures,
/// ProcessSide) with its fingerprint and outputs, as the side job and the
/// sample job both declare it.
Result<StageDecl> MasksStage(const std::string& sample_dir, int side, const WorkerOptions& opts);

/// The side job: MasksStage through the stage runner, so that the sample job
/// later keeps its result when its fingerprint still matches and redoes it
/// when not.
Status RunSideJob(const std::string& sample_dir, int side, const WorkerOptions& opts);

/// A view whose mask has at least this many pixels on the photo's outermost
/// rows and columns shows a rock cut by the frame.
inline constexpr int kMaskFrameMinPx = 3;
/// A view whose mask covers less than this fraction of the side's largest
/// mask lost the rock (a 3:1 rod seen end-on keeps about a third; the sim's
/// 22 cm ashlar 923, reaching the frame, left masks of 0.8 %).
inline constexpr double kMaskMinAreaOfLargest = 0.15;

/// Marks the views of one side's result whose masks cannot be the rock's
/// whole silhouette: cut by the photo's edge (mask_frame_px), or under
/// kMaskMinAreaOfLargest of the side's largest (mask_area_fraction). Those get
/// ok = false and an error; the later stages leave them out. Returns what was
/// found and what to do, empty when nothing.
std::string CheckSideMasks(std::vector<records::View2D>* views);

/// kCorrupt, naming the side, the views left and what to do, when a side
/// result (side<N>_morph2d.json) lost more than a third of its views to
/// CheckSideMasks: the silhouettes left are too few for a trustworthy model,
/// and the cause (a rock too big for the frame, say) is usually in every view.
Status SideHasEnoughWholeViews(const records::SideResult& side_result);

/// Paths of the outputs, relative names as in the layout above.
std::string SideResultPath(const std::string& sample_dir, int side);
std::string SampleResultPath(const std::string& sample_dir);
std::string ViewMaskPath(const std::string& sample_dir, int side, int view);

/// The measured turntable angle of a view from its sidecar file in side_dir
/// (NaN without one).
double MeasuredAngle(const std::string& side_dir, const std::string& sidecar);

/// The empty-turntable photo of a view shot at `angle_deg` (the sample's
/// SAMPLE/empty/ set, nearest angle), decoded: the masks' per-pixel
/// background. An empty Mat, with the reason in *why, when the nearest was
/// shot farther away than opts.empty_turntable_max_angle_deg, cannot be
/// decoded or is not the photo's size: a set from another camera mode or
/// angle must not decide what is rock.
cv::Mat EmptyTurntablePhoto(const std::string& sample_dir, const EmptyTurntableSet& set,
                            double angle_deg, const cv::Mat& photo, const WorkerOptions& opts,
                            std::string* why);

}  // namespace aggscan
