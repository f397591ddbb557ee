// Reading and writing the JSON records of the state directory: whole files,
// the fields of a record with an error that names the file and the field, and
// the schema version every record carries.
//
// A record read from disk may have been written by an older release, edited
// by hand, cut short by a full disk or written by a newer release. Each of
// those gets an error that names the file, what is wrong and what to do,
// never a library exception.
#pragma once

#include <cstdint>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <type_traits>
#include <vector>

#include "common/error.h"

namespace aggscan::jsonio {

/// The whole file parsed. kNotFound when it does not exist, kCorrupt (naming
/// `what`, the file and `redo`: what to do) when it is not a JSON object.
Result<nlohmann::json> ReadFile(const std::string& path, const std::string& what,
                                const std::string& redo = {});

/// Writes `j` (indented, newline-terminated) atomically: the file appears
/// whole under its name or not at all (common/fsutil.h).
Status WriteFile(const std::string& path, const nlohmann::json& j, bool no_replace = false);

/// Where a record came from, for errors: "<what> <path>".
struct Source {
  std::string what;  // "stitch record"
  std::string path;  // the file, or "" for a record not read from a file
  std::string redo;  // what to do about a bad record ("run ... again from the stitch")

  Error Bad(const std::string& problem) const;
};

/// The record's schema version. A record without the key was written before
/// records carried one and counts as version 1; a version newer than
/// `current` is refused (written by a newer release: update this one).
Result<int> SchemaVersion(const nlohmann::json& j, const char* key, int current, const Source& src);

/// Required fields: an error naming the field when absent or of another type.
Result<double> Number(const nlohmann::json& j, const char* key, const Source& src);
Result<int> Int(const nlohmann::json& j, const char* key, const Source& src);
Result<std::string> String(const nlohmann::json& j, const char* key, const Source& src);
Result<bool> Bool(const nlohmann::json& j, const char* key, const Source& src);

/// Optional fields: `fallback` when absent or null, an error when present
/// with another type (a hand edit that would otherwise be silently ignored).
Result<double> NumberOr(const nlohmann::json& j, const char* key, double fallback,
                        const Source& src);
Result<int> IntOr(const nlohmann::json& j, const char* key, int fallback, const Source& src);
Result<std::string> StringOr(const nlohmann::json& j, const char* key, std::string fallback,
                             const Source& src);
Result<bool> BoolOr(const nlohmann::json& j, const char* key, bool fallback, const Source& src);
/// An object or array member; an empty object/array when absent.
Result<nlohmann::json> ObjectOr(const nlohmann::json& j, const char* key, const Source& src);
Result<nlohmann::json> ArrayOr(const nlohmann::json& j, const char* key, const Source& src);

/// A JSON number, or null for a figure that is not finite (JSON has no NaN;
/// nlohmann writes null for it, and a reader must see null, not 0).
nlohmann::json Finite(double v);

Result<int64_t> Int64(const nlohmann::json& j, const char* key, const Source& src);
Result<uint64_t> UInt64(const nlohmann::json& j, const char* key, const Source& src);

/// Reads the fields of one JSON object into a struct: keeps the first error
/// (later reads do nothing), and the keys it did not read (Extra(): a
/// record's unknown keys, written back unchanged).
///
///   jsonio::Fields f(j, src);
///   f.Schema(kCurrent);
///   f.Req("view", &v.view);           // required
///   f.Opt("mask", &v.mask);           // optional: unchanged when absent or null
///   f.Opt("angle_deg", &v.angle);     // std::optional<T>: nullopt when absent
///   if (!f.ok()) return f.error();
///   v.extra = f.Extra();
class Fields {
 public:
  Fields(const nlohmann::json& j, const Source& src);

  bool ok() const { return !err_; }
  const Error& error() const { return *err_; }
  void Fail(Error e) {
    if (!err_) err_ = std::move(e);
  }
  const Source& source() const { return src_; }

  void Req(const char* key, int* out) { Use(key, Int(j_, key, src_), out); }
  void Req(const char* key, int64_t* out) { Use(key, Int64(j_, key, src_), out); }
  void Req(const char* key, uint64_t* out) { Use(key, UInt64(j_, key, src_), out); }
  void Req(const char* key, double* out) { Use(key, Number(j_, key, src_), out); }
  void Req(const char* key, bool* out) { Use(key, Bool(j_, key, src_), out); }
  void Req(const char* key, std::string* out) { Use(key, String(j_, key, src_), out); }

  template <typename T>
  void Opt(const char* key, T* out) {
    seen_.push_back(key);
    if (!ok() || Absent(key)) return;
    Req(key, out);
  }
  template <typename T>
  void Opt(const char* key, std::optional<T>* out) {
    seen_.push_back(key);
    if (!ok() || Absent(key)) return;
    T v{};
    Req(key, &v);
    if (ok()) *out = std::move(v);
  }
  /// Any JSON, kept as it is; `out` unchanged when absent.
  void Raw(const char* key, nlohmann::json* out);
  /// A list of strings (empty when absent).
  void Strings(const char* key, std::vector<std::string>* out);
  /// A list of objects, each read by `read(item_json, item_source)`, whose
  /// errors name the item ("views[3]").
  template <typename T, typename ReadOne>
  void List(const char* key, std::vector<T>* out, ReadOne read) {
    seen_.push_back(key);
    if (!ok()) return;
    auto a = ArrayOr(j_, key, src_);
    if (!a) return Fail(a.error());
    for (size_t i = 0; i < a->size(); ++i) {
      Source item = src_;
      item.what = src_.what + " (" + key + "[" + std::to_string(i) + "])";
      auto v = read((*a)[i], item);
      if (!v) return Fail(v.error());
      out->push_back(std::move(*v));
    }
  }
  /// A value read by the caller (a type of its own), stored when ok.
  template <typename T>
  void Use(const char* key, Result<T> r, T* out) {
    seen_.push_back(key);
    if (!ok()) return;
    if (!r) return Fail(r.error());
    *out = std::move(*r);
  }
  /// The "schema" version (SchemaVersion): an error when newer than `current`.
  void Schema(int current);
  /// The keys not read.
  nlohmann::json Extra() const;

 private:
  bool Absent(const char* key) const;

  const nlohmann::json& j_;
  const Source& src_;
  std::optional<Error> err_;
  std::vector<std::string> seen_;
};

/// j[key] = *v when v holds a value (a non-finite double as null).
template <typename T>
void Put(nlohmann::json& j, const char* key, const std::optional<T>& v) {
  if (!v) return;
  if constexpr (std::is_same_v<T, double>) {
    j[key] = Finite(*v);
  } else {
    j[key] = *v;
  }
}

}  // namespace aggscan::jsonio
