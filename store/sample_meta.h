// A sample's description, kept in sample.json's "meta": who captured it,
// the source or lot of the stone, notes, and the material (its name and its
// specific gravity with the basis it was measured on), from which the mass is
// computed. It is given when the sample is armed and may be edited at any
// time afterwards; an edit changes sample.json's "meta" only (and appends to
// its "meta_history"), never a photo or a result.
#pragma once

#include <nlohmann/json.hpp>
#include <optional>
#include <string>

#include "common/error.h"

namespace aggscan::sample_meta {

inline constexpr size_t kMaxLineBytes = 80;     // operator, lot, material name
inline constexpr size_t kMaxNotesBytes = 2000;  // notes may have lines
/// A specific gravity outside this is a typing or unit error (riprap stone
/// is about 2.3-3.2; a density in kg/m3 is 1000 times too large).
inline constexpr double kMinSpecificGravity = 1.0;
inline constexpr double kMaxSpecificGravity = 6.0;
inline constexpr const char* kBasisBulkSsd = "bulk-ssd";
inline constexpr const char* kBasisOvenDry = "oven-dry";

/// Checks a description given by a person (an API body, the CLI) and returns
/// it normalised: {"operator", "lot", "notes": text, "material": {"name":
/// text, "specific_gravity": number, "basis": "bulk-ssd"|"oven-dry"}}, each
/// optional. Text is trimmed; control characters are refused (notes keep
/// line breaks and tabs). A null value (with `allow_removal`) removes that
/// field when applied. Keys named in `ignored` (e.g. "id" of an arm request)
/// pass unchecked and are left out; any other unknown key is refused,
/// naming the known ones. A specific gravity needs its basis, given with it
/// or already kept (`current_material`, the record's).
Result<nlohmann::json> CheckPatch(const nlohmann::json& doc, bool allow_removal,
                                  const std::vector<std::string>& ignored = {},
                                  const nlohmann::json& current_material = nullptr);

/// Merges a checked patch into `meta` (a record's "meta" object); returns
/// what it changed as {"field": value before (null when absent)}; material
/// fields are named "material.name" etc.
nlohmann::json ApplyPatch(nlohmann::json& meta, const nlohmann::json& patch);

/// The record's material as a patch would give it, from a [material] config
/// section's values: null when the config names no material and no specific
/// gravity.
nlohmann::json MaterialFromConfig(const std::string& name, double specific_gravity,
                                  const std::string& basis);

/// A rock's mass from its volume and the record's "meta" (grams, as
/// volume in cm3 x specific gravity x 1 g/cm3 of water), or why there is none.
struct Mass {
  std::optional<double> grams;
  double specific_gravity = 0;
  std::string basis;
  std::string why_none;  // set when grams is empty: what is missing and how to give it
};
Mass MassOf(double volume_mm3, const nlohmann::json& meta);

}  // namespace aggscan::sample_meta
