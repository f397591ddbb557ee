#include "cli/reconstruct_command.h"

#include <filesystem>

#include "config/config.h"
#include "pipeline/mask_net.h"
#include "pipeline/reconstruct.h"

namespace aggscan {

int RunReconstructCommand(const std::vector<std::string>& args, std::ostream& out,
                          std::ostream& err) {
  std::string sample_dir, state_dir, config_path, surface = "hull+photo", poses, from;
  // An option taking one of two words; false (usage error said) otherwise.
  auto choice = [&](size_t* i, const char* a, const char* b, const char* help, std::string* v) {
    if (*i + 1 >= args.size() || (args[*i + 1] != a && args[*i + 1] != b)) {
      err << "aggscan reconstruct: " << args[*i] << " needs " << help << "\n";
      return false;
    }
    *v = args[++*i];
    return true;
  };
  for (size_t i = 0; i < args.size(); ++i) {
    if (args[i] == "--poses") {
      PosesPath unused;
      if (i + 1 >= args.size() ||
          (args[i + 1] != "turntable+ba" && !ParsePosesPath(args[i + 1], &unused))) {
        err << "aggscan reconstruct: --poses needs turntable (calibration and measured angles), "
               "turntable+ba "
               "(refined by bundle adjustment, the default), sfm (full SfM through COLMAP, scaled "
               "by the "
               "background labels) or auto (turntable with a rig calibration, sfm without)\n";
        return 2;
      }
      poses = args[++i];
    } else if (args[i] == "--surface") {
      if (!choice(
              &i, "hull", "hull+photo",
              "hull (visual hull only) or hull+photo (refined by photo-consistency, the default)",
              &surface)) {
        return 2;
      }
    } else if (args[i] == "--from") {
      if (i + 1 >= args.size()) {
        err << "aggscan reconstruct: --from needs a stage: masks, 2d, calibration, poses, "
               "stitch, surface or morphology (or one side's, e.g. \"poses side 2\")\n";
        return 2;
      }
      from = args[++i];
    } else if (args[i] == "--config") {
      if (i + 1 >= args.size()) {
        err << "aggscan reconstruct: --config needs a file\n";
        return 2;
      }
      config_path = args[++i];
    } else if (args[i] == "--state-dir") {
      if (i + 1 >= args.size()) {
        err << "aggscan reconstruct: --state-dir needs a directory\n";
        return 2;
      }
      state_dir = args[++i];
    } else if (!args[i].empty() && args[i][0] == '-') {
      err << "aggscan reconstruct: unknown option '" << args[i] << "'\n";
      return 2;
    } else if (sample_dir.empty()) {
      sample_dir = args[i];
    } else {
      err << "aggscan reconstruct: unexpected argument '" << args[i] << "'\n";
      return 2;
    }
  }
  if (sample_dir.empty()) {
    err << "aggscan reconstruct: give a sample directory (STATE_DIR/samples/ID)\n";
    return 2;
  }
  std::error_code ec;
  if (!std::filesystem::is_directory(sample_dir, ec)) {
    err << "aggscan reconstruct: " << sample_dir << " is not a directory\n";
    return 2;
  }
  if (state_dir.empty()) {
    // A sample inside a state directory: STATE/samples/ID.
    const auto parent = std::filesystem::absolute(sample_dir).lexically_normal().parent_path();
    if (parent.filename() == "samples") state_dir = parent.parent_path().string();
  }
  ReconstructOptions opts;
  opts.state_dir = state_dir;
  opts.photo_refine = surface == "hull+photo";
  opts.from_stage = from;
  if (poses == "turntable") opts.bundle_adjust = false;
  if (!poses.empty() && poses != "turntable+ba") ParsePosesPath(poses, &opts.poses);
  if (!config_path.empty()) {
    // The [mask] section (an ONNX mask network, if configured) and [worker] poses.
    std::vector<ConfigProblem> problems;
    auto cfg = LoadConfigFile(config_path, &problems);
    if (!cfg.ok()) {
      for (const auto& p : problems) err << "aggscan reconstruct: " << p.ToString() << "\n";
      err << "aggscan reconstruct: invalid config: " << cfg.error().ToString() << "\n";
      return 2;
    }
    auto net = LoadMaskNet(cfg->mask);
    if (!net.ok()) {
      err << "aggscan reconstruct: " << net.error().ToString() << "\n";
      return 2;
    }
    opts.worker.mask_net = *net;
    opts.worker.empty_turntable_max_angle_deg = cfg->mask.empty_turntable_max_angle_deg;
    if (poses.empty())
      ParsePosesPath(cfg->worker.poses, &opts.poses);  // validated by LoadConfigFile
  }
  if (Status s = ReconstructSample(sample_dir, opts); !s) {
    err << "aggscan reconstruct: " << s.error().ToString() << "\n";
    return 1;
  }
  auto m = ReadMorphology(sample_dir);
  if (!m) {
    err << "aggscan reconstruct: " << m.error().ToString() << "\n";
    return 1;
  }
  out << m->dump(2) << "\n";
  return 0;
}

}  // namespace aggscan
