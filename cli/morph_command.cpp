#include "cli/morph_command.h"

#include <cmath>
#include <cstdio>
#include <exception>
#include <nlohmann/json.hpp>
#include <utility>

#include "common/mesh.h"
#include "common/mesh_check.h"
#include "common/mesh_props.h"

namespace aggscan {

namespace {
int Morph(const std::string& path, const std::string& unit, bool json, std::ostream& out,
          std::ostream& err);
}  // namespace

int RunMorphCommand(const std::string& path, const std::string& unit, bool json, std::ostream& out,
                    std::ostream& err) {
  // Any library exception (an allocation the loader's checks did not
  // foresee, say) is this file's error, never the end of the process.
  try {
    return Morph(path, unit, json, out, err);
  } catch (const std::exception& e) {
    err << "aggscan morph: " << path << ": cannot be measured (" << e.what() << ")\n";
    return 2;
  }
}

namespace {

int Morph(const std::string& path, const std::string& unit, bool json, std::ostream& out,
          std::ostream& err) {
  double factor = 0;
  if (!UnitToMm(unit, &factor)) {
    err << "aggscan morph: unknown unit '" << unit << "': use mm, cm or m\n";
    return 2;
  }
  Result<Mesh> mesh = LoadMesh(path, unit);
  if (!mesh) {
    err << "aggscan morph: " << mesh.error().ToString() << "\n";
    return 2;
  }
  const MeshTopology topo = AnalyzeTopology(*mesh);
  if (Status s = CheckClosedManifold(*mesh, path); !s) {
    if (json) {
      nlohmann::json e = {
          {"error", {{"class", ErrorClassName(s.error().cls)}, {"message", s.error().message}}},
          {"watertight", false},
          {"boundary_edges", topo.boundary_edges},
          {"nonmanifold_edges", topo.nonmanifold_edges},
          {"misoriented_edges", topo.misoriented_edges},
          {"nonmanifold_vertices", topo.nonmanifold_vertices},
          {"degenerate_faces", topo.degenerate_faces}};
      out << e.dump(2) << "\n";
    }
    err << "aggscan morph: " << s.error().message << "\n";
    return 1;
  }
  const MeshProps p = ComputeMeshProps(*mesh);
  // The loader bounds the coordinates, so this is a last guard: a figure that
  // is not a finite number is never printed as a result.
  for (auto [name, v] :
       {std::pair{"volume", p.volume_mm3}, std::pair{"surface area", p.surface_area_mm2},
        std::pair{"a", p.a_mm}, std::pair{"b", p.b_mm}, std::pair{"c", p.c_mm},
        std::pair{"sphericity", p.sphericity}, std::pair{"FER", p.fer_3d}}) {
    if (!std::isfinite(v)) {
      err << "aggscan morph: " << path << ": the " << name
          << " is not a finite number; the mesh's coordinates are degenerate or out of range\n";
      return 1;
    }
  }
  nlohmann::json j = {{"file", path},
                      {"unit", unit},
                      {"vertices", mesh->vertices.size()},
                      {"faces", mesh->faces.size()},
                      {"components", topo.components},
                      {"watertight", true}};
  j.update(MeshPropsJson(p));
  if (json) {
    out << j.dump(2) << "\n";
    return 0;
  }
  char buf[512];
  std::snprintf(buf, sizeof buf,
                "%s (%zu vertices, %zu faces, closed manifold)\n"
                "volume         %.3f cm^3 (%.1f mm^3)\n"
                "surface area   %.3f cm^2 (%.1f mm^2)\n"
                "a <= b <= c    %.3f / %.3f / %.3f mm (minimum-volume box)\n"
                "FER 3D c/a     %.3f   c/b %.3f   b/a %.3f\n"
                "sphericity     %.4f (Wadell)\n",
                path.c_str(), mesh->vertices.size(), mesh->faces.size(), p.volume_mm3 / 1000.0,
                p.volume_mm3, p.surface_area_mm2 / 100.0, p.surface_area_mm2, p.a_mm, p.b_mm,
                p.c_mm, p.fer_3d, p.c_over_b, p.b_over_a, p.sphericity);
  out << buf;
  for (size_t i = 0; i < p.near_boxes.size(); ++i) {
    const MeshProps::NearBox& b = p.near_boxes[i];
    std::snprintf(
        buf, sizeof buf, "%s%.3f / %.3f / %.3f mm (box %.2f %% larger)",
        i == 0 ? "note: a, b, c are ill-conditioned; boxes of nearly the same volume measure "
               : "; ",
        b.a_mm, b.b_mm, b.c_mm, 100 * (b.volume_ratio - 1));
    out << buf;
    if (i + 1 == p.near_boxes.size()) out << "\n";
  }
  if (topo.components > 1) out << "note: " << topo.components << " separate pieces\n";
  return 0;
}

}  // namespace

}  // namespace aggscan
