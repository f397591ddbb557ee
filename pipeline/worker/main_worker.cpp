// aggscan-worker: takes side and sample jobs from the queue in the state
// directory and runs the reconstruction stages on them: side jobs compute the
// masks and 2D figures of one side; a sample job, when the sample recorded a
// rig calibration at arm time (samples/<id>/calibration.json), runs every
// stage to the 3D model and morphology (pipeline/worker/reconstruct.h), else only
// the 2D figures, saying how to calibrate. Niced below the capture daemon.
//
// Each job runs in a child process forked for it, so that nothing a library
// does to the process (an abort, SIGSEGV, std::terminate from a thread, the
// OOM killer) can take the queue down with it: the parent sees how the child
// ended. A named failure (an error value, or a library exception caught at a
// stage boundary, pipeline/core/stage.h) and a crash (with the stage it was in)
// count an attempt; [worker] max_attempts of them mark the job failed and the
// queue moves on. SIGTERM/SIGINT: forwarded to the child, whose side stops
// between views (it resumes there next time); the job goes back to the queue
// without counting. A job found running at start-up (the whole worker was
// killed or lost power) is requeued uncounted, [worker] max_interruptions
// times in a row at most.
//
// The worker tells aggscand what it does through the queue database (store/
// queue.h WorkerReport): idle, or busy with a job, its innermost stage and
// that stage's progress, every [worker] heartbeat_interval and whenever the
// stage changes. The child keeps its stage in the page it shares with the
// parent; the parent, which is never blocked by a library, writes the report.
//
//   aggscan-worker --state-dir DIR [--config FILE] [--once] [--poll-ms N] [--log-level L]
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <new>
#include <string>
#include <thread>
#include <vector>

#include "common/fsutil.h"
#include "common/log.h"
#include "common/version.h"
#include "config/config.h"
#include "pipeline/calib/calibrate.h"
#include "pipeline/core/image_io.h"
#include "pipeline/core/stage.h"
#include "pipeline/worker/reconstruct.h"
#include "pipeline/worker/side_job.h"
#include "pipeline/worker/worker_config.h"
#include "store/layout.h"
#include "store/queue.h"

namespace {

using namespace aggscan;

constexpr const char* kCat = "worker";

// Exit codes of a job's child process; any other end is a crash.
constexpr int kChildDone = 0;
constexpr int kChildFailed = 1;   // a named failure, described in the report
constexpr int kChildStopped = 3;  // stopped between views on request

// What a child leaves for the parent, in memory shared across fork(): the
// stage it is in and that stage's progress (kept current while it runs, so
// it survives a crash) and its failure. Written only by the child. The
// parent reads the stage while the child runs under `seq` (odd while the
// child writes: a sequence lock), the failure after the child ended.
struct ChildReport {
  std::atomic<uint32_t> seq;
  std::atomic<int> done;
  std::atomic<int> total;
  char stage[256];
  char error_class[32];
  char message[16384];
};
static_assert(std::atomic<uint32_t>::is_always_lock_free && std::atomic<int>::is_always_lock_free,
              "the child and the parent share these across processes");

ChildReport* g_report = nullptr;

void CopyText(char* dst, size_t size, const std::string& s) {
  const size_t n = std::min(size - 1, s.size());
  std::memcpy(dst, s.data(), n);
  dst[n] = '\0';
}

// Test hook for the supervision tests: AGGSCAN_WORKER_TEST_ABORT =
// "SAMPLE_ID/STAGE" makes the child of that sample's job abort when it enters
// a stage whose name holds STAGE, as a library's failed assertion would.
char g_abort_stage[256];

extern "C" void ChildStageObserver(const char* stage, int done, int total) {
  const uint32_t seq = g_report->seq.load(std::memory_order_relaxed);
  g_report->seq.store(seq + 1, std::memory_order_relaxed);
  std::atomic_thread_fence(std::memory_order_release);
  const size_t n = std::min(std::strlen(stage), sizeof g_report->stage - 1);
  std::memcpy(g_report->stage, stage, n);
  g_report->stage[n] = '\0';
  g_report->done.store(done, std::memory_order_relaxed);
  g_report->total.store(total, std::memory_order_relaxed);
  g_report->seq.store(seq + 2, std::memory_order_release);
  if (g_abort_stage[0] != '\0' && std::strstr(stage, g_abort_stage) != nullptr) std::abort();
}

std::atomic<bool> g_stop{false};

extern "C" void OnSignal(int) { g_stop.store(true); }

void Usage(FILE* f) {
  std::fprintf(
      f,
      "usage: aggscan-worker --state-dir DIR [--config FILE] [--once] [--poll-ms N] [--log-level "
      "L]\n"
      "       aggscan-worker --sample SAMPLE_DIR [--config FILE] [--log-level L]\n"
      "       aggscan-worker --version\n"
      "  --sample DIR      process one sample directory now (every captured side, then\n"
      "                    the sample stage), without the queue; exit 1 on failure\n"
      "  --state-dir DIR   aggscan state directory (samples/, queue.db)\n"
      "  --config FILE     TOML config (worker.nice, worker.poll_interval, worker.poses); defaults "
      "otherwise\n"
      "  --once            exit when the queue is empty (exit 1 if a job failed for good)\n"
      "  --poll-ms N       idle queue polling period in ms (overrides the config)\n"
      "  --log-level L     error|warning|notice|info|debug\n"
      "  --version         print the software version and exit\n");
}

struct Args {
  std::string state_dir;
  std::string sample_dir;
  std::string config;
  bool once = false;
  long poll_ms = -1;
  std::string log_level;
};

bool ParseArgs(int argc, char** argv, Args* a) {
  // Answered before the other options are judged: neither needs a state
  // directory or a config, whatever else is on the line.
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    if (k == "--version") {
      std::printf("aggscan-worker %s\n", aggscan::SoftwareVersion());
      std::exit(0);
    }
    if (k == "-h" || k == "--help") {
      Usage(stdout);
      std::exit(0);
    }
  }
  for (int i = 1; i < argc; ++i) {
    const std::string k = argv[i];
    auto need = [&](std::string* out) {
      if (i + 1 >= argc) {
        std::fprintf(stderr, "aggscan-worker: %s needs a value\n", k.c_str());
        return false;
      }
      *out = argv[++i];
      return true;
    };
    std::string v;
    if (k == "--state-dir") {
      if (!need(&a->state_dir)) return false;
    } else if (k == "--sample") {
      if (!need(&a->sample_dir)) return false;
    } else if (k == "--config") {
      if (!need(&a->config)) return false;
    } else if (k == "--once") {
      a->once = true;
    } else if (k == "--poll-ms") {
      if (!need(&v)) return false;
      char* end = nullptr;
      a->poll_ms = std::strtol(v.c_str(), &end, 10);
      if (end == v.c_str() || *end || a->poll_ms < 1) {
        std::fprintf(stderr, "aggscan-worker: --poll-ms needs a positive integer, got '%s'\n",
                     v.c_str());
        return false;
      }
    } else if (k == "--log-level") {
      if (!need(&a->log_level)) return false;
    } else if (k == "-h" || k == "--help") {
      Usage(stdout);
      std::exit(0);
    } else {
      std::fprintf(stderr, "aggscan-worker: unknown argument '%s'\n", k.c_str());
      return false;
    }
  }
  if (a->state_dir.empty() == a->sample_dir.empty()) {
    std::fprintf(stderr, "aggscan-worker: give either --state-dir or --sample\n");
    return false;
  }
  return true;
}

// Sleeps up to `ms`, waking early on a stop request.
// The running child's stage and progress, read while it may be writing them;
// false when it was mid-write on every try (the next tick reads again).
bool ReadChildStage(std::string* stage, int* done, int* total) {
  char copy[sizeof g_report->stage];
  for (int attempt = 0; attempt < 8; ++attempt) {
    const uint32_t before = g_report->seq.load(std::memory_order_acquire);
    if (before & 1u) continue;
    std::memcpy(copy, g_report->stage, sizeof copy);
    const int d = g_report->done.load(std::memory_order_relaxed);
    const int t = g_report->total.load(std::memory_order_relaxed);
    std::atomic_thread_fence(std::memory_order_acquire);
    if (g_report->seq.load(std::memory_order_relaxed) != before) continue;
    *stage = std::string(copy, strnlen(copy, sizeof copy));
    *done = d;
    *total = t;
    return true;
  }
  return false;
}

// Keeps the worker's report in the queue current: on every change of state
// or stage (at most every kMinGap) and every heartbeat interval.
class WorkerReporter {
 public:
  WorkerReporter(JobQueue* queue, int64_t interval_ns) : queue_(queue), interval_ns_(interval_ns) {
    r_.pid = ::getpid();
    r_.started_boot_ns = BootTimeNs();
  }

  void Idle() {
    Clear("idle");
    Write();
  }
  void Stopped() {
    Clear("stopped");
    Write();
  }
  void Busy(const Job& job) {
    Clear("busy");
    r_.job_id = job.id;
    r_.sample_id = job.sample_id;
    r_.side = job.side;
    r_.job_started_boot_ns = r_.stage_since_boot_ns = BootTimeNs();
    Write();
  }
  // The running job's stage, as the child last wrote it.
  void Stage(const std::string& stage, int done, int total) {
    if (stage != r_.stage) r_.stage_since_boot_ns = BootTimeNs();
    if (stage != r_.stage || done != r_.done || total != r_.total) dirty_ = true;
    r_.stage = stage;
    r_.done = done;
    r_.total = total;
    Tick();
  }
  void Tick() {
    const int64_t now = BootTimeNs();
    if ((dirty_ && now - last_write_ns_ >= kMinGapNs) || now - last_write_ns_ >= interval_ns_)
      Write();
  }

 private:
  static constexpr int64_t kMinGapNs = 500'000'000;

  void Clear(const char* state) {
    r_.state = state;
    r_.job_id = 0;
    r_.sample_id.clear();
    r_.side = 0;
    r_.stage.clear();
    r_.done = r_.total = 0;
    r_.job_started_boot_ns = 0;
    r_.stage_since_boot_ns = BootTimeNs();
  }
  void Write() {
    last_write_ns_ = BootTimeNs();
    dirty_ = false;
    Status st = queue_->ReportWorker(r_);
    // Said once per run of failures: a locked or full disk must not flood the log.
    if (!st.ok() && !failing_)
      AGG_LOGW(kCat,
               "cannot report to aggscand through the queue (it will call the worker silent): %s",
               st.error().ToString().c_str());
    if (st.ok() && failing_) AGG_LOGI(kCat, "reporting to aggscand through the queue again");
    failing_ = !st.ok();
  }

  JobQueue* queue_;
  int64_t interval_ns_;
  WorkerReport r_;
  int64_t last_write_ns_ = 0;
  bool dirty_ = false;
  bool failing_ = false;
};

void IdleWait(long ms, WorkerReporter* reporter) {
  for (long waited = 0; waited < ms && !g_stop.load(); waited += 20) {
    if (reporter) reporter->Tick();
    std::this_thread::sleep_for(std::chrono::milliseconds(std::min<long>(20, ms - waited)));
  }
}

// The sample stage: the 3D reconstruction when the sample carries its rig
// calibration or [worker] poses asks for SfM (auto, sfm), the 2D figures
// alone otherwise.
Status RunSampleStage(const std::string& dir, const std::string& state_dir, ReconstructOptions ro) {
  if (ro.poses == PosesPath::kTurntable && !PathExists(dir + "/" + layout::kCalibrationCopy)) {
    AGG_LOGW(
        kCat,
        "%s: no rig calibration recorded in the sample: 2D figures only; run `aggscan calibrate` "
        "(the daemon records it in every later sample), or give this sample a calibration.json and "
        "run `aggscan reconstruct %s`",
        dir.c_str(), dir.c_str());
    return TwoDFigures(dir, ro.worker);
  }
  ro.state_dir = state_dir;
  ro.cancel = ro.worker.cancel;
  return ReconstructSample(dir, ro);
}

Status RunJob(const std::string& state_dir, const Job& job, const ReconstructOptions& ro) {
  if (!layout::IsValidSampleId(job.sample_id))
    return MakeError(ErrorClass::kCorrupt,
                     "job " + std::to_string(job.id) + " names an invalid sample id");
  if (job.kind == kJobCalibration) {
    // The board: solved into the rig calibration, never masked as a rock.
    const std::string dir = layout::CalibrationCaptureDir(state_dir, job.sample_id);
    return RunStage("calibrate",
                    [&] { return RunCalibrationCapture(dir, std::max(1, job.side), state_dir); });
  }
  const std::string dir = layout::SampleDir(state_dir, job.sample_id);
  return job.side > 0 ? RunSideJob(dir, job.side, ro.worker) : RunSampleStage(dir, state_dir, ro);
}

// How a child process ended.
struct ChildEnd {
  enum Kind { kDone, kFailed, kStopped, kCrashed } kind = kCrashed;
  std::string reason;  // kFailed: the error; kCrashed: signal or exit code, and the stage
};

std::string SignalText(int sig) {
  const char* abbrev = ::sigabbrev_np(sig);
  return (abbrev ? "SIG" + std::string(abbrev) : "signal " + std::to_string(sig)) + " (" +
         ::strsignal(sig) + ")";
}

// Runs fn() -> exit code in a forked child and waits for it, passing the
// child's stage to `reporter` as it goes (when given); a stop request to this
// process is forwarded to the child once.
template <typename F>
Result<ChildEnd> RunInChild(F&& fn, WorkerReporter* reporter = nullptr) {
  g_report->seq.store(0);
  g_report->done.store(0);
  g_report->total.store(0);
  std::memset(g_report->stage, 0, sizeof g_report->stage);
  std::memset(g_report->error_class, 0, sizeof g_report->error_class);
  std::memset(g_report->message, 0, sizeof g_report->message);
  std::fflush(nullptr);  // buffered output must not be written twice
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid < 0) return ErrnoError("cannot fork the job's process", errno);
  if (pid == 0) {
    // The child must not outlive a killed parent: a new worker would run the
    // same job beside it.
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (::getppid() != parent) ::_exit(kChildStopped);
    SetStageObserver(ChildStageObserver);
    const int code = fn();
    std::fflush(nullptr);
    // No exit handlers: the parent's queue connection and the libraries'
    // static state belong to the parent.
    ::_exit(code);
  }
  bool forwarded = false;
  int status = 0;
  for (;;) {
    const pid_t r = ::waitpid(pid, &status, WNOHANG);
    if (r == pid) break;
    if (r < 0 && errno != EINTR) return ErrnoError("cannot wait for the job's process", errno);
    if (g_stop.load() && !forwarded) {
      ::kill(pid, SIGTERM);
      forwarded = true;
    }
    if (reporter) {
      std::string stage;
      int done = 0, total = 0;
      if (ReadChildStage(&stage, &done, &total)) reporter->Stage(stage, done, total);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  const std::string stage(g_report->stage, strnlen(g_report->stage, sizeof g_report->stage));
  const std::string in_stage = stage.empty() ? "" : " in stage \"" + stage + "\"";
  ChildEnd end;
  if (WIFEXITED(status) && WEXITSTATUS(status) == kChildDone) {
    end.kind = ChildEnd::kDone;
  } else if ((WIFEXITED(status) && WEXITSTATUS(status) == kChildStopped) ||
             (WIFSIGNALED(status) && forwarded &&
              (WTERMSIG(status) == SIGTERM || WTERMSIG(status) == SIGKILL))) {
    // Stopped: by our own exit code, or by a signal that stopped us too
    // (systemd stops the whole unit).
    end.kind = ChildEnd::kStopped;
  } else if (WIFEXITED(status) && WEXITSTATUS(status) == kChildFailed &&
             g_report->message[0] != '\0') {
    end.kind = ChildEnd::kFailed;
    end.reason =
        std::string(g_report->message, strnlen(g_report->message, sizeof g_report->message));
  } else if (WIFSIGNALED(status)) {
    const int sig = WTERMSIG(status);
    end.reason =
        (sig == SIGKILL ? "killed by " : "crashed with ") + SignalText(sig) + in_stage +
        (sig == SIGKILL
             ? ": out of memory? check the kernel log for the OOM killer (journalctl -k)"
             : ": a library failed on this sample's data (the worker log has its message); "
               "check that stage's files, fix or re-capture them");
  } else {
    end.reason = "the job's process ended with exit code " + std::to_string(WEXITSTATUS(status)) +
                 in_stage + " without a failure record; see the worker log";
  }
  return end;
}

// The child's side of a job: exit code for RunInChild.
int ChildRunJob(const std::string& state_dir, const Job& job, const Config& cfg) {
  if (const char* hook = std::getenv("AGGSCAN_WORKER_TEST_ABORT")) {
    const std::string h = hook;
    const size_t slash = h.find('/');
    if (slash != std::string::npos && h.substr(0, slash) == job.sample_id) {
      CopyText(g_abort_stage, sizeof g_abort_stage, h.substr(slash + 1));
    }
  }
  Status st = RunStage("job", [&]() -> Status {
    // Loaded here, not in the parent: its check pass starts OpenCV's thread
    // pool, which a process that forks must never have.
    auto ro = ReconstructOptionsFromConfig(cfg);
    if (!ro.ok()) return ro.error();
    ro->worker.cancel = &g_stop;
    return RunJob(state_dir, job, *ro);
  });
  if (st.ok()) return kChildDone;
  if (g_stop.load() && st.error().cls == ErrorClass::kCancelled) return kChildStopped;
  CopyText(g_report->error_class, sizeof g_report->error_class, ErrorClassName(st.error().cls));
  // One line: the reason is shown in status listings.
  std::string reason = st.error().ToString();
  std::replace(reason.begin(), reason.end(), '\n', ' ');
  while (!reason.empty() && reason.back() == ' ') reason.pop_back();
  CopyText(g_report->message, sizeof g_report->message, reason);
  return kChildFailed;
}

}  // namespace

int main(int argc, char** argv) {
  aggscan::KeepFreedImageMemory();
  Args args;
  if (!ParseArgs(argc, argv, &args)) {
    Usage(stderr);
    return 2;
  }
  Config cfg;
  if (!args.config.empty()) {
    std::vector<ConfigProblem> problems;
    auto loaded = LoadConfigFile(args.config, &problems);
    if (!loaded.ok()) {
      for (const auto& p : problems)
        std::fprintf(stderr, "aggscan-worker: %s\n", p.ToString().c_str());
      std::fprintf(stderr, "aggscan-worker: invalid config: %s\n",
                   loaded.error().ToString().c_str());
      return 2;
    }
    cfg = std::move(loaded.value());
  }
  const std::string level = !args.log_level.empty() ? args.log_level : cfg.daemon.log_level;
  LogLevel lvl;
  if (!ParseLogLevel(level, &lvl)) {
    std::fprintf(stderr, "aggscan-worker: unknown log level '%s'\n", level.c_str());
    return 2;
  }
  SetLogLevel(lvl);
  const long poll_ms =
      args.poll_ms > 0 ? args.poll_ms : static_cast<long>(cfg.worker.poll_interval / kNsPerMs);

  // Below the capture daemon. Lowering niceness needs privileges: only warn.
  errno = 0;
  const int current = getpriority(PRIO_PROCESS, 0);
  if (errno == 0 && current != cfg.worker.nice &&
      setpriority(PRIO_PROCESS, 0, cfg.worker.nice) != 0)
    AGG_LOGW(kCat, "cannot set nice %d (staying at %d): %s", cfg.worker.nice, current,
             std::strerror(errno));

  if (!args.sample_dir.empty()) {
    // One sample in this process: the stages' boundaries catch what the
    // libraries throw; there is no queue to protect from a crash.
    auto one = ReconstructOptionsFromConfig(cfg);
    if (!one.ok()) {
      std::fprintf(stderr, "aggscan-worker: %s\n", one.error().ToString().c_str());
      return 2;
    }
    Status st = RunSampleStage(args.sample_dir, "", *one);
    if (!st.ok()) {
      AGG_LOGE(kCat, "%s: %s", args.sample_dir.c_str(), st.error().ToString().c_str());
      return 1;
    }
    AGG_LOGI(kCat, "%s: processed", args.sample_dir.c_str());
    return 0;
  }

  struct sigaction sa {};
  sa.sa_handler = OnSignal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);

  void* shared = ::mmap(nullptr, sizeof(ChildReport), PROT_READ | PROT_WRITE,
                        MAP_SHARED | MAP_ANONYMOUS, -1, 0);
  if (shared == MAP_FAILED) {
    AGG_LOGE(kCat, "cannot map the job report page: %s", std::strerror(errno));
    return 1;
  }
  g_report = new (shared) ChildReport();

  // The mask network (if configured) is checked once, at start, in a child
  // of its own: a missing or broken model is a config error, reported before
  // any job is claimed.
  if (cfg.mask.method == "onnx") {
    auto probe = RunInChild([&] {
      auto net = LoadMaskNet(cfg.mask);
      if (net.ok()) return kChildDone;
      CopyText(g_report->message, sizeof g_report->message, net.error().ToString());
      return kChildFailed;
    });
    if (!probe.ok() || probe->kind != ChildEnd::kDone) {
      std::fprintf(stderr, "aggscan-worker: %s\n",
                   !probe.ok()                         ? probe.error().ToString().c_str()
                   : probe->kind == ChildEnd::kStopped ? "stopped while checking the mask network"
                                                       : probe->reason.c_str());
      return 2;
    }
    AGG_LOGI(kCat, "masks: ONNX network %s", cfg.mask.model.c_str());
  }

  auto q = JobQueue::Open(layout::QueuePath(args.state_dir));
  if (!q.ok()) {
    AGG_LOGE(kCat, "cannot open the job queue in %s: %s", args.state_dir.c_str(),
             q.error().ToString().c_str());
    return 1;
  }
  JobQueue& queue = **q;
  if (auto n = queue.RequeueRunning(cfg.worker.max_interruptions); !n.ok()) {
    AGG_LOGE(kCat, "requeue of interrupted jobs failed: %s", n.error().ToString().c_str());
  } else {
    if (n->requeued > 0)
      AGG_LOGI(kCat, "requeued %d job(s) cut off when the worker was killed or lost power",
               n->requeued);
    if (n->failed > 0)
      AGG_LOGE(kCat, "%d job(s) failed: interrupted %d times in a row (see `aggscan status`)",
               n->failed, cfg.worker.max_interruptions);
  }
  AGG_LOGI(kCat, "started: state dir %s, poll %ld ms%s", args.state_dir.c_str(), poll_ms,
           args.once ? ", once" : "");
  WorkerReporter reporter(&queue, cfg.worker.heartbeat_interval);
  reporter.Idle();
  bool failed_for_good = false;
  while (!g_stop.load()) {
    auto next = queue.ClaimNext();
    if (!next.ok()) {
      AGG_LOGE(kCat, "queue error: %s", next.error().ToString().c_str());
      if (args.once) return 1;
      IdleWait(poll_ms, &reporter);
      continue;
    }
    if (!next->has_value()) {
      if (args.once) break;
      IdleWait(poll_ms, &reporter);
      continue;
    }
    const Job job = **next;
    const std::string what = job.kind == kJobCalibration ? std::string("rig calibration")
                             : job.side > 0              ? "side " + std::to_string(job.side)
                                                         : std::string("sample stage");
    const std::string name = "job " + std::to_string(job.id);
    LogLine(LogLevel::kInfo, kCat, job.sample_id,
            name + ": " + what + ", attempt " + std::to_string(job.attempts + 1) + " of " +
                std::to_string(cfg.worker.max_attempts));
    reporter.Busy(job);
    auto end = RunInChild([&] { return ChildRunJob(args.state_dir, job, cfg); }, &reporter);
    reporter.Idle();
    if (!end.ok()) {
      // No process for the job (out of processes or memory): not its fault.
      LogLine(LogLevel::kError, kCat, job.sample_id,
              name + ": " + end.error().ToString() + "; will retry");
      if (Status r = queue.Release(job.id); !r.ok())
        LogLine(LogLevel::kError, kCat, job.sample_id,
                "cannot put the job back: " + r.error().ToString());
      IdleWait(poll_ms, &reporter);
      continue;
    }
    if (end->kind == ChildEnd::kDone) {
      if (Status c = queue.Complete(job.id); !c.ok())
        LogLine(LogLevel::kError, kCat, job.sample_id,
                "cannot mark job done: " + c.error().ToString());
      else
        LogLine(LogLevel::kInfo, kCat, job.sample_id, name + " done");
    } else if (end->kind == ChildEnd::kStopped) {
      LogLine(LogLevel::kNotice, kCat, job.sample_id, name + " interrupted, will resume");
      if (Status r = queue.Release(job.id); !r.ok())
        LogLine(LogLevel::kError, kCat, job.sample_id,
                "cannot put the job back: " + r.error().ToString());
      if (g_stop.load()) break;
    } else {
      // A board the solver could not use (too few views or corners) gives
      // the same answer every time: the operator is told at once to shoot
      // it again. Crashes are retried like any job's.
      const bool board_unusable = job.kind == kJobCalibration && end->kind == ChildEnd::kFailed;
      const bool requeue = !board_unusable && job.attempts + 1 < cfg.worker.max_attempts;
      const std::string kind = end->kind == ChildEnd::kCrashed ? " crashed: " : " failed: ";
      LogLine(LogLevel::kError, kCat, job.sample_id,
              name + kind + end->reason +
                  (requeue          ? "; will retry"
                   : board_unusable ? "; lay the board flat in good light and calibrate again"
                                    : "; giving up after " + std::to_string(job.attempts + 1) +
                                          " attempts: fix the cause, then run `aggscan retry " +
                                          job.sample_id + "`"));
      if (!requeue) failed_for_good = true;
      if (Status f = queue.Fail(job.id, end->reason, requeue); !f.ok())
        LogLine(LogLevel::kError, kCat, job.sample_id,
                "cannot record the failure: " + f.error().ToString());
    }
  }
  reporter.Stopped();
  AGG_LOGI(kCat, "%s", g_stop.load() ? "stopped by signal" : "queue empty, exiting");
  return failed_for_good && args.once ? 1 : 0;
}
