// `aggscan calibrate`: the rig calibration from a ChArUco board lying on the
// turntable (pipeline/calib/calibrate.h).
//
//   aggscan calibrate board --out FILE.png|FILE.pgm [--dpi N] [--margin-mm M] [--config FILE]
//       the printable board of the config's [calibration] section (PGM with
//       --margin-mm 0: the image the sim's charuco scene reads)
//   aggscan calibrate SAMPLE_DIR [--side N] [--state-dir DIR | --out FILE]
//                     [--config FILE] [--json]
//       solves from one captured side of a sample shot with the board on the
//       disc and writes calibration.json atomically; an existing file is kept
//       as calibration.json.prev-<utc>. The board is the [calibration] of
//       --config, else of the sample's config.toml.
#pragma once

#include <ostream>
#include <string>
#include <vector>

namespace aggscan {

/// args start after the word "calibrate". Exit codes: 0 ok, 1 calibration
/// failed (the message says why and what to do), 2 usage, 78 bad config.
int RunCalibrateCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err);

}  // namespace aggscan
