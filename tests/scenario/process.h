// Runs the real aggscand / aggscan-worker binaries for scenario tests.
#pragma once

#include <httplib.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "tests/util/temp_dir.h"

namespace aggscan::test {

inline std::string Bin(const std::string& rel) {
  return std::string(AGGSCAN_BINARY_DIR) + "/" + rel;
}

/// Starts a program with arguments; stdout+stderr go to `log`.
inline pid_t Spawn(const std::vector<std::string>& argv, const std::string& log) {
  pid_t pid = ::fork();
  if (pid == 0) {
    FILE* f = std::fopen(log.c_str(), "a");
    if (f) {
      ::dup2(fileno(f), 1);
      ::dup2(fileno(f), 2);
    }
    std::vector<char*> a;
    for (const auto& s : argv) a.push_back(const_cast<char*>(s.c_str()));
    a.push_back(nullptr);
    ::execv(a[0], a.data());
    _exit(127);
  }
  return pid;
}

/// Waits for exit; returns the exit code, or 128+signal.
inline int WaitExit(pid_t pid) {
  int st = 0;
  ::waitpid(pid, &st, 0);
  if (WIFEXITED(st)) return WEXITSTATUS(st);
  if (WIFSIGNALED(st)) return 128 + WTERMSIG(st);
  return -1;
}

inline std::string ReadAll(const std::string& p) {
  std::ifstream f(p);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

/// A running aggscand on an ephemeral port.
class Daemon {
 public:
  /// Waits up to `start_s` for the API port (longer under a VM's TCG).
  Daemon(const std::string& config, const std::string& dir, double start_s = 5) : dir_(dir) {
    port_file_ = dir + "/port";
    std::filesystem::remove(port_file_);
    log_ = dir + "/aggscand.log";
    pid_ = Spawn(
        {Bin("daemon/aggscand"), "--config", config, "--port", "0", "--port-file", port_file_},
        log_);
    for (int i = 0; i < start_s * 100 && port_ == 0; ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
      std::string p = ReadAll(port_file_);
      if (!p.empty()) port_ = std::atoi(p.c_str());
      int st;
      if (::waitpid(pid_, &st, WNOHANG) == pid_) {
        pid_ = -1;
        break;
      }
    }
  }
  ~Daemon() { Stop(); }
  bool ok() const { return port_ > 0 && pid_ > 0; }
  int port() const { return port_; }
  pid_t pid() const { return pid_; }
  const std::string& log() const { return log_; }
  void Kill(int sig) {
    if (pid_ > 0) {
      ::kill(pid_, sig);
      exit_code_ = WaitExit(pid_);
      pid_ = -1;
    }
  }
  int Stop() {
    Kill(SIGTERM);
    return exit_code_;
  }

  nlohmann::json Get(const std::string& path, int* status = nullptr) {
    httplib::Client c("127.0.0.1", port_);
    c.set_read_timeout(15, 0);
    auto r = c.Get(path.c_str());
    if (status) *status = r ? r->status : 0;
    if (!r) return nullptr;
    auto j = nlohmann::json::parse(r->body, nullptr, false);
    return j.is_discarded() ? nlohmann::json(r->body) : j;
  }
  nlohmann::json Post(const std::string& path, const std::string& body = "{}",
                      int* status = nullptr) {
    httplib::Client c("127.0.0.1", port_);
    c.set_read_timeout(15, 0);
    auto r = c.Post(path.c_str(), body, "application/json");
    if (status) *status = r ? r->status : 0;
    if (!r) return nullptr;
    auto j = nlohmann::json::parse(r->body, nullptr, false);
    return j.is_discarded() ? nlohmann::json(r->body) : j;
  }
  /// Polls status until `pred` holds or `seconds` pass.
  template <typename P>
  bool WaitFor(P pred, double seconds, nlohmann::json* last = nullptr) {
    const auto end = std::chrono::steady_clock::now() +
                     std::chrono::milliseconds(static_cast<int>(seconds * 1000));
    while (std::chrono::steady_clock::now() < end) {
      nlohmann::json s = Get("/api/v1/status");
      if (last) *last = s;
      if (!s.is_null() && pred(s)) return true;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return false;
  }

 private:
  std::string dir_, port_file_, log_;
  pid_t pid_ = -1;
  int port_ = 0;
  int exit_code_ = -1;
};

/// A sim-rig config for tests: small frames, fast clock.
inline std::string WriteConfig(const std::string& dir, const std::string& extra = "",
                               double time_scale = 20, const std::string& capture = "") {
  const std::string path = dir + "/test.toml";
  std::ofstream f(path);
  f << "[daemon]\nstate_dir = \"" << dir << "/state\"\nlisten_port = 0\ntime_scale = " << time_scale
    << "\nlog_level = \"info\"\n\n"
    << "[capture]\n"
    << capture << "\n"
    << "[camera]\nwidth = 640\nheight = 480\n\n"
    << extra;
  return path;
}

}  // namespace aggscan::test
