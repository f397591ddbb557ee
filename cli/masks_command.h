// `aggscan masks`: the rig's own salient-object mask network, end to end.
//   dataset --out DIR SAMPLE_DIR...   training pairs from reconstructed samples
//                                     (pipeline/masks/mask_dataset.h: the mesh projected into every
//                                     view)
//   train --dataset DIR --out M.onnx  trains scripts/masks/train_masks.py (python3-torch, CPU),
//                                     exports ONNX, writes the [mask] config lines to use it
//   eval [--model M.onnx] [--grabcut DIR] SAMPLE_DIR...
//                                     IoU of the classical and the trained masks side by side
//                                     against truth masks (simulated samples) and trimaps
#pragma once

#include <ostream>
#include <string>
#include <vector>

namespace aggscan {

void PrintMasksUsage(std::ostream& o);

/// args after "masks". 0 on success, 1 when the work fails (the error says
/// what to fix), 2 for usage errors.
int RunMasksCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err);

}  // namespace aggscan
