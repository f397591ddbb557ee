// library.csv in the state directory: one row per reconstructed rock, for a
// spreadsheet. Numbers in plain decimals (no exponent), text fields quoted as
// RFC 4180 says, the sample's description and mass beside its figures.
//
// Two processes write it: the worker when a rock is reconstructed, the
// daemon when a sample's description is edited. Each rewrites the whole file
// atomically under an advisory lock (library.csv.lock), so neither loses the
// other's row.
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan::library_csv {

std::string Header();
/// The fields of one line of a CSV file as RFC 4180 reads it (quoted fields,
/// doubled quotes, a trailing CR or LF dropped): the reader of what Row
/// writes, and of the CSV files people give the rig (reference volumes).
std::vector<std::string> SplitLine(const std::string& line);
/// The row of one rock from its morphology.json (as written) and its
/// sample.json "meta" (mass from the specific gravity there). A figure the
/// record lacks is an empty field.
std::string Row(const nlohmann::json& morphology, const nlohmann::json& meta);
/// Adds or replaces the sample's row in state_dir/library.csv. A file with
/// other columns (an older release) is kept beside as library-<UTC>.csv and a
/// new one begun. An empty state_dir does nothing.
Status Upsert(const std::string& state_dir, const std::string& sample_id, const std::string& row);

}  // namespace aggscan::library_csv
