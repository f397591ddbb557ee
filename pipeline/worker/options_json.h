// The worker's option structs as JSON: what goes into a stage's fingerprint
// (pipeline/core/stage_runner.h), so that a result is reused only when the options
// that made it are the ones asked for now. Thread counts and program paths
// are left out: they change how fast a result comes, not what it is.
//
// Every struct's size is checked at compile time in options_json.cpp: a field
// added to one of them fails the build there until it is added here too (a
// field left out would let a stage keep a result its new value changes).
#pragma once

#include <nlohmann/json.hpp>

#include "pipeline/core/image_io.h"
#include "pipeline/masks/mask.h"
#include "pipeline/masks/mask_net.h"
#include "pipeline/poses/bundle_adjust.h"
#include "pipeline/sfm/sfm_poses.h"
#include "pipeline/stitch/stitch.h"
#include "pipeline/surface/photo_refine.h"
#include "pipeline/surface/visual_hull.h"

namespace aggscan {

nlohmann::json OptionsJson(const MaskOptions& o);
nlohmann::json OptionsJson(const PhotoRefineOptions& o);
nlohmann::json OptionsJson(const VisualHullOptions& o);
nlohmann::json OptionsJson(const BundleAdjustOptions& o);
nlohmann::json OptionsJson(const SfmPosesOptions& o);
nlohmann::json OptionsJson(const FeatureCloudOptions& o);
nlohmann::json OptionsJson(const geom::TriangulationOptions& o);
nlohmann::json OptionsJson(const ImageLimits& o);
/// The network's file is fingerprinted by its bytes by the caller; here its
/// input size, normalisation and threshold.
nlohmann::json OptionsJson(const MaskNetOptions& o);

}  // namespace aggscan
