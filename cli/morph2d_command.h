// `aggscan morph2d IMAGE_OR_MASK`: 2D morphology of one picture. A binary mask
// (only 0 and 255, one channel or identical channels) is measured as it is;
// any other image is segmented first (mask.h).
#pragma once

#include <ostream>
#include <string>

#include "pipeline/core/image_io.h"

namespace aggscan {

/// Prints {l_max_px, l_min_px, fer_2d, area_px, perimeter_px, circularity} as
/// JSON (json = true) or as text to `out`. Returns 0 on success, 2 when the
/// file cannot be read as an image, 1 when no object is found; messages go to `err`.
/// Images outside `limits` (pixel count, smallest side, shape) and damaged
/// JPEGs are refused (2) before or instead of being measured.
int RunMorph2dCommand(const std::string& path, bool json, std::ostream& out, std::ostream& err,
                      const ImageLimits& limits = {});

}  // namespace aggscan
