#include "pipeline/worker/worker_config.h"

#include <filesystem>
#include <vector>

#include "pipeline/masks/mask_net.h"
#include "store/layout.h"

namespace aggscan {

bool ParsePosesChoice(const std::string& word, PosesChoice* out) {
  PosesChoice c;
  if (word == "turntable+ba") {
    c.path = PosesPath::kTurntable;
  } else if (word == "turntable") {
    c.path = PosesPath::kTurntable;
    c.bundle_adjust = false;
  } else if (!ParsePosesPath(word, &c.path)) {
    return false;
  }
  *out = c;
  return true;
}

const char* PosesChoiceWords() { return "turntable+ba, turntable, sfm, auto"; }

Result<ReconstructOptions> ReconstructOptionsFromConfig(const Config& cfg) {
  ReconstructOptions ro;
  auto net = LoadMaskNet(cfg.mask);
  if (!net.ok()) return net.error();
  ro.worker.mask_net = *net;
  ro.worker.empty_turntable_max_angle_deg = cfg.mask.empty_turntable_max_angle_deg;
  PosesChoice poses;
  if (!ParsePosesChoice(cfg.worker.poses, &poses)) {
    // LoadConfigFile refuses any other word; a Config built in code may not.
    return MakeError(ErrorClass::kInvalidArgument, "[worker] poses = \"" + cfg.worker.poses +
                                                       "\" is not one of " + PosesChoiceWords());
  }
  ro.poses = poses.path;
  ro.bundle_adjust = poses.bundle_adjust;
  return ro;
}

Result<Config> ConfigForSample(const std::string& sample_dir, std::string* source) {
  const std::string path = sample_dir + "/" + layout::kConfigCopy;
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) {
    if (source) *source = "defaults";
    return Config{};
  }
  std::vector<ConfigProblem> problems;
  auto cfg = LoadConfigFile(path, &problems);
  if (!cfg.ok()) {
    std::string why = cfg.error().ToString();
    for (const auto& p : problems) why += "; " + p.ToString();
    return MakeError(ErrorClass::kCorrupt, "the config the sample was armed with, " + path +
                                               ", does not load (" + why +
                                               "): give one with --config");
  }
  if (source) *source = path;
  return std::move(cfg.value());
}

}  // namespace aggscan
