#include "common/mesh_check.h"

#include <algorithm>
#include <numeric>
#include <unordered_map>
#include <vector>

namespace aggscan {
namespace {

// Union-find over small index ranges.
struct Dsu {
  std::vector<int> p;
  explicit Dsu(size_t n) : p(n) { std::iota(p.begin(), p.end(), 0); }
  int Find(int x) {
    while (p[x] != x) x = p[x] = p[p[x]];
    return x;
  }
  void Union(int a, int b) { p[Find(a)] = Find(b); }
};

std::string Plural(size_t n, const char* one, const char* many) {
  return std::to_string(n) + " " + (n == 1 ? one : many);
}

}  // namespace

std::string MeshTopology::Defects() const {
  std::string out;
  auto add = [&](size_t n, const char* one, const char* many) {
    if (n == 0) return;
    if (!out.empty()) out += ", ";
    out += Plural(n, one, many);
  };
  if (faces == 0) return "no faces";
  add(boundary_edges, "boundary edge (a hole)", "boundary edges (holes)");
  add(nonmanifold_edges, "non-manifold edge (shared by more than two faces)",
      "non-manifold edges (shared by more than two faces)");
  add(misoriented_edges, "misoriented edge (flipped neighbouring faces)",
      "misoriented edges (flipped neighbouring faces)");
  add(nonmanifold_vertices, "non-manifold vertex (pinched)", "non-manifold vertices (pinched)");
  add(degenerate_faces, "degenerate face (repeated vertex)", "degenerate faces (repeated vertex)");
  return out;
}

MeshTopology AnalyzeTopology(const Mesh& mesh) {
  MeshTopology t;
  t.vertices = mesh.vertices.size();
  t.faces = mesh.faces.size();
  // Directed use of every undirected edge: +1 for a->b with a<b, -1 for b->a.
  struct EdgeUse {
    int count = 0;
    int direction_sum = 0;
    int first_face = -1;
  };
  std::unordered_map<uint64_t, EdgeUse> edges;
  edges.reserve(mesh.faces.size() * 2);
  std::vector<std::vector<std::pair<int, int>>> fans(
      mesh.vertices.size());  // per vertex: (next, prev) of each face
  Dsu faces_dsu(mesh.faces.size());
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    const auto& tri = mesh.faces[f];
    if (tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2]) {
      ++t.degenerate_faces;
      continue;
    }
    for (int k = 0; k < 3; ++k) {
      const int a = tri[k], b = tri[(k + 1) % 3];
      const uint64_t key =
          (static_cast<uint64_t>(std::min(a, b)) << 32) | static_cast<uint32_t>(std::max(a, b));
      EdgeUse& e = edges[key];
      ++e.count;
      e.direction_sum += a < b ? 1 : -1;
      if (e.first_face < 0) {
        e.first_face = static_cast<int>(f);
      } else {
        faces_dsu.Union(static_cast<int>(f), e.first_face);
      }
      fans[static_cast<size_t>(a)].emplace_back(b, tri[(k + 2) % 3]);
    }
  }
  for (const auto& [key, e] : edges) {
    if (e.count == 1) ++t.boundary_edges;
    if (e.count > 2) ++t.nonmanifold_edges;
    // Consistent orientation uses each edge once in each direction; any
    // direction used twice means a flipped neighbour (always so with 3+ faces).
    const int forward = (e.count + e.direction_sum) / 2, backward = (e.count - e.direction_sum) / 2;
    if (forward > 1 || backward > 1) ++t.misoriented_edges;
  }
  // A vertex is manifold when the faces around it form one fan: link each
  // face's two other vertices and count the pieces.
  for (const auto& fan : fans) {
    if (fan.size() < 2) continue;
    std::vector<int> ids;
    ids.reserve(fan.size() * 2);
    for (const auto& [a, b] : fan) {
      ids.push_back(a);
      ids.push_back(b);
    }
    std::sort(ids.begin(), ids.end());
    ids.erase(std::unique(ids.begin(), ids.end()), ids.end());
    auto idx = [&](int v) {
      return static_cast<int>(std::lower_bound(ids.begin(), ids.end(), v) - ids.begin());
    };
    Dsu d(ids.size());
    for (const auto& [a, b] : fan) d.Union(idx(a), idx(b));
    size_t pieces = 0;
    for (size_t i = 0; i < ids.size(); ++i)
      pieces += d.Find(static_cast<int>(i)) == static_cast<int>(i);
    if (pieces > 1) ++t.nonmanifold_vertices;
  }
  std::vector<char> seen(mesh.faces.size(), 0);
  for (size_t f = 0; f < mesh.faces.size(); ++f) {
    const int r = faces_dsu.Find(static_cast<int>(f));
    if (!seen[static_cast<size_t>(r)]) {
      seen[static_cast<size_t>(r)] = 1;
      ++t.components;
    }
  }
  return t;
}

Status CheckClosedManifold(const Mesh& mesh, const std::string& what) {
  const MeshTopology t = AnalyzeTopology(mesh);
  if (t.ClosedManifold()) return OkStatus();
  return MakeError(
      ErrorClass::kInvalidArgument,
      what + " is not a closed manifold surface, so it has no well-defined volume: " + t.Defects() +
          ". Repair the mesh (close holes, split pinched vertices, make face orientation "
          "consistent) "
          "and try again.");
}

}  // namespace aggscan
