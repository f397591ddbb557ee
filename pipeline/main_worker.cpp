// aggscan-worker: takes side and sample jobs from the queue in the state
// directory and runs the reconstruction stages on them: side jobs compute the
// masks and 2D figures of one side; a sample job, when the sample recorded a
// rig calibration at arm time (samples/<id>/calibration.json), runs every
// stage to the 3D model and morphology (pipeline/reconstruct.h), else only
// the 2D figures, saying how to calibrate. Niced below the capture daemon. SIGTERM/SIGINT: the
// current side stops between views (resumes there next time, the job stays
// "running" and is requeued at the next start without counting an attempt).
//
//   aggscan-worker --state-dir DIR [--config FILE] [--once] [--poll-ms N] [--log-level L]
#include <sys/resource.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cerrno>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "common/log.h"
#include "config/config.h"
#include "common/fsutil.h"
#include "pipeline/reconstruct.h"
#include "pipeline/side_job.h"
#include "store/layout.h"
#include "store/queue.h"

namespace {

using namespace aggscan;

constexpr const char* kCat = "worker";
constexpr int kMaxAttempts = 3;  // a job failing this many times stays failed

std::atomic<bool> g_stop{false};

extern "C" void OnSignal(int) { g_stop.store(true); }

void Usage(FILE* f) {
  std::fprintf(f,
               "usage: aggscan-worker --state-dir DIR [--config FILE] [--once] [--poll-ms N] [--log-level L]\n"
               "       aggscan-worker --sample SAMPLE_DIR [--config FILE] [--log-level L]\n"
               "  --sample DIR      process one sample directory now (every captured side, then\n"
               "                    the sample stage), without the queue; exit 1 on failure\n"
               "  --state-dir DIR   aggscan state directory (samples/, queue.db)\n"
               "  --config FILE     TOML config (worker.nice, worker.poll_interval, worker.poses); defaults otherwise\n"
               "  --once            exit when the queue is empty (exit 1 if a job failed for good)\n"
               "  --poll-ms N       idle queue polling period in ms (overrides the config)\n"
               "  --log-level L     error|warning|notice|info|debug\n");
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
        std::fprintf(stderr, "aggscan-worker: --poll-ms needs a positive integer, got '%s'\n", v.c_str());
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
void IdleWait(long ms) {
  for (long waited = 0; waited < ms && !g_stop.load(); waited += 20)
    std::this_thread::sleep_for(std::chrono::milliseconds(std::min<long>(20, ms - waited)));
}

// The sample stage: the 3D reconstruction when the sample carries its rig
// calibration or [worker] poses asks for SfM (auto, sfm), the 2D figures
// alone otherwise.
Status RunSampleStage(const std::string& dir, const std::string& state_dir, const WorkerOptions& opts,
                      PosesPath poses) {
  if (poses == PosesPath::kTurntable && !PathExists(dir + "/" + layout::kCalibrationCopy)) {
    AGG_LOGW(kCat, "%s: no rig calibration recorded in the sample: 2D figures only; run `aggscan calibrate` "
                   "(the daemon records it in every later sample), or give this sample a calibration.json and "
                   "run `aggscan reconstruct %s`",
             dir.c_str(), dir.c_str());
    return ProcessSample(dir, opts);
  }
  ReconstructOptions ro;
  ro.worker = opts;
  ro.state_dir = state_dir;
  ro.cancel = opts.cancel;
  ro.poses = poses;
  return ReconstructSample(dir, ro);
}

Status RunJob(const std::string& state_dir, const Job& job, const WorkerOptions& opts, PosesPath poses) {
  if (!layout::IsValidSampleId(job.sample_id))
    return MakeError(ErrorClass::kCorrupt, "job " + std::to_string(job.id) + " names an invalid sample id");
  const std::string dir = layout::SampleDir(state_dir, job.sample_id);
  return job.side > 0 ? ProcessSide(dir, job.side, opts) : RunSampleStage(dir, state_dir, opts, poses);
}

}  // namespace

int main(int argc, char** argv) {
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
      for (const auto& p : problems) std::fprintf(stderr, "aggscan-worker: %s\n", p.ToString().c_str());
      std::fprintf(stderr, "aggscan-worker: invalid config: %s\n", loaded.error().ToString().c_str());
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
  const long poll_ms = args.poll_ms > 0 ? args.poll_ms : static_cast<long>(cfg.worker.poll_interval / kNsPerMs);

  // Below the capture daemon. Lowering niceness needs privileges: only warn.
  errno = 0;
  const int current = getpriority(PRIO_PROCESS, 0);
  if (errno == 0 && current != cfg.worker.nice && setpriority(PRIO_PROCESS, 0, cfg.worker.nice) != 0)
    AGG_LOGW(kCat, "cannot set nice %d (staying at %d): %s", cfg.worker.nice, current, std::strerror(errno));

  // The mask network (if configured) is loaded once, at start: a missing or
  // broken model is a config error, reported before any job is claimed.
  auto mask_net = LoadMaskNet(cfg.mask);
  if (!mask_net.ok()) {
    std::fprintf(stderr, "aggscan-worker: %s\n", mask_net.error().ToString().c_str());
    return 2;
  }
  if (*mask_net) AGG_LOGI(kCat, "masks: ONNX network %s", cfg.mask.model.c_str());
  PosesPath poses = PosesPath::kTurntable;
  ParsePosesPath(cfg.worker.poses, &poses);  // validated with the config

  if (!args.sample_dir.empty()) {
    WorkerOptions one;
    one.mask_net = *mask_net;
    Status st = RunSampleStage(args.sample_dir, "", one, poses);
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

  auto q = JobQueue::Open(layout::QueuePath(args.state_dir));
  if (!q.ok()) {
    AGG_LOGE(kCat, "cannot open the job queue in %s: %s", args.state_dir.c_str(), q.error().ToString().c_str());
    return 1;
  }
  JobQueue& queue = **q;
  if (auto n = queue.RequeueRunning(); !n.ok())
    AGG_LOGE(kCat, "requeue of interrupted jobs failed: %s", n.error().ToString().c_str());
  else if (*n > 0)
    AGG_LOGI(kCat, "requeued %d job(s) interrupted by an earlier stop or crash", *n);

  WorkerOptions opts;
  opts.cancel = &g_stop;
  opts.mask_net = *mask_net;
  AGG_LOGI(kCat, "started: state dir %s, poll %ld ms%s", args.state_dir.c_str(), poll_ms, args.once ? ", once" : "");
  bool failed_for_good = false;
  while (!g_stop.load()) {
    auto next = queue.ClaimNext();
    if (!next.ok()) {
      AGG_LOGE(kCat, "queue error: %s", next.error().ToString().c_str());
      if (args.once) return 1;
      IdleWait(poll_ms);
      continue;
    }
    if (!next->has_value()) {
      if (args.once) break;
      IdleWait(poll_ms);
      continue;
    }
    const Job job = **next;
    const std::string what = job.side > 0 ? "side " + std::to_string(job.side) : std::string("sample stage");
    LogLine(LogLevel::kInfo, kCat, job.sample_id, "job " + std::to_string(job.id) + ": " + what + ", attempt " +
                                                      std::to_string(job.attempts));
    Status st = RunJob(args.state_dir, job, opts, poses);
    if (!st.ok() && g_stop.load() && st.error().cls == ErrorClass::kInvalidState) {
      // Interrupted by a stop request: leave it running; the next start requeues it.
      LogLine(LogLevel::kNotice, kCat, job.sample_id, "job " + std::to_string(job.id) + " interrupted, will resume");
      break;
    }
    if (st.ok()) {
      if (Status c = queue.Complete(job.id); !c.ok())
        LogLine(LogLevel::kError, kCat, job.sample_id, "cannot mark job done: " + c.error().ToString());
      else
        LogLine(LogLevel::kInfo, kCat, job.sample_id, "job " + std::to_string(job.id) + " done");
    } else {
      const bool requeue = job.attempts < kMaxAttempts;
      LogLine(LogLevel::kError, kCat, job.sample_id,
              "job " + std::to_string(job.id) + " failed (" + ErrorClassName(st.error().cls) +
                  "): " + st.error().ToString() + (requeue ? "; will retry" : "; giving up"));
      if (!requeue) failed_for_good = true;
      if (Status f = queue.Fail(job.id, st.error().ToString(), requeue); !f.ok())
        LogLine(LogLevel::kError, kCat, job.sample_id, "cannot record the failure: " + f.error().ToString());
    }
  }
  AGG_LOGI(kCat, "%s", g_stop.load() ? "stopped by signal" : "queue empty, exiting");
  return failed_for_good && args.once ? 1 : 0;
}
