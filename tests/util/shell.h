// Runs a shell command in a test: its exit status, stdout and stderr together
// in *output.
#pragma once

#include <sys/wait.h>

#include <cstdio>
#include <string>

namespace aggscan::test {

inline int Shell(const std::string& cmd, std::string* output) {
  output->clear();
  FILE* p = ::popen((cmd + " 2>&1").c_str(), "r");
  if (!p) return -1;
  char buf[4096];
  size_t n;
  while ((n = std::fread(buf, 1, sizeof buf, p)) > 0) output->append(buf, n);
  const int st = ::pclose(p);
  return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

}  // namespace aggscan::test
