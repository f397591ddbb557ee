#include "daemon/report_maker.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cctype>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <thread>
#include <vector>

#include "common/fsutil.h"
#include "store/layout.h"

namespace aggscan {

namespace {

// Below the capture daemon, as the worker runs ([worker] nice's default):
// a report made during a capture must not make the turntable late.
constexpr int kNice = 10;

bool IsPlainName(const std::string& s) {
  if (s.empty() || s.size() > 64 || s[0] == '.' || s[0] == '-') return false;
  for (const char c : s) {
    if (!std::isalnum(static_cast<unsigned char>(c)) && c != '-' && c != '_' && c != '.')
      return false;
  }
  return true;
}

}  // namespace

std::string ReportMaker::CliPath() {
  if (const char* e = std::getenv("AGGSCAN_CLI"); e != nullptr && *e != '\0') return e;
  const std::string dir = ExecutableDir();
  for (const std::string& p : {dir + "/aggscan", dir + "/../cli/aggscan"}) {
    if (::access(p.c_str(), X_OK) == 0) return p;
  }
  return dir + "/aggscan";
}

Result<std::string> ReportMaker::Make(const ReportRequest& r, double timeout_s) {
  if (r.kind != "rock" && r.kind != "batch")
    return MakeError(ErrorClass::kInvalidArgument, "a report is of a rock or of a batch");
  if (r.format != "pdf" && r.format != "html")
    return MakeError(ErrorClass::kInvalidArgument, "a report is report.pdf or report.html");
  if (!layout::IsValidSampleId(r.name))
    return MakeError(ErrorClass::kInvalidArgument, "invalid name \"" + r.name + "\"");
  // Over the network only a shipped specification: never a path on the rig.
  if (!r.spec.empty() && !IsPlainName(r.spec)) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "spec must name a shipped specification (e.g. en13383-lma10-60, "
                     "fp14-class1), not a path");
  }
  if (!r.spec.empty() && r.kind != "batch")
    return MakeError(ErrorClass::kInvalidArgument, "spec checks a batch's gradation");
  std::unique_lock<std::mutex> lock(busy_, std::try_to_lock);
  if (!lock.owns_lock()) {
    return MakeError(ErrorClass::kConflict,
                     "another report is being made (one at a time on the rig): retry in a few "
                     "seconds");
  }
  char tmpl[] = "/tmp/aggscan-api-report-XXXXXX";
  if (::mkdtemp(tmpl) == nullptr) {
    return MakeError(ErrorClass::kIo, std::string("cannot make a temporary folder in /tmp: ") +
                                          std::strerror(errno));
  }
  const std::string dir = tmpl;
  const std::string out = dir + "/report." + r.format;
  const std::string log = dir + "/log.txt";
  std::vector<std::string> args = {CliPath(), "report"};
  if (r.kind == "batch") {
    args.insert(args.end(), {"--batch", r.name});
  } else {
    args.push_back(r.name);
  }
  args.insert(args.end(), {"--state-dir", state_dir_, "--" + r.format, out});
  if (!r.spec.empty()) args.insert(args.end(), {"--spec", r.spec});
  std::vector<char*> argv;
  argv.reserve(args.size() + 1);
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);

  const auto cleanup = [&dir, &log] {
    ::unlink(log.c_str());
    ::rmdir(dir.c_str());
  };
  const int log_fd = ::open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
  if (log_fd < 0) {
    cleanup();
    return MakeError(ErrorClass::kIo, "cannot open " + log + ": " + std::strerror(errno));
  }
  const pid_t pid = ::fork();
  if (pid == 0) {
    // Only async-signal-safe calls between fork and exec (the daemon has threads).
    ::setpriority(PRIO_PROCESS, 0, kNice);
    ::dup2(log_fd, STDOUT_FILENO);
    ::dup2(log_fd, STDERR_FILENO);
    const int devnull = ::open("/dev/null", O_RDONLY);
    if (devnull >= 0) ::dup2(devnull, STDIN_FILENO);
    ::execv(argv[0], argv.data());
    ::_exit(127);
  }
  ::close(log_fd);
  if (pid < 0) {
    cleanup();
    return MakeError(ErrorClass::kIo,
                     std::string("cannot start a process: ") + std::strerror(errno));
  }
  const auto until = std::chrono::steady_clock::now() +
                     std::chrono::milliseconds(static_cast<int64_t>(timeout_s * 1000));
  int status = 0;
  bool timed_out = false;
  while (true) {
    const pid_t w = ::waitpid(pid, &status, WNOHANG);
    if (w == pid || (w < 0 && errno != EINTR)) break;
    if (std::chrono::steady_clock::now() > until) {
      ::kill(pid, SIGKILL);
      ::waitpid(pid, &status, 0);
      timed_out = true;
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  Result<std::string> said = ReadFile(log);
  std::string message = said ? *said : std::string();
  while (!message.empty() && (message.back() == '\n' || message.back() == ' ')) message.pop_back();
  if (message.size() > 2000) message = "..." + message.substr(message.size() - 2000);
  if (timed_out || !WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    ::unlink(out.c_str());
    cleanup();
    if (timed_out) {
      return MakeError(ErrorClass::kTimeout, "the report took longer than " +
                                                 std::to_string(static_cast<int>(timeout_s)) +
                                                 " s and was stopped");
    }
    const int code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    if (code == 127) {
      return MakeError(ErrorClass::kInternal,
                       "cannot run " + args[0] + " (set AGGSCAN_CLI to the aggscan program)");
    }
    if (code == 3) return MakeError(ErrorClass::kInternal, message);  // a library is missing
    const bool unknown = message.find("no sample ") != std::string::npos ||
                         message.find("no batch ") != std::string::npos;
    return MakeError(unknown ? ErrorClass::kNotFound : ErrorClass::kInvalidState, message);
  }
  ::unlink(log.c_str());
  return out;  // the caller removes it and its folder
}

}  // namespace aggscan
