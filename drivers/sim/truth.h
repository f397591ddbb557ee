// Ground truth of a simulated capture, for tests and the accuracy harness:
// per view the rock mask (truth/side<N>/view_NNN_mask.pgm) and the true
// rock->camera pose; per sample (truth.json) the rock's true volume, area,
// principal dimensions and sphericity, its rest pose on each side, the camera
// intrinsics and the object markers. A real rig has none of this.
#pragma once

#include <functional>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>

#include "config/config.h"
#include "drivers/factory.h"

namespace aggscan::sim {

class SimWorld;

class TruthRecorder {
 public:
  explicit TruthRecorder(std::shared_ptr<SimWorld> world) : world_(std::move(world)) {}
  /// Receives every rendered view's truth from the rig's sim camera (no-op
  /// when the camera is not simulated). `truth_dir_for(sample_id)` names the
  /// folder for that sample's truth files.
  void Attach(RigDevices& rig, std::function<std::string(const std::string&)> truth_dir_for);
  /// Writes truth.json for everything recorded so far.
  Status WriteTruthJson(const std::string& path, const Config& config) const;
  /// The sample-level truth (no per-view entries).
  nlohmann::json SampleTruth(const Config& config) const;

 private:
  std::shared_ptr<SimWorld> world_;
  mutable std::mutex mu_;
  nlohmann::json views_ = nlohmann::json::array();
};

}  // namespace aggscan::sim
