#include "pipeline/core/stage_runner.h"

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <set>

#include "common/clock.h"
#include "common/fsutil.h"
#include "pipeline/core/stage.h"
#include "store/layout.h"

namespace aggscan {
namespace {

using json = nlohmann::json;
constexpr const char* kCat = "worker";
constexpr const char* kLedgerFormat = "aggscan-stages-1";

std::string ResultsDir(const std::string& sample_dir) {
  return sample_dir + "/" + layout::kResultsDir;
}

Status WriteLedger(const std::string& sample_dir, const json& ledger) {
  if (Status s = MakeDirsDurable(ResultsDir(sample_dir)); !s) return s;
  return WriteFileAtomic(ResultsDir(sample_dir) + "/" + kStageLedger,
                         std::string_view(ledger.dump(2) + "\n"));
}

// Removes one output (file or directory) of a stage about to run afresh.
Status RemoveOutput(const std::string& sample_dir, const std::string& rel) {
  const std::string path = sample_dir + "/" + rel;
  std::error_code ec;
  std::filesystem::remove_all(path, ec);
  if (ec) {
    return MakeError(ErrorClass::kIo, "cannot remove the earlier result " + path + " (" +
                                          ec.message() +
                                          "); check the state directory's "
                                          "permissions and remove it by hand");
  }
  return OkStatus();
}

bool OutputsPresent(const std::string& sample_dir, const StageDecl& d) {
  for (const std::string& rel : d.outputs) {
    if (!PathExists(sample_dir + "/" + rel)) return false;
  }
  return true;
}

bool AnyOutputPresent(const std::string& sample_dir, const StageDecl& d) {
  for (const auto* list : {&d.outputs, &d.scratch}) {
    for (const std::string& rel : *list) {
      if (PathExists(sample_dir + "/" + rel)) return true;
    }
  }
  return false;
}

}  // namespace

// --- Fingerprint ------------------------------------------------------------

void Fingerprint::Mix(std::string_view bytes) {
  for (unsigned char c : bytes) {
    h_ ^= c;
    h_ *= 1099511628211ull;
  }
}

Fingerprint& Fingerprint::Add(std::string_view field, std::string_view bytes) {
  // Length-prefixed, so that ("ab", "c") and ("a", "bc") differ.
  const std::string head = std::string(field) + ":" + std::to_string(bytes.size()) + ":";
  Mix(head);
  Mix(bytes);
  return *this;
}

Fingerprint& Fingerprint::Add(std::string_view field, const json& value) {
  return Add(field, std::string_view(value.dump()));
}

Status Fingerprint::AddFile(std::string_view field, const std::string& path) {
  if (!PathExists(path)) {
    Add(field, std::string_view("<absent>"));
    return OkStatus();
  }
  auto bytes = ReadFile(path);
  if (!bytes) return bytes.error();
  Add(field, std::string_view(*bytes));
  return OkStatus();
}

std::string Fingerprint::Hex() const {
  char buf[17];
  std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(h_));
  return buf;
}

// --- StageContext -----------------------------------------------------------

Status StageContext::CheckCancelled(const std::string& where) const {
  if (cancel_ && cancel_->load()) {
    return MakeError(ErrorClass::kCancelled, "stage " + stage_ + " of " + sample_id_ +
                                                 " cancelled" + (where.empty() ? "" : " " + where) +
                                                 "; it resumes there when run again");
  }
  return OkStatus();
}

void StageContext::Log(LogLevel level, const std::string& text) const {
  LogLine(level, kCat, sample_id_, stage_ + ": " + text);
}

void StageContext::Progress(int done, int total) const { ReportStageProgress(done, total); }

// --- the runner -------------------------------------------------------------

Result<json> ReadStageLedger(const std::string& sample_dir) {
  const std::string path = ResultsDir(sample_dir) + "/" + kStageLedger;
  if (!PathExists(path)) return json{{"format", kLedgerFormat}, {"stages", json::object()}};
  auto text = ReadFile(path);
  if (!text) return text.error();
  json j = json::parse(*text, nullptr, false);
  if (!j.is_object() || j.value("format", "") != kLedgerFormat || !j.contains("stages") ||
      !j["stages"].is_object()) {
    // Damaged or from another release: every stage is run again, which is
    // always correct, only slower.
    LogLine(LogLevel::kWarning, kCat, layout::SampleIdOfDir(sample_dir),
            path + " is not a stage ledger this worker reads; every stage runs again");
    return json{{"format", kLedgerFormat}, {"stages", json::object()}};
  }
  return j;
}

Result<StageRunReport> RunStages(const std::string& sample_dir,
                                 const std::vector<StageDecl>& stages,
                                 const StageRunOptions& opts) {
  const std::string sample_id = layout::SampleIdOfDir(sample_dir);
  if (!opts.from.empty()) {
    bool known = false;
    std::string names;
    std::set<std::string> seen;
    for (const StageDecl& d : stages) {
      const std::string family = d.family.empty() ? d.name : d.family;
      if (opts.from == d.name || opts.from == family) known = true;
      if (seen.insert(family).second) names += (names.empty() ? "" : ", ") + family;
    }
    if (!known) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "no stage '" + opts.from + "' in this job; its stages are: " + names);
    }
  }
  auto ledger = ReadStageLedger(sample_dir);
  if (!ledger) return ledger.error();
  json& recorded = (*ledger)["stages"];

  StageRunReport report;
  bool afresh = false;   // an earlier stage runs afresh: so does every later one
  bool resumed = false;  // an earlier stage resumes: no later one is kept
  bool asked = false;    // the stage named by opts.from has been reached
  const int n = static_cast<int>(stages.size());
  for (int i = 0; i < n; ++i) {
    const StageDecl& d = stages[i];
    const std::string family = d.family.empty() ? d.name : d.family;
    ReportStageProgress(i, n);
    if (opts.cancel && opts.cancel->load()) {
      return MakeError(ErrorClass::kCancelled, "job of " + sample_id + " cancelled before stage " +
                                                   d.name + "; it resumes there when run again");
    }
    const bool earlier_afresh = afresh;
    if (!opts.from.empty() && (opts.from == d.name || opts.from == family)) asked = afresh = true;
    const json entry = recorded.value(d.name, json::object());
    const bool same = entry.value("fingerprint", "") == d.fingerprint;
    enum { kKeep, kResume, kAfresh } mode = kAfresh;
    const bool unrecorded = entry.empty() && AnyOutputPresent(sample_dir, d);
    if (!afresh && !resumed && same && entry.value("finished", false) &&
        OutputsPresent(sample_dir, d)) {
      mode = kKeep;
    } else if (!afresh && ((!resumed && same && !entry.value("finished", false)) || unrecorded)) {
      // Started with these options and stopped; or never recorded (results
      // placed by hand or by a test, or made before the ledger existed): the
      // stage continues from what is there. After a stage that resumed, only
      // unrecorded results are continued from: a recorded one may be older
      // than what the resumed stage is about to finish.
      mode = kResume;
    }
    if (mode == kAfresh) afresh = true;
    if (mode == kResume) resumed = true;
    if (mode == kAfresh) {
      for (const auto* list : {&d.outputs, &d.scratch}) {
        for (const std::string& rel : *list) {
          if (Status s = RemoveOutput(sample_dir, rel); !s) return s.error();
        }
      }
      if (!entry.empty()) {
        const char* why = asked            ? nullptr
                          : !same          ? "other options or inputs"
                          : earlier_afresh ? "an earlier stage ran again"
                                           : "an output is missing";
        LogLine(LogLevel::kInfo, kCat, sample_id,
                d.name + ": runs again (" + (why ? why : "asked from " + opts.from) + ")");
      }
    }
    if (mode != kKeep) {
      recorded[d.name] = {
          {"fingerprint", d.fingerprint}, {"finished", false}, {"started_utc", NowUtcString()}};
      if (Status s = WriteLedger(sample_dir, *ledger); !s) return s.error();
    }
    StageContext ctx(sample_id, d.name, opts.cancel, mode == kKeep);
    const auto t0 = std::chrono::steady_clock::now();
    Status s = RunStage(d.name, [&] { return d.run(ctx); });
    const double seconds =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (!s) return s.error();
    if (mode == kKeep) {
      report.kept.push_back(d.name);
      report.seconds[d.name] = entry.value("seconds", 0.0);
      continue;
    }
    (mode == kResume ? report.resumed : report.ran).push_back(d.name);
    report.seconds[d.name] = seconds;
    json& e = recorded[d.name];
    e["finished"] = true;
    e["finished_utc"] = NowUtcString();
    e["seconds"] = seconds;
    if (Status w = WriteLedger(sample_dir, *ledger); !w) return w.error();
  }
  ReportStageProgress(n, n);
  return report;
}

}  // namespace aggscan
