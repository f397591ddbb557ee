// The software's version, as results and reports record it.
#pragma once

namespace aggscan {

/// "0.1.0" from the project() of the top CMakeLists.txt, then "+g<commit>"
/// (and "-dirty" for a tree with uncommitted changes) where the build was
/// made from a git checkout; "0.1.0" alone otherwise. Regenerated at every
/// build, so a result never carries the commit of an earlier build.
const char* SoftwareVersion();

}  // namespace aggscan
