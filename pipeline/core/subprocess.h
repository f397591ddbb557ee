// Runs an external program (COLMAP) as a child process: fork/exec with an
// argument vector (no shell, nothing is re-parsed), stdin from /dev/null,
// stdout and stderr appended to one log file, a wall-clock timeout and
// cancellation that kill the child's whole process group.
//
// The child runs in its own process group and gets SIGKILL if the calling
// thread dies (PR_SET_PDEATHSIG), so a crashed worker leaves no colmap behind.
#pragma once

#include <atomic>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan {

struct SubprocessOptions {
  std::string log_path;     // stdout + stderr appended here (created 0644); empty: /dev/null
  std::string working_dir;  // chdir() before exec; empty: inherit
  double timeout_s = 0;     // wall-clock limit; 0: none. On expiry: SIGTERM, then SIGKILL
  double kill_grace_s = 2;  // seconds between SIGTERM and SIGKILL
  const std::atomic<bool>* cancel = nullptr;  // polled every ~20 ms; set: the child is killed
};

struct SubprocessResult {
  int exit_code = -1;  // exit status when the child exited, else -1
  int term_signal =
      0;  // signal that ended the child (SIGSEGV, SIGKILL by the OOM killer ...), else 0
  double wall_s = 0;  // seconds from fork to reaping
  bool Succeeded() const { return exit_code == 0 && term_signal == 0; }
  /// "exit 3", "killed by signal 9 (Killed)".
  std::string Describe() const;
};

/// Runs argv[0] (a path, or a name looked up in PATH) with argv and waits.
/// Returns the exit status even when it is not 0: the caller decides what a
/// failure means. Errors: kInvalidArgument (empty argv), kNotFound (the program
/// does not exist or is not executable; detail: exec's errno text), kIo (log
/// file, fork), kTimeout (ran past timeout_s; killed), kCancelled with
/// message "interrupted" (cancelled; killed).
Result<SubprocessResult> RunSubprocess(const std::vector<std::string>& argv,
                                       const SubprocessOptions& opts = {});

/// The last `max_lines` lines of a text file (for error details); empty on error.
std::string TailOfFile(const std::string& path, int max_lines = 8);

}  // namespace aggscan
