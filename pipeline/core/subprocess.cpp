#include "pipeline/core/subprocess.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <ctime>
#include <deque>
#include <fstream>
#include <thread>

namespace aggscan {
namespace {

using SteadyClock = std::chrono::steady_clock;

class UniqueFd {
 public:
  explicit UniqueFd(int fd = -1) : fd_(fd) {}
  ~UniqueFd() { reset(); }
  UniqueFd(const UniqueFd&) = delete;
  UniqueFd& operator=(const UniqueFd&) = delete;
  int get() const { return fd_; }
  void reset(int fd = -1) {
    if (fd_ >= 0) ::close(fd_);
    fd_ = fd;
  }

 private:
  int fd_;
};

// A started child process group; killed and reaped on destruction unless it
// has been reaped already, so no early return leaves a zombie or a runaway
// colmap behind.
class ChildProcess {
 public:
  explicit ChildProcess(pid_t pid) : pid_(pid) {}
  ~ChildProcess() {
    if (pid_ > 0) {
      ::kill(-pid_, SIGKILL);
      int st = 0;
      while (::waitpid(pid_, &st, 0) < 0 && errno == EINTR) {
      }
    }
  }
  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  // Non-blocking reap: true when the child has exited (status filled in).
  bool TryReap(int* status) {
    pid_t r = ::waitpid(pid_, status, WNOHANG);
    if (r == pid_) {
      pid_ = -1;
      return true;
    }
    return false;
  }
  // SIGTERM to the group, SIGKILL after `grace_s`, then reap.
  void Kill(double grace_s, int* status) {
    ::kill(-pid_, SIGTERM);
    const auto deadline = SteadyClock::now() + std::chrono::duration<double>(grace_s);
    while (SteadyClock::now() < deadline) {
      if (TryReap(status)) return;
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    ::kill(-pid_, SIGKILL);
    while (::waitpid(pid_, status, 0) < 0 && errno == EINTR) {
    }
    pid_ = -1;
  }

 private:
  pid_t pid_;
};

std::string JoinArgv(const std::vector<std::string>& argv) {
  std::string s;
  for (const auto& a : argv) {
    if (!s.empty()) s += ' ';
    const bool quote = a.empty() || a.find_first_of(" \t\"'\\$") != std::string::npos;
    s += quote ? "'" + a + "'" : a;
  }
  return s;
}

std::string UtcNow() {
  std::time_t t = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&t, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

void WriteAll(int fd, const std::string& s) {
  size_t off = 0;
  while (off < s.size()) {
    ssize_t n = ::write(fd, s.data() + off, s.size() - off);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return;
    off += static_cast<size_t>(n);
  }
}

}  // namespace

std::string SubprocessResult::Describe() const {
  if (term_signal != 0) {
    return "killed by signal " + std::to_string(term_signal) + " (" + ::strsignal(term_signal) +
           ")";
  }
  return "exit " + std::to_string(exit_code);
}

Result<SubprocessResult> RunSubprocess(const std::vector<std::string>& argv,
                                       const SubprocessOptions& opts) {
  if (argv.empty() || argv[0].empty())
    return MakeError(ErrorClass::kInvalidArgument, "no program to run");

  // Everything the child needs is prepared before fork(): after it, only
  // async-signal-safe calls.
  std::vector<char*> cargv;
  cargv.reserve(argv.size() + 1);
  for (const auto& a : argv) cargv.push_back(const_cast<char*>(a.c_str()));
  cargv.push_back(nullptr);

  UniqueFd log_fd(::open(opts.log_path.empty() ? "/dev/null" : opts.log_path.c_str(),
                         O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644));
  if (log_fd.get() < 0) return ErrnoError("cannot open log file " + opts.log_path, errno);
  UniqueFd null_fd(::open("/dev/null", O_RDONLY | O_CLOEXEC));
  if (null_fd.get() < 0) return ErrnoError("cannot open /dev/null", errno);
  WriteAll(log_fd.get(), "==== " + UtcNow() + " $ " + JoinArgv(argv) + "\n");

  // exec failure is reported through a close-on-exec pipe: EOF means exec worked.
  int pfd[2];
  if (::pipe2(pfd, O_CLOEXEC) != 0) return ErrnoError("cannot create pipe", errno);
  UniqueFd err_r(pfd[0]), err_w(pfd[1]);

  const pid_t parent = ::getpid();
  const auto t0 = SteadyClock::now();
  const pid_t pid = ::fork();
  if (pid < 0) return ErrnoError("cannot fork to run " + argv[0], errno);
  if (pid == 0) {
    ::setpgid(0, 0);
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (::getppid() != parent) ::_exit(127);  // parent died before prctl
    sigset_t none;
    sigemptyset(&none);
    ::sigprocmask(SIG_SETMASK, &none, nullptr);
    ::signal(SIGPIPE, SIG_DFL);
    int err = 0;
    if (::dup2(null_fd.get(), 0) < 0 || ::dup2(log_fd.get(), 1) < 0 || ::dup2(log_fd.get(), 2) < 0)
      err = errno;
    if (err == 0 && !opts.working_dir.empty() && ::chdir(opts.working_dir.c_str()) != 0)
      err = errno;
    if (err == 0) {
      ::execvp(cargv[0], cargv.data());
      err = errno;
    }
    ssize_t ignored = ::write(err_w.get(), &err, sizeof err);
    (void)ignored;
    ::_exit(127);
  }
  ::setpgid(pid, pid);  // also here: no race with kill(-pid) below
  ChildProcess child(pid);
  err_w.reset();

  int exec_errno = 0;
  ssize_t n;
  while ((n = ::read(err_r.get(), &exec_errno, sizeof exec_errno)) < 0 && errno == EINTR) {
  }
  if (n == static_cast<ssize_t>(sizeof exec_errno)) {
    int st = 0;
    child.Kill(0, &st);
    const bool missing = exec_errno == ENOENT || exec_errno == EACCES || exec_errno == ENOTDIR;
    std::string msg = "cannot run " + argv[0];
    WriteAll(log_fd.get(), msg + ": " + std::strerror(exec_errno) + "\n");
    return MakeError(missing ? ErrorClass::kNotFound : ErrorClass::kIo, msg,
                     std::strerror(exec_errno));
  }

  const bool has_deadline = opts.timeout_s > 0;
  const auto deadline = t0 + std::chrono::duration<double>(opts.timeout_s);
  int status = 0;
  for (;;) {
    if (child.TryReap(&status)) break;
    if (opts.cancel && opts.cancel->load()) {
      child.Kill(opts.kill_grace_s, &status);
      WriteAll(log_fd.get(), "==== cancelled: killed\n");
      return MakeError(ErrorClass::kCancelled, "interrupted",
                       argv[0] + " was cancelled and killed");
    }
    if (has_deadline && SteadyClock::now() >= deadline) {
      child.Kill(opts.kill_grace_s, &status);
      WriteAll(log_fd.get(), "==== timed out: killed\n");
      char limit[32];
      std::snprintf(limit, sizeof limit, "%.0f s", opts.timeout_s);
      return MakeError(ErrorClass::kTimeout,
                       argv[0] + " ran longer than " + limit + " and was killed",
                       "log: " + opts.log_path);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  SubprocessResult r;
  r.wall_s = std::chrono::duration<double>(SteadyClock::now() - t0).count();
  if (WIFEXITED(status)) r.exit_code = WEXITSTATUS(status);
  if (WIFSIGNALED(status)) r.term_signal = WTERMSIG(status);
  char tail[96];
  std::snprintf(tail, sizeof tail, "==== %s after %.1f s\n", r.Describe().c_str(), r.wall_s);
  WriteAll(log_fd.get(), tail);
  return r;
}

std::string TailOfFile(const std::string& path, int max_lines) {
  std::ifstream f(path);
  if (!f) return {};
  std::deque<std::string> lines;
  std::string line;
  while (std::getline(f, line)) {
    if (line.empty()) continue;
    lines.push_back(std::move(line));
    if (static_cast<int>(lines.size()) > max_lines) lines.pop_front();
  }
  std::string out;
  for (const auto& l : lines) {
    if (!out.empty()) out += '\n';
    out += l;
  }
  return out;
}

}  // namespace aggscan
