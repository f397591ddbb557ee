// `aggscan reconstruct SAMPLE_DIR [--state-dir DIR]`: runs every unfinished
// worker stage on a sample directory now, in this process (masks, poses,
// stitching, surface, morphology), and prints results/morphology.json.
#pragma once

#include <ostream>
#include <string>
#include <vector>

namespace aggscan {

/// Returns 0 on success, 1 when a stage fails (the error names it), 2 for usage errors.
int RunReconstructCommand(const std::vector<std::string>& args, std::ostream& out,
                          std::ostream& err);

}  // namespace aggscan
