// Reading and writing the JSON records of the state directory: whole files,
// the fields of a record with an error that names the file and the field, and
// the schema version every record carries.
//
// A record read from disk may have been written by an older release, edited
// by hand, cut short by a full disk or written by a newer release. Each of
// those gets an error that names the file, what is wrong and what to do,
// never a library exception.
#pragma once

#include <nlohmann/json.hpp>
#include <string>
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

}  // namespace aggscan::jsonio
