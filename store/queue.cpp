#include "store/queue.h"

#include <sqlite3.h>
#include <time.h>

#include <fstream>

#include "common/clock.h"

namespace aggscan {
namespace {

// Finalizes a prepared statement on scope exit.
class Stmt {
 public:
  Stmt(sqlite3* db, const char* sql) : db_(db) {
    rc_ = sqlite3_prepare_v2(db, sql, -1, &st_, nullptr);
  }
  ~Stmt() { sqlite3_finalize(st_); }
  Stmt(const Stmt&) = delete;
  Stmt& operator=(const Stmt&) = delete;
  bool ok() const { return rc_ == SQLITE_OK; }
  sqlite3_stmt* get() { return st_; }
  void Bind(int i, const std::string& s) {
    sqlite3_bind_text(st_, i, s.c_str(), -1, SQLITE_TRANSIENT);
  }
  void Bind(int i, int64_t v) { sqlite3_bind_int64(st_, i, v); }
  int Step() { return sqlite3_step(st_); }
  std::string Text(int col) {
    const unsigned char* t = sqlite3_column_text(st_, col);
    return t ? reinterpret_cast<const char*>(t) : "";
  }
  int64_t Int(int col) { return sqlite3_column_int64(st_, col); }

 private:
  sqlite3* db_;
  sqlite3_stmt* st_ = nullptr;
  int rc_;
};

Error DbError(sqlite3* db, const std::string& what) {
  const int code = sqlite3_errcode(db);
  ErrorClass cls = (code == SQLITE_FULL)                               ? ErrorClass::kDiskFull
                   : (code == SQLITE_CORRUPT || code == SQLITE_NOTADB) ? ErrorClass::kCorrupt
                                                                       : ErrorClass::kIo;
  return MakeError(cls, "job queue: " + what, sqlite3_errmsg(db));
}

constexpr const char* kJobColumns =
    "id, sample_id, side, state, attempts, COALESCE(error,''), created_utc, updated_utc, "
    "interruptions, "
    "kind";

Job ReadJob(Stmt& st) {
  Job j;
  j.id = st.Int(0);
  j.sample_id = st.Text(1);
  j.side = static_cast<int>(st.Int(2));
  j.state = st.Text(3);
  j.attempts = static_cast<int>(st.Int(4));
  j.error = st.Text(5);
  j.created_utc = st.Text(6);
  j.updated_utc = st.Text(7);
  j.interruptions = static_cast<int>(st.Int(8));
  j.kind = st.Text(9);
  return j;
}

}  // namespace

Result<std::unique_ptr<JobQueue>> JobQueue::Open(const std::string& path) {
  sqlite3* db = nullptr;
  const int rc =
      sqlite3_open_v2(path.c_str(), &db,
                      SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_FULLMUTEX, nullptr);
  if (rc != SQLITE_OK) {
    Error e = MakeError(ErrorClass::kIo, "cannot open job queue " + path,
                        db ? sqlite3_errmsg(db) : "out of memory");
    sqlite3_close(db);
    return e;
  }
  std::unique_ptr<JobQueue> q(new JobQueue(db));
  // Another process (daemon or worker) may hold the write lock briefly.
  sqlite3_busy_timeout(db, 5000);
  // WAL + FULL: a committed enqueue survives power loss; readers never block the writer.
  for (const char* sql :
       {"PRAGMA journal_mode=WAL", "PRAGMA synchronous=FULL",
        "CREATE TABLE IF NOT EXISTS jobs ("
        " id INTEGER PRIMARY KEY AUTOINCREMENT,"
        " sample_id TEXT NOT NULL,"
        " side INTEGER NOT NULL,"
        " state TEXT NOT NULL CHECK (state IN ('queued','running','done','failed')),"
        " attempts INTEGER NOT NULL DEFAULT 0,"
        " error TEXT,"
        " created_utc TEXT NOT NULL,"
        " updated_utc TEXT NOT NULL)",
        "CREATE INDEX IF NOT EXISTS jobs_state ON jobs(state, id)",
        // One row: the worker's last report (WorkerReport).
        "CREATE TABLE IF NOT EXISTS worker ("
        " id INTEGER PRIMARY KEY CHECK (id = 1),"
        " pid INTEGER NOT NULL,"
        " state TEXT NOT NULL,"
        " job_id INTEGER NOT NULL,"
        " sample_id TEXT NOT NULL,"
        " side INTEGER NOT NULL,"
        " stage TEXT NOT NULL,"
        " done INTEGER NOT NULL,"
        " total INTEGER NOT NULL,"
        " started_boot_ns INTEGER NOT NULL,"
        " job_started_boot_ns INTEGER NOT NULL,"
        " stage_since_boot_ns INTEGER NOT NULL,"
        " boot_id TEXT NOT NULL,"
        " heard_boot_ns INTEGER NOT NULL,"
        " heard_utc TEXT NOT NULL)",
        "CREATE INDEX IF NOT EXISTS jobs_sample ON jobs(sample_id, side)"}) {
    Status s = q->Exec(sql);
    if (!s) return s.error();
  }
  if (Status s = q->Migrate(); !s) return s.error();
  return q;
}

// Columns added after the first release: a queue written by an older build
// gets them (the daemon and the worker may both open it first, so the check
// and the change are one write transaction).
Status JobQueue::Migrate() {
  if (Status s = Exec("BEGIN IMMEDIATE"); !s) return s;
  bool has_interruptions = false, has_kind = false;
  {
    Stmt info(db_, "PRAGMA table_info(jobs)");
    while (info.Step() == SQLITE_ROW) {
      if (info.Text(1) == "interruptions") has_interruptions = true;
      if (info.Text(1) == "kind") has_kind = true;
    }
  }
  if (!has_interruptions) {
    if (Status s = Exec("ALTER TABLE jobs ADD COLUMN interruptions INTEGER NOT NULL DEFAULT 0");
        !s) {
      (void)Exec("ROLLBACK");
      return s;
    }
  }
  // Jobs queued before calibration captures existed are all rocks.
  if (!has_kind) {
    if (Status s = Exec("ALTER TABLE jobs ADD COLUMN kind TEXT NOT NULL DEFAULT 'rock'"); !s) {
      (void)Exec("ROLLBACK");
      return s;
    }
  }
  if (Status s = Exec("COMMIT"); !s) {
    (void)Exec("ROLLBACK");
    return s;
  }
  return OkStatus();
}

JobQueue::~JobQueue() { sqlite3_close(db_); }

Status JobQueue::Exec(const char* sql) {
  char* msg = nullptr;
  if (sqlite3_exec(db_, sql, nullptr, nullptr, &msg) != SQLITE_OK) {
    Error e = DbError(db_, std::string("cannot run ") + sql);
    sqlite3_free(msg);
    return e;
  }
  return OkStatus();
}

Result<int64_t> JobQueue::Enqueue(const std::string& sample_id, int side, const std::string& kind) {
  Status s = Exec("BEGIN IMMEDIATE");
  if (!s) return s.error();
  {
    Stmt find(db_,
              "SELECT id FROM jobs WHERE sample_id=? AND side=? AND state IN ('queued','running')");
    find.Bind(1, sample_id);
    find.Bind(2, side);
    if (find.Step() == SQLITE_ROW) {
      const int64_t id = find.Int(0);
      if (Status c = Exec("COMMIT"); !c) {
        (void)Exec("ROLLBACK");  // never leave the transaction open: every later BEGIN would fail
        return c.error();
      }
      return id;
    }
  }
  const std::string now = NowUtcString();
  Stmt ins(db_,
           "INSERT INTO jobs(sample_id, side, state, created_utc, updated_utc, kind) "
           "VALUES(?,?,'queued',?,?,?)");
  ins.Bind(1, sample_id);
  ins.Bind(2, side);
  ins.Bind(3, now);
  ins.Bind(4, now);
  ins.Bind(5, kind);
  if (ins.Step() != SQLITE_DONE) {
    Error e = DbError(db_, "cannot queue job for sample " + sample_id);
    (void)Exec("ROLLBACK");
    return e;
  }
  const int64_t id = sqlite3_last_insert_rowid(db_);
  s = Exec("COMMIT");
  if (!s) {
    (void)Exec("ROLLBACK");
    return s.error();
  }
  return id;
}

Result<std::optional<Job>> JobQueue::ClaimNext() {
  Status s = Exec("BEGIN IMMEDIATE");
  if (!s) return s.error();
  std::optional<Job> job;
  {
    Stmt sel(db_, (std::string("SELECT ") + kJobColumns +
                   " FROM jobs WHERE state='queued' ORDER BY id LIMIT 1")
                      .c_str());
    if (sel.Step() == SQLITE_ROW) job = ReadJob(sel);
  }
  if (job) {
    Stmt upd(db_, "UPDATE jobs SET state='running', updated_utc=? WHERE id=?");
    upd.Bind(1, NowUtcString());
    upd.Bind(2, job->id);
    if (upd.Step() != SQLITE_DONE) {
      Error e = DbError(db_, "cannot claim job");
      (void)Exec("ROLLBACK");
      return e;
    }
    job->state = "running";
  }
  s = Exec("COMMIT");
  if (!s) {
    (void)Exec("ROLLBACK");
    return s.error();
  }
  return job;
}

Status JobQueue::Complete(int64_t job_id) {
  Stmt upd(db_,
           "UPDATE jobs SET state='done', error=NULL, interruptions=0, updated_utc=? WHERE id=?");
  upd.Bind(1, NowUtcString());
  upd.Bind(2, job_id);
  if (upd.Step() != SQLITE_DONE) return DbError(db_, "cannot complete job");
  if (sqlite3_changes(db_) != 1)
    return MakeError(ErrorClass::kNotFound, "job " + std::to_string(job_id) + " not found");
  return OkStatus();
}

Status JobQueue::Fail(int64_t job_id, const std::string& error, bool requeue) {
  Stmt upd(db_,
           "UPDATE jobs SET state=?, error=?, attempts=attempts+1, interruptions=0, updated_utc=? "
           "WHERE id=?");
  upd.Bind(1, std::string(requeue ? "queued" : "failed"));
  upd.Bind(2, error);
  upd.Bind(3, NowUtcString());
  upd.Bind(4, job_id);
  if (upd.Step() != SQLITE_DONE) return DbError(db_, "cannot mark job failed");
  if (sqlite3_changes(db_) != 1)
    return MakeError(ErrorClass::kNotFound, "job " + std::to_string(job_id) + " not found");
  return OkStatus();
}

Status JobQueue::Release(int64_t job_id) {
  Stmt upd(db_, "UPDATE jobs SET state='queued', updated_utc=? WHERE id=? AND state='running'");
  upd.Bind(1, NowUtcString());
  upd.Bind(2, job_id);
  if (upd.Step() != SQLITE_DONE) return DbError(db_, "cannot put job back in the queue");
  if (sqlite3_changes(db_) != 1)
    return MakeError(ErrorClass::kNotFound, "job " + std::to_string(job_id) + " is not running");
  return OkStatus();
}

Result<JobQueue::Requeued> JobQueue::RequeueRunning(int max_interruptions) {
  Status s = Exec("BEGIN IMMEDIATE");
  if (!s) return s.error();
  Requeued out;
  const std::string now = NowUtcString();
  auto rollback = [&](const std::string& what) {
    Error e = DbError(db_, what);
    (void)Exec("ROLLBACK");
    return e;
  };
  {
    Stmt inc(db_,
             "UPDATE jobs SET interruptions=interruptions+1, updated_utc=? WHERE state='running'");
    inc.Bind(1, now);
    if (inc.Step() != SQLITE_DONE) return rollback("cannot requeue running jobs");
  }
  {
    Stmt fail(db_,
              "UPDATE jobs SET state='failed', error='interrupted ' || interruptions || ' times in "
              "a row while "
              "running (the worker was killed or the machine lost power each time): out of memory "
              "or killed? "
              "Check the kernel log for the OOM killer (journalctl -k) and the worker log, then "
              "retry the "
              "sample', updated_utc=? WHERE state='running' AND interruptions>=?");
    fail.Bind(1, now);
    fail.Bind(2, static_cast<int64_t>(max_interruptions));
    if (fail.Step() != SQLITE_DONE) return rollback("cannot fail interrupted jobs");
    out.failed = sqlite3_changes(db_);
  }
  {
    Stmt upd(db_, "UPDATE jobs SET state='queued', updated_utc=? WHERE state='running'");
    upd.Bind(1, now);
    if (upd.Step() != SQLITE_DONE) return rollback("cannot requeue running jobs");
    out.requeued = sqlite3_changes(db_);
  }
  if (Status c = Exec("COMMIT"); !c) {
    (void)Exec("ROLLBACK");
    return c.error();
  }
  return out;
}

Result<int> JobQueue::Retry(const std::string& sample_id) {
  // A failed job with a live twin (queued or running) is left as it is: the
  // twin already does its work.
  Stmt upd(db_,
           "UPDATE jobs SET state='queued', attempts=0, interruptions=0, error=NULL, updated_utc=? "
           "WHERE sample_id=? AND state='failed' AND NOT EXISTS (SELECT 1 FROM jobs AS t WHERE "
           "t.sample_id=jobs.sample_id AND t.side=jobs.side AND t.state IN ('queued','running'))");
  upd.Bind(1, NowUtcString());
  upd.Bind(2, sample_id);
  if (upd.Step() != SQLITE_DONE)
    return DbError(db_, "cannot requeue the failed jobs of " + sample_id);
  const int n = sqlite3_changes(db_);
  if (n == 0) {
    return MakeError(ErrorClass::kNotFound,
                     "sample " + sample_id +
                         " has no failed job to retry (see its jobs with `aggscan show " +
                         sample_id + "`)");
  }
  return n;
}

Result<int> JobQueue::Depth() {
  Stmt sel(db_, "SELECT COUNT(*) FROM jobs WHERE state IN ('queued','running')");
  if (sel.Step() != SQLITE_ROW) return DbError(db_, "cannot count jobs");
  return static_cast<int>(sel.Int(0));
}

Result<std::vector<Job>> JobQueue::JobsForSample(const std::string& sample_id) {
  Stmt sel(
      db_,
      (std::string("SELECT ") + kJobColumns + " FROM jobs WHERE sample_id=? ORDER BY id").c_str());
  sel.Bind(1, sample_id);
  std::vector<Job> out;
  int rc;
  while ((rc = sel.Step()) == SQLITE_ROW) out.push_back(ReadJob(sel));
  if (rc != SQLITE_DONE) return DbError(db_, "cannot list jobs of " + sample_id);
  return out;
}

Result<std::vector<Job>> JobQueue::FailedJobs(int limit) {
  Stmt sel(db_, (std::string("SELECT ") + kJobColumns +
                 " FROM jobs WHERE state='failed' ORDER BY id DESC LIMIT ?")
                    .c_str());
  sel.Bind(1, static_cast<int64_t>(limit));
  std::vector<Job> out;
  int rc;
  while ((rc = sel.Step()) == SQLITE_ROW) out.push_back(ReadJob(sel));
  if (rc != SQLITE_DONE) return DbError(db_, "cannot list failed jobs");
  return out;
}

Result<int> JobQueue::FailedCount() {
  Stmt sel(db_, "SELECT COUNT(*) FROM jobs WHERE state='failed'");
  if (sel.Step() != SQLITE_ROW) return DbError(db_, "cannot count failed jobs");
  return static_cast<int>(sel.Int(0));
}

int64_t BootTimeNs() {
  timespec ts{};
  ::clock_gettime(CLOCK_BOOTTIME, &ts);
  return static_cast<int64_t>(ts.tv_sec) * kNsPerSec + ts.tv_nsec;
}

const std::string& BootId() {
  static const std::string id = [] {
    std::ifstream in("/proc/sys/kernel/random/boot_id");
    std::string s;
    std::getline(in, s);
    return s;
  }();
  return id;
}

Status JobQueue::ReportWorker(const WorkerReport& r) {
  // NORMAL in WAL mode: the commit is not synced, yet the database stays
  // consistent through a power cut. Back to FULL for the jobs' own changes.
  if (Status s = Exec("PRAGMA synchronous=NORMAL"); !s) return s;
  Stmt up(
      db_,
      "INSERT OR REPLACE INTO worker(id, pid, state, job_id, sample_id, side, stage, done, total,"
      " started_boot_ns, job_started_boot_ns, stage_since_boot_ns, boot_id, heard_boot_ns, "
      "heard_utc)"
      " VALUES(1,?,?,?,?,?,?,?,?,?,?,?,?,?,?)");
  up.Bind(1, r.pid);
  up.Bind(2, r.state);
  up.Bind(3, r.job_id);
  up.Bind(4, r.sample_id);
  up.Bind(5, static_cast<int64_t>(r.side));
  up.Bind(6, r.stage);
  up.Bind(7, static_cast<int64_t>(r.done));
  up.Bind(8, static_cast<int64_t>(r.total));
  up.Bind(9, r.started_boot_ns);
  up.Bind(10, r.job_started_boot_ns);
  up.Bind(11, r.stage_since_boot_ns);
  up.Bind(12, BootId());
  up.Bind(13, BootTimeNs());
  up.Bind(14, NowUtcString());
  std::optional<Error> failed;
  if (up.Step() != SQLITE_DONE) failed = DbError(db_, "cannot record the worker's report");
  Status back = Exec("PRAGMA synchronous=FULL");
  if (failed) return *failed;
  return back;
}

Result<std::optional<WorkerSeen>> JobQueue::Worker() {
  Stmt sel(db_,
           "SELECT pid, state, job_id, sample_id, side, stage, done, total, started_boot_ns,"
           " job_started_boot_ns, stage_since_boot_ns, boot_id, heard_boot_ns, heard_utc"
           " FROM worker WHERE id=1");
  const int rc = sel.Step();
  if (rc == SQLITE_DONE) return std::optional<WorkerSeen>();
  if (rc != SQLITE_ROW) return DbError(db_, "cannot read the worker's report");
  WorkerSeen w;
  WorkerReport& r = w.report;
  r.pid = sel.Int(0);
  r.state = sel.Text(1);
  r.job_id = sel.Int(2);
  r.sample_id = sel.Text(3);
  r.side = static_cast<int>(sel.Int(4));
  r.stage = sel.Text(5);
  r.done = static_cast<int>(sel.Int(6));
  r.total = static_cast<int>(sel.Int(7));
  r.started_boot_ns = sel.Int(8);
  r.job_started_boot_ns = sel.Int(9);
  r.stage_since_boot_ns = sel.Int(10);
  const std::string boot = sel.Text(11);
  const int64_t heard = sel.Int(12);
  w.heard_utc = sel.Text(13);
  const int64_t now = BootTimeNs();
  w.this_boot = !boot.empty() && boot == BootId() && heard <= now;
  if (w.this_boot) {
    auto secs = [now](int64_t t) {
      return t > 0 && t <= now ? static_cast<double>(now - t) / 1e9 : 0.0;
    };
    w.heard_s_ago = secs(heard);
    w.job_s = secs(r.job_started_boot_ns);
    w.stage_s = secs(r.stage_since_boot_ns);
    w.up_s = secs(r.started_boot_ns);
  }
  return std::optional<WorkerSeen>(std::move(w));
}

}  // namespace aggscan
