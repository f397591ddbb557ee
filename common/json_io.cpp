#include "common/json_io.h"

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "common/fsutil.h"

namespace aggscan::jsonio {

using nlohmann::json;

Result<json> ReadFile(const std::string& path, const std::string& what, const std::string& redo) {
  Result<std::string> text = aggscan::ReadFile(path);
  if (!text) return text.error();
  json j = json::parse(*text, nullptr, false);
  if (j.is_discarded() || !j.is_object()) {
    return MakeError(ErrorClass::kCorrupt, what + " " + path + " is not a JSON object" +
                                               (redo.empty() ? "" : "; ") + redo);
  }
  return j;
}

Status WriteFile(const std::string& path, const json& j, bool no_replace) {
  // dump() throws on strings that are not UTF-8 (a file name from a
  // foreign camera); replaced characters keep the record writable.
  return WriteFileAtomic(path, j.dump(2, ' ', false, json::error_handler_t::replace) + "\n",
                         no_replace);
}

Error Source::Bad(const std::string& problem) const {
  std::string m = what;
  if (!path.empty()) m += " " + path;
  m += ": " + problem;
  if (!redo.empty()) m += "; " + redo;
  return MakeError(ErrorClass::kCorrupt, m);
}

Result<int> SchemaVersion(const json& j, const char* key, int current, const Source& src) {
  if (!j.is_object()) return src.Bad("not a JSON object");
  if (!j.contains(key)) return 1;
  const json& v = j[key];
  if (!v.is_number_integer() || v.get<int>() < 1)
    return src.Bad(std::string("\"") + key + "\" is not a positive whole number");
  const int n = v.get<int>();
  if (n > current) {
    return MakeError(ErrorClass::kCorrupt,
                     src.what + " " + src.path + " has schema version " + std::to_string(n) +
                         ", newer than this release reads (" + std::to_string(current) +
                         "): it was written by a newer aggscan; update this one");
  }
  return n;
}

namespace {

std::string Field(const char* key) { return std::string("\"") + key + "\""; }

bool Absent(const json& j, const char* key) { return !j.contains(key) || j[key].is_null(); }

}  // namespace

Result<double> Number(const json& j, const char* key, const Source& src) {
  if (!j.is_object() || !j.contains(key)) return src.Bad(Field(key) + " is missing");
  if (!j[key].is_number()) return src.Bad(Field(key) + " is not a number");
  return j[key].get<double>();
}

Result<int> Int(const json& j, const char* key, const Source& src) {
  if (!j.is_object() || !j.contains(key)) return src.Bad(Field(key) + " is missing");
  const json& v = j[key];
  if (!v.is_number_integer()) return src.Bad(Field(key) + " is not a whole number");
  const auto n = v.get<int64_t>();
  if (n < INT32_MIN || n > INT32_MAX) return src.Bad(Field(key) + " is out of range");
  return static_cast<int>(n);
}

Result<std::string> String(const json& j, const char* key, const Source& src) {
  if (!j.is_object() || !j.contains(key)) return src.Bad(Field(key) + " is missing");
  if (!j[key].is_string()) return src.Bad(Field(key) + " is not a string");
  return j[key].get<std::string>();
}

Result<bool> Bool(const json& j, const char* key, const Source& src) {
  if (!j.is_object() || !j.contains(key)) return src.Bad(Field(key) + " is missing");
  if (!j[key].is_boolean()) return src.Bad(Field(key) + " is not true or false");
  return j[key].get<bool>();
}

Result<double> NumberOr(const json& j, const char* key, double fallback, const Source& src) {
  if (!j.is_object() || Absent(j, key)) return fallback;
  return Number(j, key, src);
}

Result<int> IntOr(const json& j, const char* key, int fallback, const Source& src) {
  if (!j.is_object() || Absent(j, key)) return fallback;
  return Int(j, key, src);
}

Result<std::string> StringOr(const json& j, const char* key, std::string fallback,
                             const Source& src) {
  if (!j.is_object() || Absent(j, key)) return fallback;
  return String(j, key, src);
}

Result<bool> BoolOr(const json& j, const char* key, bool fallback, const Source& src) {
  if (!j.is_object() || Absent(j, key)) return fallback;
  return Bool(j, key, src);
}

Result<json> ObjectOr(const json& j, const char* key, const Source& src) {
  if (!j.is_object() || Absent(j, key)) return json::object();
  if (!j[key].is_object()) return src.Bad(Field(key) + " is not an object");
  return j[key];
}

Result<json> ArrayOr(const json& j, const char* key, const Source& src) {
  if (!j.is_object() || Absent(j, key)) return json::array();
  if (!j[key].is_array()) return src.Bad(Field(key) + " is not a list");
  return j[key];
}

json Finite(double v) { return std::isfinite(v) ? json(v) : json(); }

Result<int64_t> Int64(const json& j, const char* key, const Source& src) {
  if (!j.is_object() || !j.contains(key)) return src.Bad(Field(key) + " is missing");
  const json& v = j[key];
  if (!v.is_number_integer()) return src.Bad(Field(key) + " is not a whole number");
  if (v.is_number_unsigned() && v.get<uint64_t>() > static_cast<uint64_t>(INT64_MAX))
    return src.Bad(Field(key) + " is out of range");
  return v.get<int64_t>();
}

Result<uint64_t> UInt64(const json& j, const char* key, const Source& src) {
  if (!j.is_object() || !j.contains(key)) return src.Bad(Field(key) + " is missing");
  const json& v = j[key];
  if (!v.is_number_integer()) return src.Bad(Field(key) + " is not a whole number");
  if (!v.is_number_unsigned() && v.get<int64_t>() < 0) return src.Bad(Field(key) + " is negative");
  return v.get<uint64_t>();
}

Fields::Fields(const json& j, const Source& src) : j_(j), src_(src) {
  if (!j.is_object()) Fail(src.Bad("not a JSON object"));
}

bool Fields::Absent(const char* key) const {
  return !j_.is_object() || !j_.contains(key) || j_[key].is_null();
}

void Fields::Raw(const char* key, json* out) {
  seen_.push_back(key);
  if (j_.is_object() && j_.contains(key)) *out = j_[key];
}

void Fields::Strings(const char* key, std::vector<std::string>* out) {
  seen_.push_back(key);
  if (!ok()) return;
  auto a = ArrayOr(j_, key, src_);
  if (!a) return Fail(a.error());
  for (const json& e : *a) {
    if (!e.is_string()) return Fail(src_.Bad(Field(key) + " holds something not a string"));
    out->push_back(e.get<std::string>());
  }
}

void Fields::Schema(int current) {
  seen_.push_back("schema");
  if (!ok()) return;
  auto v = SchemaVersion(j_, "schema", current, src_);
  if (!v) Fail(v.error());
}

json Fields::Extra() const {
  json e = json::object();
  if (!j_.is_object()) return e;
  for (const auto& [k, v] : j_.items()) {
    if (std::find(seen_.begin(), seen_.end(), k) == seen_.end()) e[k] = v;
  }
  return e;
}

}  // namespace aggscan::jsonio
