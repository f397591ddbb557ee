#include "cli/reconstruct_command.h"

#include <filesystem>

#include "config/config.h"
#include "pipeline/worker/reconstruct.h"
#include "pipeline/worker/worker_config.h"

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
  bool sfm_whole_frame = false;
  for (size_t i = 0; i < args.size(); ++i) {
    if (args[i] == "--poses") {
      PosesChoice unused;
      if (i + 1 >= args.size() || !ParsePosesChoice(args[i + 1], &unused)) {
        err << "aggscan reconstruct: --poses needs turntable+ba (calibration and measured "
               "angles refined by bundle adjustment), turntable (calibration and measured angles "
               "as read), sfm (full SfM through COLMAP, scaled by the background labels) or auto "
               "(turntable+ba with a rig calibration, sfm without); without it, [worker] poses of "
               "the config\n";
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
    } else if (args[i] == "--sfm-whole-frame") {
      sfm_whole_frame = true;
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
  // The config: the one given, else the one the sample was armed with (what
  // the worker used), else the defaults. Its [mask] and [worker] sections
  // become the options exactly as in aggscan-worker (pipeline/worker/worker_config.h).
  Config cfg;
  if (!config_path.empty()) {
    std::vector<ConfigProblem> problems;
    auto loaded = LoadConfigFile(config_path, &problems);
    if (!loaded.ok()) {
      for (const auto& p : problems) err << "aggscan reconstruct: " << p.ToString() << "\n";
      err << "aggscan reconstruct: invalid config: " << loaded.error().ToString() << "\n";
      return 2;
    }
    cfg = std::move(loaded.value());
  } else {
    std::string source;
    auto armed = ConfigForSample(sample_dir, &source);
    if (!armed.ok()) {
      err << "aggscan reconstruct: " << armed.error().ToString() << "\n";
      return 2;
    }
    cfg = std::move(armed.value());
    err << "aggscan reconstruct: config: " << source << "\n";
  }
  if (!poses.empty()) cfg.worker.poses = poses;  // checked above
  auto opts = ReconstructOptionsFromConfig(cfg);
  if (!opts.ok()) {
    err << "aggscan reconstruct: " << opts.error().ToString() << "\n";
    return 2;
  }
  opts->state_dir = state_dir;
  opts->photo_refine = surface == "hull+photo";
  opts->from_stage = from;
  if (sfm_whole_frame) opts->sfm.crop_to_masks = false;
  if (Status s = ReconstructSample(sample_dir, *opts); !s) {
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
