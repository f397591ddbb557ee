// The worker's jobs as declared lists of stages over one sample directory.
//
// A stage names its outputs (under results/ or work/) and a fingerprint of everything
// that decides them: its options and its inputs, each input stage by that
// stage's own fingerprint (a chain), the captured files by their bytes. The
// ledger results/stages.json records, per stage, the fingerprint it was
// started with and whether it finished. Before a job runs, the runner walks
// its stages in order:
//   - finished with the same fingerprint and its outputs present: kept (the
//     stage then only loads what it wrote);
//   - started with the same fingerprint but not finished (a crash or kill),
//     or not in the ledger at all but with some of its outputs there
//     (results made before the ledger existed, masks put in place by hand):
//     resumed in place, what is there kept (the stages resume within
//     themselves: per view, per COLMAP step); every later stage runs afresh;
//   - otherwise (other options or inputs, an output missing, or `from` names
//     it): its outputs are removed and it runs again, and so does every stage
//     after it.
// One StageContext carries the sample id, the stage's name, cancellation
// (ErrorClass::kCancelled), logging and the progress the daemon shows.
#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <nlohmann/json.hpp>
#include <string>
#include <string_view>
#include <vector>

#include "common/error.h"
#include "common/log.h"
#include "store/layout.h"

namespace aggscan {

/// Incremental 64-bit FNV-1a over typed, length-prefixed fields: a change
/// detector for stage inputs, not a security hash.
class Fingerprint {
 public:
  Fingerprint& Add(std::string_view field, std::string_view bytes);
  Fingerprint& Add(std::string_view field, const nlohmann::json& value);
  /// The file's bytes, or a marker that it is absent (so appearing and
  /// disappearing both change the fingerprint). kIo when it exists but cannot
  /// be read.
  Status AddFile(std::string_view field, const std::string& path);
  std::string Hex() const;

 private:
  void Mix(std::string_view bytes);
  uint64_t h_ = 1469598103934665603ull;
};

/// What a running stage is given.
class StageContext {
 public:
  StageContext(std::string sample_id, std::string stage, const std::atomic<bool>* cancel,
               bool reused)
      : sample_id_(std::move(sample_id)),
        stage_(std::move(stage)),
        cancel_(cancel),
        reused_(reused) {}

  const std::string& sample_id() const { return sample_id_; }
  const std::string& stage() const { return stage_; }
  /// The stage's outputs were kept from an earlier run: it only loads them.
  bool reused() const { return reused_; }
  /// kCancelled naming the stage and `where` once cancellation was asked for;
  /// OK otherwise.
  Status CheckCancelled(const std::string& where = "") const;
  /// A log line with the sample id, prefixed with the stage's name.
  void Log(LogLevel level, const std::string& text) const;
  /// `done` of `total` units of this stage (what the daemon's status shows).
  void Progress(int done, int total) const;

 private:
  std::string sample_id_;
  std::string stage_;
  const std::atomic<bool>* cancel_;
  bool reused_;
};

struct StageDecl {
  std::string name;    // unique in the job: "poses side 1"
  std::string family;  // what `from` may name: "poses" (the name when empty)
  std::string fingerprint;
  /// Paths relative to the sample directory (files or directories: results/
  /// and work/ only, never captured data) removed before the stage runs
  /// afresh; all must exist for a finished stage to be kept.
  std::vector<std::string> outputs;
  /// Also removed before it runs afresh, but not required afterwards (work
  /// files the stage resumes from: a COLMAP workspace).
  std::vector<std::string> scratch;
  std::function<Status(StageContext&)> run;
};

struct StageRunOptions {
  /// Run this stage (a name or a family) and every stage after it afresh,
  /// whatever the ledger says. Empty: none. Unknown: kInvalidArgument.
  std::string from;
  const std::atomic<bool>* cancel = nullptr;
};

struct StageRunReport {
  std::vector<std::string> ran;      // started afresh
  std::vector<std::string> resumed;  // continued from an earlier, unfinished run
  std::vector<std::string> kept;     // finished earlier with the same fingerprint
  /// Seconds of every stage: this run's, or the recorded ones of kept stages.
  nlohmann::json seconds = nlohmann::json::object();
};

using layout::kStageLedger;

/// Runs the job's stages in order over `sample_dir` (see the top of this
/// file). Each stage runs inside RunStage (exceptions become its error); the
/// first error stops the job, leaving its stage marked started so that the
/// next run resumes it. Cancellation between stages is kCancelled.
Result<StageRunReport> RunStages(const std::string& sample_dir,
                                 const std::vector<StageDecl>& stages, const StageRunOptions& opts);

/// The ledger of a sample (empty object when there is none).
Result<nlohmann::json> ReadStageLedger(const std::string& sample_dir);

}  // namespace aggscan
