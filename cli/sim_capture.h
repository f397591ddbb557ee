// `aggscan sim capture`: runs the real capture service on the simulated rig
// with a virtual clock (no waiting: the schedule is followed in simulated
// time) and writes one complete sample directory, exactly as aggscand would,
// plus truth.json and truth/ with the sim's ground truth.
#pragma once

#include <cstdint>
#include <optional>
#include <ostream>
#include <string>

namespace aggscan {

struct SimCaptureOptions {
  std::optional<uint64_t> seed;  // procedural rock from this seed
  std::string mesh;              // or a mesh file ...
  std::string unit = "mm";       // ... in this unit
  std::string out;               // sample directory to create (must not exist)
  std::string profile;           // paper | full-turn (empty: the config's)
  std::string config_path;       // optional TOML config (sim backends are forced)
  int width = 0, height = 0;     // resolution override (0 = config)
  int views_per_side = 0;        // override (profile full-turn/custom)
  std::string calibration;       // calibration.json recorded in the sample as the daemon's
                                 // state_dir/calibration.json would be (empty: none)
  std::string scene;             // rock | charuco (empty: the config's). charuco without a
                                 // --profile: one side of views_per_side views over a full turn;
                                 // without sim.board_image the board is drawn from [calibration]
};

/// Returns a process exit code (0 ok, 2 usage, 78 bad config, 1 other failure).
int RunSimCapture(const SimCaptureOptions& opt, std::ostream& out, std::ostream& err);

}  // namespace aggscan
