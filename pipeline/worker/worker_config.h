// From a config to the worker's options: the one place where [mask] and
// [worker] become ReconstructOptions, for aggscan-worker (queue and --sample)
// and for `aggscan reconstruct` alike, so that a sample reconstructed by hand
// goes through the same stages, with the same fingerprints, as the worker's.
#pragma once

#include <string>

#include "common/error.h"
#include "config/config.h"
#include "pipeline/worker/reconstruct.h"

namespace aggscan {

/// The poses choice ([worker] poses, `aggscan reconstruct --poses`):
///   "turntable+ba"  calibration and measured angles, refined by bundle adjustment
///   "turntable"     calibration and measured angles as read
///   "sfm"           full SfM through COLMAP
///   "auto"          turntable+ba with a rig calibration, sfm without
struct PosesChoice {
  PosesPath path = PosesPath::kTurntable;
  bool bundle_adjust = true;
};
/// False for any other word.
bool ParsePosesChoice(const std::string& word, PosesChoice* out);
/// The words ParsePosesChoice takes, for messages: "turntable+ba, turntable, sfm, auto".
const char* PosesChoiceWords();

/// ReconstructOptions from a validated config: the mask network ([mask]
/// method = "onnx": loaded here, so kNotFound/kCorrupt/kInvalidArgument from
/// LoadMaskNet when its model is missing or broken), the empty-turntable
/// angle limit and the poses choice. Everything else stays at its default.
Result<ReconstructOptions> ReconstructOptionsFromConfig(const Config& cfg);

/// The config a by-hand reconstruction of `sample_dir` uses when none is
/// given: the one the sample was armed with (samples/<id>/config.toml), else
/// the defaults (`*source` says which: the file's path or "defaults").
/// kCorrupt naming the file when the sample's copy does not load.
Result<Config> ConfigForSample(const std::string& sample_dir, std::string* source);

}  // namespace aggscan
