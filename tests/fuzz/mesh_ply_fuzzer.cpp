// libFuzzer target: PLY files through LoadMesh and the morphology checks.
#include "tests/fuzz/mesh_fuzz.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  return aggscan::fuzz::FuzzMeshFile(data, size, ".ply");
}
