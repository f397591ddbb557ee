// What `aggscan morph FILE` does with a mesh file (cli/morph_command.cpp):
// load it (chosen by extension), check its topology and, for a closed
// manifold, compute the 3D morphology. Shared by the PLY, OBJ and STL targets.
#pragma once

#include <cstdlib>

#include "common/mesh.h"
#include "common/mesh_check.h"
#include "common/mesh_props.h"
#include "tests/fuzz/fuzz_util.h"

namespace aggscan::fuzz {

// The minimum-volume box search grows faster than linearly with the hull: a
// mesh this small keeps an input's run in milliseconds, which is all the
// loaders' and checks' branches need.
inline constexpr size_t kMaxPropsVertices = 2000;

inline int FuzzMeshFile(const uint8_t* data, size_t size, const char* ext) {
  const std::string path = ScratchDir() + "/input" + ext;
  WriteFile(path, AsView(data, size));
  Result<Mesh> mesh = LoadMesh(path, "mm");
  if (!mesh) {
    if (mesh.error().message.empty()) std::abort();  // an error must say what is wrong
    return 0;
  }
  for (const auto& f : mesh->faces)
    for (int i : f)
      if (i < 0 || static_cast<size_t>(i) >= mesh->vertices.size())
        std::abort();  // a bad index let through
  const MeshTopology topo = AnalyzeTopology(*mesh);
  (void)topo.Defects();
  if (CheckClosedManifold(*mesh, path) && mesh->vertices.size() <= kMaxPropsVertices) {
    (void)MeshPropsJson(ComputeMeshProps(*mesh)).dump();
  }
  return 0;
}

}  // namespace aggscan::fuzz
