// The QA reports served by the API: `aggscan report` run beside the daemon
// (the same program as on the command line) into a private temporary file,
// one at a time, below the capture in CPU priority.
#pragma once

#include <mutex>
#include <string>

#include "common/error.h"

namespace aggscan {

struct ReportRequest {
  std::string kind;  // "rock" (name: a sample id) or "batch" (name: a batch)
  std::string name;
  std::string format;  // "pdf" or "html"
  std::string spec;    // a batch's gradation specification: a shipped name, or empty
};

class ReportMaker {
 public:
  /// `state_dir`: the daemon's. The `aggscan` program: $AGGSCAN_CLI, else
  /// beside this executable, else the build tree's cli/aggscan.
  explicit ReportMaker(std::string state_dir) : state_dir_(std::move(state_dir)) {}

  /// The report's file (the caller reads and removes it). kInvalidArgument
  /// for a bad request (a spec that is not a shipped name), kConflict while
  /// another report is being made, kNotFound for an unknown sample or batch,
  /// kInvalidState when the report cannot be made from what is stored (the
  /// message says why and what to do), kTimeout after `timeout_s`.
  Result<std::string> Make(const ReportRequest& r, double timeout_s = 120.0);

  /// Where the aggscan program is looked for (for messages and tests).
  static std::string CliPath();

 private:
  std::string state_dir_;
  std::mutex busy_;
};

}  // namespace aggscan
