// Triangle meshes: the sim's rock, and later the reconstruction's output.
// Coordinates in millimetres once loaded (the file's unit is converted).
#pragma once

#include <array>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan {

struct Mesh {
  std::vector<std::array<double, 3>> vertices;  // mm
  std::vector<std::array<int, 3>> faces;        // counter-clockwise seen from outside
};

/// Scale factor from a unit name to millimetres: "mm" 1, "cm" 10, "m" 1000.
/// Returns false for unknown units.
bool UnitToMm(const std::string& unit, double* factor);
/// Loads PLY (ASCII or binary), OBJ or STL (ASCII or binary), chosen by
/// extension, converting `unit` to mm. Errors name the file and the defect.
Result<Mesh> LoadMesh(const std::string& path, const std::string& unit);
/// Writes binary little-endian PLY (mm).
Status SaveMeshPly(const Mesh& mesh, const std::string& path);

}  // namespace aggscan
