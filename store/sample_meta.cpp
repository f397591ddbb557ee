#include "store/sample_meta.h"

#include <algorithm>
#include <cmath>
#include <cstdio>

namespace aggscan::sample_meta {

using nlohmann::json;

namespace {

const char* const kKnown =
    "operator, lot, notes, material {name, specific_gravity, basis}, reference {volume_mm3, "
    "method}";

Error Bad(const std::string& message) { return MakeError(ErrorClass::kInvalidArgument, message); }

// Text a person typed: trimmed; control characters refused, except line
// breaks and tabs in multi-line fields.
Result<std::string> CheckText(const json& v, const std::string& key, size_t max_bytes,
                              bool multiline) {
  if (!v.is_string()) return Bad("\"" + key + "\" must be a string");
  std::string text = v.get<std::string>();
  if (text.size() > max_bytes) {
    return Bad("\"" + key + "\" is " + std::to_string(text.size()) + " bytes long: at most " +
               std::to_string(max_bytes));
  }
  for (const unsigned char ch : text) {
    if ((ch < 0x20 && !(multiline && (ch == '\n' || ch == '\t'))) || ch == 0x7f) {
      return Bad("\"" + key + "\" contains a control character" +
                 (multiline ? " (only line breaks and tabs are kept)" : "") + ": remove it");
    }
  }
  const size_t b = text.find_first_not_of(" \t\n");
  const size_t e = text.find_last_not_of(" \t\n");
  return b == std::string::npos ? std::string() : text.substr(b, e - b + 1);
}

std::string Number(double v) {
  char b[32];
  std::snprintf(b, sizeof b, "%g", v);
  return b;
}

Result<json> CheckMaterial(const json& m, bool allow_removal, const json& current) {
  if (!m.is_object()) {
    return Bad(
        "\"material\" must be an object {\"name\", \"specific_gravity\", \"basis\"}, each "
        "optional");
  }
  json out = json::object();
  for (const auto& [key, v] : m.items()) {
    const std::string where = "material." + key;
    if (v.is_null()) {
      if (!allow_removal) return Bad("\"" + where + "\" is null: leave it out instead");
      out[key] = nullptr;
      continue;
    }
    if (key == "name") {
      Result<std::string> t = CheckText(v, where, kMaxLineBytes, false);
      if (!t) return t.error();
      out[key] = *t;
    } else if (key == "specific_gravity") {
      if (!v.is_number()) return Bad("\"" + where + "\" must be a number, e.g. 2.65");
      const double sg = v.get<double>();
      if (!std::isfinite(sg) || sg < kMinSpecificGravity || sg > kMaxSpecificGravity) {
        return Bad("\"" + where + "\" is " + Number(sg) + ": a stone's specific gravity is " +
                   Number(kMinSpecificGravity) + " to " + Number(kMaxSpecificGravity) +
                   " (riprap about 2.3-3.2; a density in kg/m3 is 1000 times this)");
      }
      out[key] = sg;
    } else if (key == "basis") {
      if (!v.is_string() || (v != kBasisBulkSsd && v != kBasisOvenDry)) {
        return Bad("\"" + where + "\" must be \"" + kBasisBulkSsd +
                   "\" (saturated surface-dry) or \"" + kBasisOvenDry + "\"");
      }
      out[key] = v;
    } else {
      return Bad("unknown field \"" + where + "\": a material has name, specific_gravity, basis");
    }
  }
  // A specific gravity means nothing without what it was measured on.
  const bool sg_given = out.contains("specific_gravity") && out["specific_gravity"].is_number();
  const bool basis_given = out.contains("basis") && out["basis"].is_string();
  const bool basis_kept = current.is_object() && current.contains("basis") &&
                          current["basis"].is_string() && !out.contains("basis");
  if (sg_given && !basis_given && !basis_kept) {
    return Bad("\"material.specific_gravity\" needs its basis: give \"material.basis\" as \"" +
               std::string(kBasisBulkSsd) + "\" or \"" + kBasisOvenDry + "\"");
  }
  return out;
}

// A volume measured another way (water displacement, ASTM D6473 style),
// against which the report compares the rig's (the study's Figure 6).
Result<json> CheckReference(const json& r) {
  if (!r.is_object()) return Bad("\"reference\" must be an object {\"volume_mm3\", \"method\"}");
  json out = json::object();
  for (const auto& [key, v] : r.items()) {
    if (key == "volume_mm3") {
      if (!v.is_number() || !std::isfinite(v.get<double>()) || v.get<double>() <= 0)
        return Bad("\"reference.volume_mm3\" must be a positive number of mm3");
      out[key] = v.get<double>();
    } else if (key == "method" || key == "source") {
      Result<std::string> t = CheckText(v, "reference." + key, kMaxLineBytes, false);
      if (!t) return t.error();
      out[key] = *t;
    } else {
      return Bad("unknown field \"reference." + key +
                 "\": a reference has volume_mm3, method, "
                 "source");
    }
  }
  if (!out.contains("volume_mm3")) return Bad("\"reference\" needs its volume_mm3");
  return out;
}

}  // namespace

Result<json> CheckPatch(const json& doc, bool allow_removal,
                        const std::vector<std::string>& ignored, const json& current_material) {
  if (!doc.is_object()) return Bad(std::string("expected a JSON object with ") + kKnown);
  json out = json::object();
  for (const auto& [key, v] : doc.items()) {
    if (std::find(ignored.begin(), ignored.end(), key) != ignored.end()) continue;
    if (key != "operator" && key != "lot" && key != "notes" && key != "material" &&
        key != "reference")
      return Bad("unknown field \"" + key + "\": a sample's description has " + kKnown);
    if (v.is_null()) {
      if (!allow_removal) continue;  // an arm request's "not given"
      out[key] = nullptr;
      continue;
    }
    if (key == "material") {
      Result<json> m = CheckMaterial(v, allow_removal, current_material);
      if (!m) return m.error();
      out[key] = std::move(*m);
      continue;
    }
    if (key == "reference") {
      Result<json> r = CheckReference(v);
      if (!r) return r.error();
      out[key] = std::move(*r);
      continue;
    }
    Result<std::string> t = key == "notes" ? CheckText(v, key, kMaxNotesBytes, true)
                                           : CheckText(v, key, kMaxLineBytes, false);
    if (!t) return t.error();
    // An empty text is no description: at arming it is left out, in an edit
    // it removes the field.
    if (t->empty()) {
      if (allow_removal) out[key] = nullptr;
      continue;
    }
    out[key] = *t;
  }
  return out;
}

json ApplyPatch(json& meta, const json& patch) {
  if (!meta.is_object()) meta = json::object();
  json changed = json::object();
  auto set = [&changed](json& obj, const std::string& key, const json& v, const std::string& name) {
    const json before = obj.contains(key) ? obj[key] : json();
    if (before == v || (v.is_null() && !obj.contains(key))) return;
    changed[name] = before;
    if (v.is_null())
      obj.erase(key);
    else
      obj[key] = v;
  };
  for (const auto& [key, v] : patch.items()) {
    if (key != "material" || v.is_null()) {
      set(meta, key, v, key);
      continue;
    }
    if (!meta.contains("material") || !meta["material"].is_object())
      meta["material"] = json::object();
    const size_t before = changed.size();
    for (const auto& [mk, mv] : v.items()) set(meta["material"], mk, mv, "material." + mk);
    // A default from the config that a person changed is theirs now.
    if (changed.size() != before && meta["material"].contains("source") && !v.contains("source"))
      set(meta["material"], "source", nullptr, "material.source");
    if (meta["material"].empty()) meta.erase("material");
  }
  return changed;
}

json MaterialFromConfig(const std::string& name, double specific_gravity,
                        const std::string& basis) {
  if (name.empty() && specific_gravity <= 0) return nullptr;
  json m = {{"basis", basis}, {"source", "config"}};
  if (!name.empty()) m["name"] = name;
  if (specific_gravity > 0) m["specific_gravity"] = specific_gravity;
  return m;
}

Mass MassOf(double volume_mm3, const json& meta) {
  Mass out;
  const json* m = nullptr;
  if (meta.is_object() && meta.contains("material") && meta["material"].is_object())
    m = &meta["material"];
  if (m == nullptr || !m->contains("specific_gravity") || !(*m)["specific_gravity"].is_number()) {
    out.why_none =
        "no specific gravity: give the sample's material (`aggscan meta ID --sg 2.65 --sg-basis "
        "bulk-ssd`) or a default in [material] of the config";
    return out;
  }
  out.specific_gravity = (*m)["specific_gravity"].get<double>();
  out.basis = m->contains("basis") && (*m)["basis"].is_string() ? (*m)["basis"].get<std::string>()
                                                                : std::string();
  if (!(out.specific_gravity >= kMinSpecificGravity &&
        out.specific_gravity <= kMaxSpecificGravity)) {
    out.why_none = "the sample's specific gravity " + Number(out.specific_gravity) +
                   " is not a stone's (" + Number(kMinSpecificGravity) + " to " +
                   Number(kMaxSpecificGravity) + "): correct it with `aggscan meta ID --sg ...`";
    return out;
  }
  if (!std::isfinite(volume_mm3) || volume_mm3 <= 0) {
    out.why_none = "no volume measured";
    return out;
  }
  // 1 cm3 = 1000 mm3 of water weighs 1 g.
  out.grams = volume_mm3 / 1000.0 * out.specific_gravity;
  return out;
}

}  // namespace aggscan::sample_meta
