// `aggscan validate`: the accuracy harness. For each rock
// (procedural seeds, or the meshes of a folder scaled to riprap size) it
// captures a simulated sample with the sim rig's realism on, reconstructs it
// with the worker's stages (computed masks, calibrated turntable poses,
// stitching, surface, morphology) and compares the reconstructed 3D
// morphology with the true mesh's. The table follows the source study's
// Table 1; the summary gives volume MPE = mean((R-T)/T) and MAPE, the worst
// a, b, c and sphericity errors, and the verdict against the targets.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <optional>
#include <ostream>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan {

struct ValidateOptions {
  int count = 20;             // procedural rocks: seeds seed .. seed+count-1
  uint64_t seed = 1;          // first seed
  std::string mesh_dir;       // instead: every .ply/.obj/.stl file in this folder
  std::string unit;           // unit of those files: mm | cm | m (required with mesh_dir)
  double scale_min_mm = 0;    // mesh rocks: longest dimension c scaled to this (0: as given) ...
  double scale_max_mm = 0;    // ... up to this, spread evenly over the files in name order
  int sides = 2;              // sides per rock (the operator flips the rock between them)
  int views_per_side = 30;    // views per side, 30 deg apart (the study's protocol)
  int width = 0, height = 0;  // image size (0: the config's 2016 x 1512)
  double camera_distance_mm = 0;  // the tripod's distance from the disc centre, as the rig is set
                                  // up for the batch's rock sizes (0: the config's 650 mm)
  std::string calibration = "charuco";  // charuco: calibrate from a simulated board capture;
                                        // truth: the sim's exact calibration
  std::string keep;  // keep every sample under this new folder (empty: temporary)
  // The renderer of the photos: sim (the sim rig's own) or blender (every
  // view redrawn by Blender's Cycles from the same poses, cli/blender_render.h;
  // the sim's lens distortion is off then, Blender's camera is a pinhole).
  std::string renderer = "sim";
  std::string look;          // blender: one look for every rock ("surface=wood,light=low-sun,...");
                             // empty: BatchLook(i) per rock, the variety cycled
  int samples = 16;          // blender: Cycles samples per pixel
  int look_index = 0;        // blender: BatchLook index of the first rock (to continue a batch)
  bool backgrounds = false;  // blender: also each view's empty-turntable photo (SAMPLE/empty/)
  bool denoise = true;       // blender: the path tracer's noise out, a camera's in
                             // (scripts/blender/denoise.py)
  bool render_only = false;  // capture (and render) the samples into --keep, reconstruct nothing:
                             // test sets for `aggscan masks eval`
};

/// The accuracy targets: the product aims at a tenth of the study's errors.
struct ValidateTargets {
  double volume_mpe_pct = 1.0;   // |mean((R-T)/T)| in %
  double volume_mape_pct = 2.0;  // mean(|R-T|/T) in %
  double dims_pct = 2.0;         // every rock's a, b, c within this, in %
  double sphericity = 0.02;      // every rock's |R-T|
};

/// A box's sorted sides and its volume relative to the mesh's minimum box.
struct BoxDims {
  double a_mm = 0, b_mm = 0, c_mm = 0;
  double volume_ratio = 1;
};

/// The figures compared: study Table 1's columns.
struct RockFigures {
  double volume_mm3 = 0, area_mm2 = 0, a_mm = 0, b_mm = 0, c_mm = 0, sphericity = 0;
  // Other distinct boxes within kBoxAmbiguousVolume of the minimum's volume
  // (MeshProps::near_boxes): when there are any, a, b, c are ill-conditioned.
  std::vector<BoxDims> near_boxes;
};

/// A rock's a, b, c errors (%). The reconstruction's minimum box against the
/// truth's, or, when either mesh's a, b, c are ill-conditioned (other boxes
/// within kBoxAmbiguousVolume of its minimum's volume, mesh_props.h), the
/// nearest pair among those near-minimal boxes: which of two boxes 0.3 %
/// apart is the minimum turns on less than the reconstruction's volume error,
/// so either is the rock's box. The error against the minimum boxes alone is
/// reported beside it (DimsAgainstMinimumBox).
struct DimErrors {
  double a_pct = 0, b_pct = 0, c_pct = 0;
  int truth_box = 0;  // 0: the truth's minimum box; k: its near_boxes[k - 1]
  int rec_box = 0;    // the same for the reconstruction
  bool NearBox() const { return truth_box != 0 || rec_box != 0; }
  double MaxAbs() const;
};
DimErrors DimsAgainstTruth(const RockFigures& truth, const RockFigures& rec);
/// The figures of a truth.json or a morphology_3d object (near-minimal boxes
/// included; older files' second box when it is near).
RockFigures RockFiguresFromJson(const nlohmann::json& j);
/// The same against the truth's minimum-volume box only.
DimErrors DimsAgainstMinimumBox(const RockFigures& truth, const RockFigures& rec);

struct StitchTruthError {
  bool measured = false;
  double deg = 0, mm = 0;                      // the stitch taken
  std::string source;                          // markers | features | ... (stitch.json)
  double markers_deg = -1, markers_mm = -1;    // the markers' own estimate
  double features_deg = -1, features_mm = -1;  // the features' own estimate
  double silhouette_deficit = 0;               // of the stitch taken
  bool consistent = true;                      // the sources agreed (stitch.json)
  std::string warning;                         // stitch.json's
};

/// The sample's stitch (results/stitch.json) against truth.json's rest poses,
/// over the vertices of results/mesh.ply; measured false when any is missing.
StitchTruthError StitchAgainstTruth(const std::string& sample_dir, const nlohmann::json& truth);

struct ValidateRock {
  std::string id;       // "seed-7" or the mesh file's stem
  std::string source;   // "procedural seed 7" or the mesh path
  std::string status;   // ok | skipped (unusable input) | failed (capture or reconstruction)
  std::string message;  // why skipped or failed
  double scale = 1;     // mesh rocks: factor applied to the file (after its unit)
  RockFigures truth, rec;
  double seconds = 0;         // capture + reconstruction, wall time
  std::string look;           // blender: the look's name (surface/light/stone)
  double render_frame_s = 0;  // blender: mean seconds per rendered frame
  // The worker's masks against the renderer's true silhouettes, over every
  // view (0 when not measured).
  double mask_iou_min = 0, mask_iou_mean = 0;
  // The stitch of each further side onto side 1 against the truth (the
  // worst side): rotation error and displacement RMS over the reconstructed
  // surface; the source that won; each source's own estimate against the
  // truth where it had one (-1: none). Two sides only.
  StitchTruthError stitch;
  std::vector<std::string> quality_flags;  // the worker's quality flag codes (morphology.json)
};

struct ValidateSummary {
  int rocks_ok = 0, rocks_failed = 0, rocks_skipped = 0;
  double volume_mpe_pct = 0, volume_mape_pct = 0, volume_max_abs_pct = 0;
  double area_mpe_pct = 0;
  double a_max_abs_pct = 0, b_max_abs_pct = 0, c_max_abs_pct = 0;  // DimsAgainstTruth
  int dims_within = 0;              // rocks with a, b, c all within the target
  int dims_near_box = 0;            // rocks matched through a near-minimal box (DimErrors::NearBox)
  double dims_raw_max_abs_pct = 0;  // minimum box against minimum box only
  int dims_raw_within = 0;          // ... rocks within the target that way
  double sphericity_max_abs = 0;
  double mask_iou_min = 0,
         mask_iou_mean = 0;  // over every view of every rock whose masks were made
  double stitch_max_deg = 0, stitch_max_mm = 0;  // worst stitch against the truth
  int stitch_measured = 0, stitch_within = 0;    // rocks measured, and within the stitch targets
  double stitch_target_deg = 0.5, stitch_target_mm = 0.5;
  double render_frame_s = 0;  // blender: mean seconds per frame
  bool volume_mpe_pass = false, volume_mape_pass = false, dims_pass = false,
       sphericity_pass = false;
  bool pass = false;  // every target met, no rock failed, at least one rock measured
};

struct ValidateReport {
  ValidateOptions options;
  ValidateTargets targets;
  nlohmann::json settings;  // resolution, views, calibration used, the sim's realism switches
  std::vector<ValidateRock> rocks;
  ValidateSummary summary;
};

/// Runs the whole harness; progress lines go to `log`. Errors are for the
/// harness itself (work folder, calibration); a rock that fails is a row.
Result<ValidateReport> RunValidation(const ValidateOptions& options, std::ostream& log);

/// Summary statistics and verdicts over the rows with status ok.
ValidateSummary Summarize(const std::vector<ValidateRock>& rocks, const ValidateTargets& targets);

/// The table and summary as text, and as JSON.
void PrintValidateReport(const ValidateReport& report, std::ostream& out);
nlohmann::json ValidateReportToJson(const ValidateReport& report);

/// The command: parses args (after "validate"), runs, prints. Exit code 0 when
/// every target is met, 1 when one is not (or a rock failed), 2 usage.
int RunValidateCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err);

/// The usage lines of the command (for aggscan's help).
void PrintValidateUsage(std::ostream& out);

}  // namespace aggscan
