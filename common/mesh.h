// Triangle meshes: the sim's rock, and later the reconstruction's output.
// Coordinates in millimetres once loaded (the file's unit is converted).
#pragma once

#include <array>
#include <cstdint>
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
/// Per-vertex sRGB colour (optional in the writers below).
using VertexColors = std::vector<std::array<uint8_t, 3>>;

/// Writes binary little-endian PLY (mm), with per-vertex red/green/blue when
/// `colors` is given (one per vertex). Atomic (temporary file + rename).
Status SaveMeshPly(const Mesh& mesh, const std::string& path, const VertexColors* colors = nullptr);
/// Wavefront OBJ (mm), "v x y z r g b" (colours 0..1) when colours are given.
Status SaveMeshObj(const Mesh& mesh, const std::string& path, const VertexColors* colors = nullptr);
/// Binary STL (mm; STL has no unit field: the header says mm).
Status SaveMeshStl(const Mesh& mesh, const std::string& path);

}  // namespace aggscan
