// Storage failures under the real aggscand: a real ENOSPC at each step that
// stores a file (side directory, record, view image, sidecar, manifest, the
// record after it), and a job queue that cannot be written. Each one is a
// named fault the operator sees in status and health (503), and after the
// cause is gone, reset and re-arm, nothing stored is lost: a side whose views
// are all stored is completed, any other is re-shot with the old attempt kept.
//
// The full disk is a tmpfs with a small file (inode) budget, mounted in a
// private mount namespace of this test process (root only), so the kernel
// itself answers ENOSPC; the daemons inherit the namespace.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sched.h>
#include <sqlite3.h>
#include <sys/mount.h>
#include <sys/statvfs.h>

#include <map>
#include <set>

#include "process.h"

namespace aggscan::test {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// One side of three views: short cases, and a side's end is the sample's end.
const char* kPlan =
    "profile = \"custom\"\nsides = 1\nviews_per_side = 3\nstep_deg = 30.0\ninterval = \"1s\"\n"
    "settle = \"50ms\"\n";

std::string StateOf(const json& s) { return s.is_object() ? s.value("state", "") : ""; }

uint64_t HashFile(const fs::path& p) {
  const std::string data = ReadAll(p.string());
  uint64_t h = 1469598103934665603ull;  // FNV-1a: content identity
  for (unsigned char c : data) h = (h ^ c) * 1099511628211ull;
  return h ^ data.size();
}

// Content hashes of every complete view (image with sidecar) under `dir`.
std::set<uint64_t> StoredViews(const std::string& dir) {
  std::set<uint64_t> out;
  if (!fs::exists(dir)) return out;
  for (const auto& e : fs::recursive_directory_iterator(dir)) {
    if (e.path().extension() != ".json" || e.path().filename().string().rfind("view_", 0) != 0)
      continue;
    fs::path img = e.path();
    img.replace_extension(".jpg");
    if (fs::exists(img)) out.insert(HashFile(img));
  }
  return out;
}

int64_t FreeFiles(const std::string& dir) {
  struct statvfs v {};
  return ::statvfs(dir.c_str(), &v) == 0 ? static_cast<int64_t>(v.f_favail) : -1;
}

int64_t FreePages(const std::string& dir) {
  struct statvfs v {};
  return ::statvfs(dir.c_str(), &v) == 0 ? static_cast<int64_t>(v.f_bavail * v.f_frsize / 4096)
                                         : -1;
}

// 4 KiB pages the complete views of a side directory take on tmpfs.
int64_t ViewPages(const std::string& side_dir) {
  int64_t pages = 0;
  for (const auto& e : fs::directory_iterator(side_dir)) {
    if (e.path().filename().string().rfind("view_", 0) == 0)
      pages += (fs::file_size(e.path()) + 4095) / 4096;
  }
  return pages;
}

// Which store step a fault message names (the failing file is in the error).
std::string StepOf(const std::string& msg) {
  if (msg.find("cannot queue") != std::string::npos) return "queue";
  if (msg.find("cannot start side") != std::string::npos)
    return "side directory or record at side start";
  if (msg.find("manifest.json") != std::string::npos) return "manifest";
  if (msg.find("sample.json") != std::string::npos) {
    return msg.find("manifest") != std::string::npos || msg.find("captured") != std::string::npos
               ? "record after the manifest"
               : "record";
  }
  if (msg.find(".jpg") != std::string::npos) return "view image";
  if (msg.find("view_") != std::string::npos && msg.find(".json") != std::string::npos)
    return "view sidecar";
  return "other: " + msg;
}

// A tmpfs mounted over `dir` in this process's private mount namespace.
class PrivateTmpfs {
 public:
  explicit PrivateTmpfs(const std::string& dir, const std::string& opts) : dir_(dir) {
    if (::geteuid() != 0) {
      why_ = "needs root to mount a tmpfs (run the suite as root, as CI does)";
      return;
    }
    if (::unshare(CLONE_NEWNS) != 0) {
      why_ = std::string("unshare(CLONE_NEWNS) failed: ") + std::strerror(errno) +
             " (a container without CAP_SYS_ADMIN?)";
      return;
    }
    // Our mounts must not leak to the host: make the tree private first.
    if (::mount("none", "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0) {
      why_ = std::string("cannot make / private: ") + std::strerror(errno);
      return;
    }
    fs::create_directories(dir);
    if (::mount("aggscan-test", dir.c_str(), "tmpfs", 0, opts.c_str()) != 0) {
      why_ = std::string("cannot mount tmpfs: ") + std::strerror(errno);
      return;
    }
    mounted_ = true;
  }
  ~PrivateTmpfs() {
    if (mounted_) ::umount2(dir_.c_str(), MNT_DETACH);
  }
  bool ok() const { return mounted_; }
  const std::string& why() const { return why_; }

 private:
  std::string dir_, why_;
  bool mounted_ = false;
};

TEST(DiskFullScenario, EveryStoreStepIsANamedFaultAndNothingIsLost) {
  TempDir t;
  const std::string state = t.path() + "/state";
  PrivateTmpfs tmpfs(state, "size=64m,nr_inodes=4096,mode=0755");
  if (!tmpfs.ok()) GTEST_SKIP() << tmpfs.why();
  // No worker runs beside this daemon for longer than worker.silent_after:
  // health here is the storage's alone.
  const std::string cfg = WriteConfig(t.path(), "[worker]\nsilent_after = \"0s\"\n", 4, kPlan);
  Daemon d(cfg, t.path(), 20);
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  const std::string filler = state + "/filler";
  fs::create_directories(filler);

  std::map<std::string, int> steps;  // store step that failed -> cases
  int completed_by_rearm = 0, reshot = 0, finished = 0;
  // K = files the daemon may still create once the side starts: 0 fails the
  // side directory, then the record, view 0's image, its sidecar, ... and
  // past the last one the side finishes.
  // Then a page budget around what a side's views take (measured on a side
  // shot here), so that the manifest, the record after it and the queue's
  // journal run out of space in turn.
  struct Budget {
    bool files;  // true: K more files, false: K more 4 KiB pages
    int64_t k;
  };
  std::vector<Budget> budgets;
  for (int k = 0; k <= 16; ++k) budgets.push_back({true, k});
  int64_t side_pages = -1;
  for (size_t bi = 0;; ++bi) {
    if (bi == 17) {
      // After the file budgets: the page budgets, from a side finished above.
      ASSERT_GT(side_pages, 3) << "no side finished under the file budgets";
      for (int64_t p = side_pages - 3; p <= side_pages + 6; ++p) budgets.push_back({false, p});
    }
    if (bi >= budgets.size()) break;
    const Budget b = budgets[bi];
    const int64_t k = b.k;
    SCOPED_TRACE((b.files ? "free files " : "free pages ") + std::to_string(k));
    const std::string id = std::string(b.files ? "files-" : "pages-") + std::to_string(k);
    const std::string sample = state + "/samples/" + id;
    int code = 0;
    json a = d.Post("/api/v1/samples", "{\"id\": \"" + id + "\"}", &code);
    ASSERT_EQ(code, 200) << a.dump();
    d.Post("/api/v1/button", "{}", &code);
    ASSERT_EQ(code, 200);
    // Homing takes 1.5 s of sim time (the side directory comes after it):
    // stop the daemon there, fill the disk, go on.
    json homing;
    ASSERT_TRUE(d.WaitFor([](const json& s) { return StateOf(s) != "armed"; }, 30, &homing))
        << homing.dump();
    ASSERT_EQ(::kill(d.pid(), SIGSTOP), 0);
    if (b.files) {
      int n = 0;
      while (FreeFiles(state) > k)
        std::ofstream(filler + "/f" + std::to_string(k) + "-" + std::to_string(n++));
      ASSERT_EQ(FreeFiles(state), k);
    } else {
      const int fd = ::open((filler + "/blocks").c_str(), O_CREAT | O_WRONLY | O_CLOEXEC, 0644);
      ASSERT_GE(fd, 0);
      ASSERT_EQ(::posix_fallocate(fd, 0, (FreePages(state) - k) * 4096), 0);
      ::close(fd);
      ASSERT_EQ(FreePages(state), k);
    }
    ASSERT_EQ(::kill(d.pid(), SIGCONT), 0);

    json last;
    ASSERT_TRUE(d.WaitFor(
        [](const json& s) { return StateOf(s) == "faulted" || StateOf(s) == "idle"; }, 60, &last))
        << last.dump() << ReadAll(d.log());
    std::set<uint64_t> before;
    if (StateOf(last) == "faulted") {
      const json f = last["fault"];
      EXPECT_EQ(f["class"], "disk_full") << last.dump();
      const std::string msg = f["message"].get<std::string>();
      const std::string step = StepOf(msg);
      ++steps[step];
      EXPECT_EQ(step.rfind("other", 0), std::string::npos) << msg;
      EXPECT_NE(last["status_line"].get<std::string>().find("FAULT"), std::string::npos);
      // Health names it: 503, storage unhealthy with the fault, status not ok.
      json h = d.Get("/api/v1/health", &code);
      EXPECT_EQ(code, 503) << h.dump();
      EXPECT_EQ(h["status"], "faulted") << h.dump();
      EXPECT_EQ(h["devices"]["storage"]["state"], "disk_full") << h.dump();
      EXPECT_FALSE(h["devices"]["storage"]["healthy"].get<bool>());
      EXPECT_NE(h["devices"]["storage"]["message"].get<std::string>().find(msg), std::string::npos)
          << h.dump();
      before = StoredViews(sample);

      // Free the space, reset, re-arm.
      fs::remove_all(filler);
      fs::create_directories(filler);
      d.Post("/api/v1/reset", "{}", &code);
      ASSERT_EQ(code, 200);
      h = d.Get("/api/v1/health", &code);
      EXPECT_EQ(code, 200) << h.dump();
      EXPECT_EQ(h["devices"]["storage"]["state"], "ok") << h.dump();
      json again = d.Post("/api/v1/samples", "{\"id\": \"" + id + "\"}", &code);
      if (step == "manifest" || step == "record after the manifest" || step == "queue") {
        // Every view is stored: completed from the store, not re-shot.
        EXPECT_EQ(code, 409) << again.dump();
        EXPECT_NE(again.dump().find("is complete"), std::string::npos) << again.dump();
        ++completed_by_rearm;
      } else {
        ASSERT_EQ(code, 200) << again.dump() << ReadAll(d.log());
        EXPECT_EQ(again["first_side"], 1);
        d.Post("/api/v1/button", "{}", &code);
        ASSERT_EQ(code, 200) << ReadAll(d.log());
        ASSERT_TRUE(
            d.WaitFor([](const json& s) { return StateOf(s) == "idle" || StateOf(s) == "faulted"; },
                      60, &last));
        ASSERT_EQ(StateOf(last), "idle") << last.dump();
        ++reshot;
      }
    } else {
      ++finished;
      fs::remove_all(filler);
      fs::create_directories(filler);
      if (side_pages < 0) side_pages = ViewPages(sample + "/side1");
    }
    // The sample is complete and queued, and every view stored before is still there.
    json rec = json::parse(ReadAll(sample + "/sample.json"));
    EXPECT_EQ(rec["state"], "captured") << rec.dump();
    EXPECT_TRUE(fs::exists(sample + "/side1/manifest.json"));
    json m = d.Get("/api/v1/samples/" + id);
    std::set<int> jobs;
    for (const auto& j : m["jobs"]) jobs.insert(j["side"].get<int>());
    EXPECT_EQ(jobs, (std::set<int>{0, 1})) << m.dump();
    const std::set<uint64_t> after = StoredViews(sample);
    for (uint64_t h : before)
      EXPECT_TRUE(after.count(h)) << "a stored view was lost after the disk filled";
  }
  std::printf("disk full: ");
  for (const auto& [s, n] : steps) std::printf("%s x%d; ", s.c_str(), n);
  std::printf("completed by re-arm %d, re-shot %d, finished %d\n", completed_by_rearm, reshot,
              finished);
  for (const char* s :
       {"view image", "view sidecar", "manifest", "record after the manifest", "queue"}) {
    EXPECT_GE(steps[s], 1) << "no case failed at the " << s;
  }
  EXPECT_GE(finished, 1) << "the budget never let a side finish";

  // No room for a side: the press is refused, naming free and needed space.
  int n = 0;
  while (FreeFiles(state) > 5) std::ofstream(filler + "/g" + std::to_string(n++));
  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "no-room"})", &code);
  ASSERT_EQ(code, 200);
  json r = d.Post("/api/v1/button", "{}", &code);
  EXPECT_NE(code, 200) << r.dump();
  EXPECT_EQ(r["error"]["class"], "disk_full") << r.dump();
  const std::string why = r["error"]["message"].get<std::string>();
  EXPECT_NE(why.find("cannot start side 1"), std::string::npos) << why;
  EXPECT_NE(why.find("more files can be created"), std::string::npos) << why;
  json h = d.Get("/api/v1/health", &code);
  EXPECT_EQ(code, 503) << h.dump();
  EXPECT_EQ(h["status"], "unhealthy") << h.dump();
  EXPECT_EQ(h["devices"]["storage"]["state"], "disk_full") << h.dump();
  EXPECT_EQ(StateOf(d.Get("/api/v1/status")), "armed");
  fs::remove_all(filler);
  EXPECT_EQ(d.Stop(), 0);
}

// Bytes, not files: a disk with less free space than a side needs refuses
// the press with both figures; the estimate comes from the camera resolution.
TEST(DiskFullScenario, PressNeedsRoomForASide) {
  TempDir t;
  const std::string state = t.path() + "/state";
  // 640x480: about 31 kB a view, 3 views with margin and 1 MiB of slack: ~1.2 MB.
  PrivateTmpfs tmpfs(state, "size=1m,mode=0755");
  if (!tmpfs.ok()) GTEST_SKIP() << tmpfs.why();
  Daemon d(WriteConfig(t.path(), "", 4, kPlan), t.path(), 20);
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "small-disk"})", &code);
  ASSERT_EQ(code, 200);
  json r = d.Post("/api/v1/button", "{}", &code);
  EXPECT_EQ(code / 100, 5) << r.dump();
  const std::string why = r["error"]["message"].get<std::string>();
  EXPECT_NE(why.find("MB free on " + state), std::string::npos) << why;
  EXPECT_NE(why.find("a side needs about"), std::string::npos) << why;
  EXPECT_NE(why.find("640x480"), std::string::npos) << why;
  json h = d.Get("/api/v1/health", &code);
  EXPECT_EQ(code, 503);
  const json st = h["devices"]["storage"];
  EXPECT_LT(st["free_bytes"].get<int64_t>(), st["side_needs_bytes"].get<int64_t>()) << h.dump();
  // 3 views x (0.102 B/px x 640 x 480 + 4 kB) x 1.5 + 1 MiB, within rounding.
  EXPECT_NEAR(st["side_needs_bytes"].get<double>(), 3 * (0.1017 * 640 * 480 + 4096) * 1.5 + 1048576,
              2000);
  EXPECT_EQ(d.Stop(), 0);
}

// The queue cannot take the side job (another process holds its write lock
// past the busy timeout): a named fault, and re-arming queues what is stored.
TEST(DiskFullScenario, QueueThatCannotBeWrittenIsANamedFault) {
  TempDir t;
  Daemon d(WriteConfig(t.path(), "", 4, kPlan), t.path(), 20);
  ASSERT_TRUE(d.ok()) << ReadAll(d.log());
  int code = 0;
  d.Post("/api/v1/samples", R"({"id": "q-locked"})", &code);
  ASSERT_EQ(code, 200);
  sqlite3* db = nullptr;
  ASSERT_EQ(sqlite3_open((t.path() + "/state/queue.db").c_str(), &db), SQLITE_OK);
  ASSERT_EQ(sqlite3_exec(db, "BEGIN IMMEDIATE", nullptr, nullptr, nullptr), SQLITE_OK)
      << sqlite3_errmsg(db);
  d.Post("/api/v1/button", "{}", &code);
  ASSERT_EQ(code, 200);
  json last;
  ASSERT_TRUE(d.WaitFor(
      [](const json& s) { return StateOf(s) == "faulted" || StateOf(s) == "idle"; }, 60, &last))
      << last.dump();
  ASSERT_EQ(StateOf(last), "faulted") << last.dump();
  const std::string msg = last["fault"]["message"].get<std::string>();
  EXPECT_NE(msg.find("cannot queue side 1 for the worker"), std::string::npos) << msg;
  EXPECT_EQ(d.Get("/api/v1/health", &code)["status"], "faulted");
  EXPECT_EQ(code, 503);
  sqlite3_exec(db, "ROLLBACK", nullptr, nullptr, nullptr);
  sqlite3_close(db);
  d.Post("/api/v1/reset", "{}", &code);
  ASSERT_EQ(code, 200);
  json again = d.Post("/api/v1/samples", R"({"id": "q-locked"})", &code);
  EXPECT_EQ(code, 409) << again.dump();
  json m = d.Get("/api/v1/samples/q-locked");
  std::set<int> jobs;
  for (const auto& j : m["jobs"]) jobs.insert(j["side"].get<int>());
  EXPECT_EQ(jobs, (std::set<int>{0, 1})) << m.dump();
  EXPECT_EQ(m["state"], "captured") << m.dump();
  EXPECT_EQ(d.Stop(), 0);
}

}  // namespace
}  // namespace aggscan::test
