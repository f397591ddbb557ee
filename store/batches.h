// Batches: named sets of samples that a QA engineer reports on together,
// kept as state_dir/batches/<name>.json. A batch names its samples by lot,
// by the date range they were created in, or by a list of ids; membership is
// worked out when asked, so a lot's batch includes rocks captured later.
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan {

struct BatchDef {
  std::string name;
  std::string lot;                   // samples whose description's lot is this
  std::string from_date;             // samples created on or after this UTC date (YYYY-MM-DD)
  std::string to_date;               // ... and on or before this one (the whole day)
  std::vector<std::string> samples;  // and these, whatever their lot and date
  std::string notes;
  std::string created_utc;
  std::string updated_utc;

  nlohmann::json ToJson() const;
};

/// Checks a batch as a person gives it ({"lot", "from", "to", "samples",
/// "notes"}): a name like a sample id, at least one of lot, date range or
/// samples, dates as YYYY-MM-DD with from <= to, listed ids valid.
Result<BatchDef> BatchFromRequest(const std::string& name, const nlohmann::json& doc);

/// Which samples belong: those listed, and those matching every criterion
/// given (lot, from, to). `samples` is SampleStore::List()'s answer
/// ({"id", "created_utc", "meta"}...); ids in its order (creation time),
/// then listed ids the store does not have (named, so a report can say so).
struct BatchMembers {
  std::vector<std::string> ids;
  std::vector<std::string> missing;  // listed but not in the store
};
BatchMembers ResolveBatch(const BatchDef& def, const nlohmann::json& samples);

class BatchStore {
 public:
  explicit BatchStore(std::string state_dir) : dir_(std::move(state_dir) + "/batches") {}
  /// Creates or replaces the batch (created_utc kept on replace).
  Result<BatchDef> Put(BatchDef def);
  /// kNotFound naming the batches there are.
  Result<BatchDef> Get(const std::string& name) const;
  /// Every batch, by name; a file that does not read is skipped and named
  /// in `problems`.
  std::vector<BatchDef> List(std::vector<std::string>* problems = nullptr) const;
  Status Remove(const std::string& name);

 private:
  std::string Path(const std::string& name) const { return dir_ + "/" + name + ".json"; }
  std::string dir_;
};

}  // namespace aggscan
