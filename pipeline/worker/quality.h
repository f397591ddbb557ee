// What the worker cannot vouch for in a reconstruction: quality flags, each
// with a code and a reason that says what was measured, the limit and what to
// check. A sample with any flag is not confident: its figures are still
// written (a figure computed from doubtful data is still evidence), but
// `aggscan show`, the API and the library CSV say that it is doubtful and why.
//
// The limits sit between what a sound capture gives and what a broken one
// does (docs/validation.md has the measured figures): on the sim rig's own
// renders the masks agree with the model's silhouettes at IoU >= 0.98 on every
// view and the stitch leaves < 0.005 of the silhouettes uncovered; masks that
// take in a cast shadow give 0.77-0.9 and a stitch that the silhouettes cannot
// confirm leaves 0.05-0.08.
#pragma once

#include <nlohmann/json.hpp>

namespace aggscan {

struct QualityLimits {
  double silhouette_iou_mean = 0.97;  // masks vs the model's silhouettes, mean over the views ...
  double silhouette_iou_min = 0.95;   // ... and the worst view
  double stitch_rms_mm = 1.0;         // residual of the stitch's points (markers or features)
  /// Silhouettes uncovered by the stitched model beyond what each side's own
  /// hull leaves (StitchOptions::silhouette_accept).
  double stitch_deficit = 0.011;
  double scale_residual_mm =
      0.5;  // scale references (labels, ArUco) against their configured distances
  /// Mean fraction of the carved hull's silhouettes that the surface no
  /// longer covers. A surface moved in by d all round a rock of size L loses
  /// about 2d/L of its outline and 3d/L of its volume; the Taubin smoothing
  /// and the depth search's noise about the hull take in a little on sound
  /// captures too.
  double outline_loss = 0.012;
};

/// The flags, [{"code", "reason"}], of a reconstruction from its quality
/// block (morphology.json "quality"), its stitch record (results/stitch.json)
/// and the surface's per-view silhouette IoU ([{"side", "view", "iou"}]).
/// Codes: mask_consistency, outline_loss, stitch_unconfirmed,
/// stitch_outline_only, stitch_disagreement, stitch_residual, scale_residual,
/// not_watertight.
nlohmann::json QualityFlags(const nlohmann::json& quality, const nlohmann::json& stitch,
                            const nlohmann::json& silhouette_iou, const QualityLimits& limits = {});

}  // namespace aggscan
