// `aggscan morph MESH [--unit mm|cm|m] [--json]`: 3D morphology of a closed
// mesh (volume, surface area, principal dimensions a <= b <= c of the
// minimum-volume oriented bounding box, FER c/a, c/b, b/a, Wadell sphericity).
// A mesh that is not a closed manifold is refused with the defects named.
#pragma once

#include <ostream>
#include <string>

namespace aggscan {

/// Returns 0 on success, 1 when the mesh is refused, 2 for unreadable input.
int RunMorphCommand(const std::string& path, const std::string& unit, bool json, std::ostream& out,
                    std::ostream& err);

}  // namespace aggscan
