#include "pipeline/core/subprocess.h"

#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <fstream>
#include <thread>

#include "common/fsutil.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

using Clock = std::chrono::steady_clock;

std::string Slurp(const std::string& path) {
  auto r = ReadFile(path);
  return r ? *r : std::string();
}

TEST(Subprocess, CapturesStdoutStderrAndExitCode) {
  test::TempDir tmp;
  SubprocessOptions o;
  o.log_path = tmp.path() + "/run.log";
  auto r = RunSubprocess({"/bin/sh", "-c", "echo to-stdout; echo to-stderr >&2; exit 3"}, o);
  ASSERT_TRUE(r.ok()) << r.error().ToString();
  EXPECT_EQ(r->exit_code, 3);
  EXPECT_EQ(r->term_signal, 0);
  EXPECT_FALSE(r->Succeeded());
  EXPECT_EQ(r->Describe(), "exit 3");
  const std::string log = Slurp(o.log_path);
  EXPECT_NE(log.find("to-stdout"), std::string::npos);
  EXPECT_NE(log.find("to-stderr"), std::string::npos);
  EXPECT_NE(log.find("/bin/sh"), std::string::npos) << "command line recorded in the log";
  EXPECT_EQ(TailOfFile(o.log_path, 1).rfind("==== exit 3 after ", 0), 0u)
      << TailOfFile(o.log_path, 1);
}

TEST(Subprocess, ArgumentsReachTheProgramVerbatim) {
  test::TempDir tmp;
  SubprocessOptions o;
  o.log_path = tmp.path() + "/run.log";
  auto r = RunSubprocess({"/bin/echo", "a b", "$HOME", "*", "it's"}, o);
  ASSERT_TRUE(r.ok());
  EXPECT_TRUE(r->Succeeded());
  EXPECT_NE(Slurp(o.log_path).find("\na b $HOME * it's\n"), std::string::npos) << Slurp(o.log_path);
}

TEST(Subprocess, WorkingDirectory) {
  test::TempDir tmp;
  SubprocessOptions o;
  o.log_path = tmp.path() + "/run.log";
  o.working_dir = tmp.path();
  auto r = RunSubprocess({"/bin/sh", "-c", "echo x > here.txt"}, o);
  ASSERT_TRUE(r.ok());
  EXPECT_TRUE(PathExists(tmp.path() + "/here.txt"));
}

TEST(Subprocess, MissingProgramIsNotFound) {
  test::TempDir tmp;
  SubprocessOptions o;
  o.log_path = tmp.path() + "/run.log";
  auto r = RunSubprocess({tmp.path() + "/no-such-colmap", "help"}, o);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kNotFound);
  EXPECT_NE(r.error().message.find("no-such-colmap"), std::string::npos);
  auto r2 = RunSubprocess({"no-such-program-in-path-xyz"}, o);
  ASSERT_FALSE(r2.ok());
  EXPECT_EQ(r2.error().cls, ErrorClass::kNotFound);
  auto r3 = RunSubprocess({}, o);
  ASSERT_FALSE(r3.ok());
  EXPECT_EQ(r3.error().cls, ErrorClass::kInvalidArgument);
}

TEST(Subprocess, SignalIsReported) {
  auto r = RunSubprocess({"/bin/sh", "-c", "kill -9 $$"});
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->term_signal, SIGKILL);
  EXPECT_EQ(r->exit_code, -1);
  EXPECT_NE(r->Describe().find("signal 9"), std::string::npos);
}

// The timeout kills the whole process group, grandchildren included.
TEST(Subprocess, TimeoutKillsTheProcessGroup) {
  test::TempDir tmp;
  SubprocessOptions o;
  o.log_path = tmp.path() + "/run.log";
  o.timeout_s = 0.5;
  o.kill_grace_s = 0.5;
  const std::string pidfile = tmp.path() + "/grandchild.pid";
  const auto t0 = Clock::now();
  auto r = RunSubprocess({"/bin/sh", "-c", "sleep 30 & echo $! > " + pidfile + "; wait"}, o);
  const double dt = std::chrono::duration<double>(Clock::now() - t0).count();
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kTimeout);
  EXPECT_LT(dt, 5.0);
  EXPECT_NE(Slurp(o.log_path).find("timed out"), std::string::npos);
  const pid_t gc = std::atoi(Slurp(pidfile).c_str());
  ASSERT_GT(gc, 0);
  // Gone, or a zombie waiting for a reaper that is not us.
  bool alive = false;
  for (int i = 0; i < 50; ++i) {
    std::ifstream stat("/proc/" + std::to_string(gc) + "/stat");
    std::string pid, comm, state;
    alive = static_cast<bool>(stat >> pid >> comm >> state) && state != "Z";
    if (!alive) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_FALSE(alive) << "grandchild " << gc << " survived the timeout";
}

TEST(Subprocess, CancelKillsAndReportsInterrupted) {
  std::atomic<bool> cancel{false};
  SubprocessOptions o;
  o.cancel = &cancel;
  std::thread t([&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    cancel = true;
  });
  const auto t0 = Clock::now();
  auto r = RunSubprocess({"/bin/sleep", "30"}, o);
  t.join();
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kCancelled);
  EXPECT_EQ(r.error().message, "interrupted");
  EXPECT_LT(std::chrono::duration<double>(Clock::now() - t0).count(), 5.0);
}

TEST(Subprocess, UnwritableLogIsAnError) {
  SubprocessOptions o;
  o.log_path = "/nonexistent-dir/x.log";
  auto r = RunSubprocess({"/bin/true"}, o);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(r.error().message.find("log file"), std::string::npos);
}

}  // namespace
}  // namespace aggscan
