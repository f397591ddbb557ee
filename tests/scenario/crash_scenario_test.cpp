// Crash scenarios: the real aggscand on the sim rig, killed with SIGKILL at
// random moments of a capture (armed, homing, mid-side, between sides, the
// instant a side's manifest appears) and restarted each time. After every
// restart the sample is either complete and queued for the worker, or
// re-armable at its first side without a manifest; no view that was ever
// stored is lost or changed, and interrupted attempts are kept.
#include <gtest/gtest.h>
#include <poll.h>
#include <sys/inotify.h>

#include <functional>
#include <map>
#include <random>
#include <set>

#include "process.h"

namespace aggscan::test {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr int kSides = 2;
constexpr int kViews = 6;
// Small frames and a fast sim clock: one side is a fraction of a second.
const char* kPlan =
    "profile = \"custom\"\nsides = 2\nviews_per_side = 6\nstep_deg = 60.0\ninterval = \"2s\"\n"
    "settle = \"100ms\"\n"
    // Sim time: a render late by a loaded machine's real
    // milliseconds must not fault the capture at 20x.
    "frame_timeout = \"120s\"\nmove_timeout = \"60s\"\nhome_timeout = \"120s\"\n";

std::string StateOf(const json& s) { return s.is_object() ? s.value("state", "") : ""; }

uint64_t HashFile(const fs::path& p) {
  const std::string data = ReadAll(p.string());
  uint64_t h = 1469598103934665603ull;  // FNV-1a: content identity, not security
  for (unsigned char c : data) h = (h ^ c) * 1099511628211ull;
  return h ^ data.size();
}

// Complete views (image + sidecar) of one side directory.
std::set<int> CompleteViews(const fs::path& side_dir) {
  std::set<int> out;
  if (!fs::is_directory(side_dir)) return out;
  for (int v = 0; v < kViews; ++v) {
    char img[32], car[32];
    std::snprintf(img, sizeof img, "view_%03d.jpg", v);
    std::snprintf(car, sizeof car, "view_%03d.json", v);
    if (fs::exists(side_dir / img) && fs::exists(side_dir / car)) out.insert(v);
  }
  return out;
}

struct DiskState {
  bool manifest[kSides + 1] = {};
  bool all_views[kSides + 1] = {};
  int attempts = 0;                       // side<N>.interrupted-<k> directories
  std::map<uint64_t, std::string> views;  // content hash of every complete view -> where
  int temp_files = 0;
  std::string record_state;  // sample.json "state" ("" = no record)
};

DiskState Scan(const std::string& sample) {
  DiskState d;
  if (!fs::exists(sample)) return d;
  const json rec = json::parse(ReadAll(sample + "/sample.json"), nullptr, false);
  if (rec.is_object()) d.record_state = rec.value("state", "");
  for (int s = 1; s <= kSides; ++s) {
    const fs::path dir = fs::path(sample) / ("side" + std::to_string(s));
    d.manifest[s] = fs::exists(dir / "manifest.json");
    d.all_views[s] = CompleteViews(dir).size() == static_cast<size_t>(kViews);
  }
  for (const auto& e : fs::recursive_directory_iterator(sample)) {
    const std::string name = e.path().filename().string();
    if (name.rfind(".tmp-", 0) == 0) ++d.temp_files;
    if (e.is_directory() && name.find(".interrupted-") != std::string::npos) ++d.attempts;
    if (name.rfind("view_", 0) == 0 && e.path().extension() == ".json") {
      fs::path img = e.path();
      img.replace_extension(".jpg");
      if (fs::exists(img)) d.views[HashFile(img)] = fs::relative(img, sample).string();
    }
  }
  return d;
}

// Watches a sample directory and its side directories for a manifest.json.
class ManifestWatch {
 public:
  explicit ManifestWatch(const std::string& sample) : sample_(sample) {
    fd_ = ::inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
    if (fd_ < 0) return;
    top_ = ::inotify_add_watch(fd_, sample.c_str(), IN_CREATE | IN_MOVED_TO);
    for (int s = 1; s <= kSides; ++s) WatchSide(s);
  }
  ~ManifestWatch() {
    if (fd_ >= 0) ::close(fd_);
  }
  bool ok() const { return fd_ >= 0 && top_ >= 0; }
  /// Waits up to `ms` for events; returns the side whose manifest appeared, else 0.
  int Poll(int ms) {
    pollfd p{fd_, POLLIN, 0};
    if (::poll(&p, 1, ms) <= 0) return 0;
    alignas(inotify_event) char buf[8192];
    int found = 0;
    for (;;) {
      const ssize_t n = ::read(fd_, buf, sizeof buf);
      if (n <= 0) break;
      for (char* q = buf; q < buf + n;) {
        const auto* ev = reinterpret_cast<const inotify_event*>(q);
        const std::string name = ev->len ? ev->name : "";
        if (ev->wd == top_) {
          // A side directory (re)created by BeginSide: watch it for its manifest.
          for (int s = 1; s <= kSides; ++s) {
            if (name == "side" + std::to_string(s)) WatchSide(s);
          }
        } else if (name == "manifest.json") {
          for (const auto& [s, wd] : sides_) {
            if (wd == ev->wd) found = s;
          }
        }
        q += sizeof(inotify_event) + ev->len;
      }
    }
    return found;
  }

 private:
  void WatchSide(int s) {
    const std::string dir = sample_ + "/side" + std::to_string(s);
    const int wd = ::inotify_add_watch(fd_, dir.c_str(), IN_CREATE | IN_MOVED_TO);
    if (wd >= 0) sides_[s] = wd;
  }
  std::string sample_;
  int fd_ = -1, top_ = -1;
  std::map<int, int> sides_;  // side -> watch descriptor
};

TEST(CrashScenario, SixtyKillsAtEveryPhaseLoseNothing) {
  TempDir t;
  const std::string cfg = WriteConfig(t.path(), "", 20, kPlan);
  const std::string samples = t.path() + "/state/samples";
  std::mt19937 rng(20261202);
  const int kKills = std::getenv("CRASH_KILLS") ? std::atoi(std::getenv("CRASH_KILLS")) : 60;

  std::map<std::string, int>
      phase_at_kill;  // last status seen before the kill, or "after manifest N"
  std::map<std::string, int> outcomes;
  std::map<uint64_t, std::string> ever_stored;    // every complete view ever seen, across samples
  std::vector<std::string> completed_by_restart;  // samples completed by start-up recovery
  std::vector<std::string> completed_samples;
  int kills = 0, kills_after_manifest[kSides + 1] = {}, trials = 0;
  int rock = 1;
  double full_capture_s = 0;  // measured on the first, unkilled sample
  DiskState before;           // what the last kill left of the current sample
  bool restarted_after_kill = false;
  const auto t_start = std::chrono::steady_clock::now();

  while (kills < kKills) {
    ASSERT_LT(++trials, 200) << "too many trials without reaching " << kKills << " kills";
    const std::string id = "crash-" + std::to_string(rock);
    const std::string sample = samples + "/" + id;
    Daemon d(cfg, t.path(), 20);
    ASSERT_TRUE(d.ok()) << ReadAll(d.log());

    // ---- what start-up recovery made of the last kill ----
    DiskState now = Scan(sample);
    EXPECT_EQ(now.temp_files, 0) << "temporary files left after start-up in " << sample;
    for (const auto& [h, where] : ever_stored) {
      if (where.rfind(id + "/", 0) != 0) continue;
      EXPECT_TRUE(now.views.count(h)) << "view lost or changed after a kill: " << where;
    }
    EXPECT_GE(now.attempts, before.attempts) << "an interrupted attempt disappeared";
    bool complete = fs::exists(sample + "/sample.json");
    for (int s = 1; s <= kSides; ++s) {
      // A side whose every view was stored is completed, never re-shot.
      if (restarted_after_kill && before.all_views[s]) {
        EXPECT_TRUE(now.manifest[s]) << id << " side " << s;
      }
      complete = complete && now.manifest[s];
    }
    if (complete) {
      json rec = json::parse(ReadAll(sample + "/sample.json"));
      EXPECT_EQ(rec["state"], "captured") << rec.dump();
      json m = d.Get("/api/v1/samples/" + id);
      std::set<int> queued;
      for (const auto& j : m["jobs"]) queued.insert(j["side"].get<int>());
      EXPECT_EQ(queued, (std::set<int>{0, 1, 2}))
          << "sample and side jobs must be queued: " << m.dump();
      // It cannot be re-armed, and says why.
      int code = 0;
      json again = d.Post("/api/v1/samples", "{\"id\": \"" + id + "\"}", &code);
      EXPECT_EQ(code, 409) << again.dump();
      if (restarted_after_kill && before.record_state != "captured") {
        // Killed before the record said so: start-up recovery completed it.
        ++outcomes["completed and queued by start-up"];
        completed_by_restart.push_back(id);
      } else if (restarted_after_kill) {
        ++outcomes["killed after it was complete"];
      }
      completed_samples.push_back(id);
      ++rock;
      before = DiskState{};
      restarted_after_kill = false;
      continue;  // the next trial shoots a new rock
    }

    // ---- re-arm: resumes at the first side without a manifest ----
    int expected_first = 1;
    while (expected_first <= kSides && now.manifest[expected_first]) ++expected_first;
    int code = 0;
    json armed = d.Post("/api/v1/samples", "{\"id\": \"" + id + "\"}", &code);
    ASSERT_EQ(code, 200) << armed.dump() << ReadAll(d.log());
    EXPECT_EQ(armed["first_side"], expected_first) << armed.dump();
    if (restarted_after_kill) ++outcomes["re-armed at side " + std::to_string(expected_first)];

    // ---- how this trial ends: a kill (armed, random moment, or a manifest) or the whole sample
    // ----
    enum Mode { kArmedKill, kRandom, kAfterManifest, kFinish } mode;
    const int r = std::uniform_int_distribution<int>(0, 99)(rng);
    if (full_capture_s == 0)
      mode = kFinish;  // the first rock measures a whole capture
    else if (r < 8)
      mode = kArmedKill;
    else if (r < 40)
      mode = kAfterManifest;
    else
      mode = kRandom;
    int target_side = expected_first;
    if (mode == kAfterManifest) {
      // The side with the fewest such kills so far that this trial can reach.
      for (int side = expected_first; side <= kSides; ++side) {
        if (kills_after_manifest[side] < kills_after_manifest[target_side]) target_side = side;
      }
    }
    ManifestWatch watch(sample);
    ASSERT_TRUE(watch.ok()) << "inotify: " << std::strerror(errno);

    std::string last_phase = "armed";
    bool killed = false;
    if (mode == kArmedKill) {
      d.Kill(SIGKILL);
      killed = true;
    } else {
      d.Post("/api/v1/button", "{}", &code);
      ASSERT_EQ(code, 200);
      const auto t0 = std::chrono::steady_clock::now();
      const double kill_after_s =
          mode == kRandom ? std::uniform_real_distribution<double>(0, full_capture_s * 1.05)(rng)
                          : 1e9;
      const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(60);
      while (mode == kAfterManifest && std::chrono::steady_clock::now() < deadline) {
        // Only the inotify event: a status request would wait for the loop,
        // which finishes the side (record, jobs) before it answers.
        const int manifest = watch.Poll(50);
        if (manifest == target_side) {
          d.Kill(SIGKILL);
          last_phase = "after manifest of side " + std::to_string(manifest);
          ++kills_after_manifest[manifest];
          killed = true;
          break;
        }
        if (manifest != 0) {
          // An earlier side is done: flip and press for the next one.
          json st;
          ASSERT_TRUE(
              d.WaitFor([](const json& s) { return StateOf(s) == "awaiting_pose"; }, 30, &st))
              << st.dump();
          d.Post("/api/v1/button", "{}", &code);
          ASSERT_EQ(code, 200);
        }
      }
      while (mode == kRandom && std::chrono::steady_clock::now() < deadline) {
        const double el =
            std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        if (el >= kill_after_s) {
          d.Kill(SIGKILL);
          killed = true;
          break;
        }
        json st = d.Get("/api/v1/status");
        const std::string phase = StateOf(st);
        if (!phase.empty()) last_phase = phase;
        if (phase == "awaiting_pose") {
          d.Post("/api/v1/button", "{}", &code);
        } else if (phase == "idle") {
          break;  // the whole sample was captured before the kill moment
        } else {
          ASSERT_NE(phase, "faulted") << st.dump() << ReadAll(d.log());
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
      }
      while (mode == kFinish) {
        json st;
        ASSERT_TRUE(d.WaitFor(
            [](const json& s) { return StateOf(s) == "awaiting_pose" || StateOf(s) == "idle"; }, 60,
            &st))
            << st.dump() << ReadAll(d.log());
        last_phase = StateOf(st);
        if (last_phase == "idle") break;
        d.Post("/api/v1/button", "{}", &code);
      }
      ASSERT_TRUE(killed || last_phase == "idle")
          << "the trial neither killed nor finished: " << ReadAll(d.log());
      if (!killed) {
        if (full_capture_s == 0) {
          full_capture_s =
              std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        }
        EXPECT_EQ(d.Stop(), 0);
        ++outcomes["finished before the kill"];
      }
    }
    if (killed) {
      ++kills;
      ++phase_at_kill[last_phase];
      restarted_after_kill = true;
    } else {
      restarted_after_kill = false;
    }
    // ---- on disk right after the kill: nothing partial, nothing lost ----
    before = Scan(sample);
    for (const auto& [h, where] : ever_stored) {
      if (where.rfind(id + "/", 0) == 0) {
        EXPECT_TRUE(before.views.count(h)) << "view lost or changed: " << where;
      }
    }
    for (const auto& [h, where] : before.views) ever_stored.emplace(h, id + "/" + where);
  }

  // The last rock: restart once more so a kill after its last manifest is recovered too.
  {
    Daemon d(cfg, t.path(), 20);
    ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  }
  const double took_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count();

  // Every view ever stored is still there, byte for byte.
  std::set<uint64_t> at_end;
  for (const auto& e : fs::recursive_directory_iterator(samples)) {
    if (e.path().extension() == ".jpg") at_end.insert(HashFile(e.path()));
    EXPECT_NE(e.path().filename().string().rfind(".tmp-", 0), 0u)
        << "leftover temp file " << e.path();
  }
  for (const auto& [h, where] : ever_stored) EXPECT_TRUE(at_end.count(h)) << "lost view " << where;

  std::printf(
      "crash scenario: %d trials, %d kills (%d after side 1's manifest, %d after side 2's), %zu "
      "samples "
      "complete (%zu completed by start-up after a kill), %zu views stored, %.1f s (a whole "
      "capture %.2f s)\n",
      trials, kills, kills_after_manifest[1], kills_after_manifest[2], completed_samples.size(),
      completed_by_restart.size(), ever_stored.size(), took_s, full_capture_s);
  for (const auto& [p, n] : phase_at_kill)
    std::printf("  killed while %-28s %d\n", (p + ":").c_str(), n);
  for (const auto& [o, n] : outcomes) std::printf("  outcome %-34s %d\n", (o + ":").c_str(), n);

  EXPECT_GE(kills, kKills);
  EXPECT_GE(kills_after_manifest[1], 5);
  EXPECT_GE(kills_after_manifest[2], 5);
  // Every phase of a capture was hit: armed, homing or mid-side, between sides.
  EXPECT_GE(phase_at_kill["armed"], 1);
  EXPECT_GE(phase_at_kill["awaiting_pose"] + kills_after_manifest[1], 1);
  int mid_side = 0;
  for (const char* p :
       {"homing", "rotating", "settling", "waiting", "capturing", "storing", "finishing"}) {
    mid_side += phase_at_kill[p];
  }
  EXPECT_GE(mid_side, 15);
  ASSERT_FALSE(completed_by_restart.empty());

  // The worker reconstructs a sample that start-up recovery completed.
  const std::string recovered = samples + "/" + completed_by_restart.front();
  const int wrc = WaitExit(
      Spawn({Bin("pipeline/aggscan-worker"), "--sample", recovered}, t.path() + "/worker.log"));
  ASSERT_EQ(wrc, 0) << ReadAll(t.path() + "/worker.log");
  for (int side = 1; side <= kSides; ++side) {
    json r =
        json::parse(ReadAll(recovered + "/results/side" + std::to_string(side) + "_morph2d.json"),
                    nullptr, false);
    ASSERT_FALSE(r.is_discarded()) << "side " << side << " results missing";
    EXPECT_EQ(r["views"].size(), static_cast<size_t>(kViews));
  }
  EXPECT_TRUE(fs::exists(recovered + "/results/morph2d.json"));
}

}  // namespace
}  // namespace aggscan::test
