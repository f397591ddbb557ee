// Topology of a triangle mesh: is it a closed, manifold, consistently oriented
// surface, i.e. does it bound a volume? Volume, area and sphericity are only
// meaningful for such a mesh, so `aggscan morph` refuses any other, naming
// each defect and how many times it occurs.
#pragma once

#include <cstddef>
#include <string>

#include "common/error.h"
#include "common/mesh.h"

namespace aggscan {

struct MeshTopology {
  size_t vertices = 0;
  size_t faces = 0;
  size_t degenerate_faces = 0;      // a vertex repeated in one triangle
  size_t boundary_edges = 0;        // edges of only one face: holes
  size_t nonmanifold_edges = 0;     // edges shared by more than two faces
  size_t misoriented_edges = 0;     // two faces run through the edge the same way (flipped faces)
  size_t nonmanifold_vertices = 0;  // faces around the vertex form separate fans (pinched)
  size_t components = 0;            // connected pieces (by shared edges)
  bool ClosedManifold() const {
    return faces > 0 && degenerate_faces == 0 && boundary_edges == 0 && nonmanifold_edges == 0 &&
           misoriented_edges == 0 && nonmanifold_vertices == 0;
  }
  /// "223 boundary edges (holes), 1 non-manifold vertex (pinched)"; empty when clean.
  std::string Defects() const;
};

MeshTopology AnalyzeTopology(const Mesh& mesh);

/// OK for a closed manifold mesh; otherwise kInvalidArgument naming `what`
/// (e.g. the file) and every defect, with what to do about it.
Status CheckClosedManifold(const Mesh& mesh, const std::string& what);

}  // namespace aggscan
