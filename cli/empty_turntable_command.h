// `aggscan empty-turntable`: installs the photos of the empty turntable that
// the masks take as their background (store/empty_turntable.h).
//
//   aggscan empty-turntable SAMPLE_DIR [--side N] [--state-dir DIR]
//       side N (1) of a capture with nothing on the disc becomes the rig's
//       current set; samples armed from then on link it in and are masked
//       against the photo shot at each view's angle
//   aggscan empty-turntable --state-dir DIR
//       the current set
#pragma once

#include <ostream>
#include <string>
#include <vector>

namespace aggscan {

int RunEmptyTurntableCommand(const std::vector<std::string>& args, std::ostream& out,
                             std::ostream& err);
void PrintEmptyTurntableUsage(std::ostream& o);

}  // namespace aggscan
