// Shared helpers of the libFuzzer targets: a scratch directory per process
// (under TMPDIR, removed at exit) and plain file writes into it. Files are
// written without fsync: nothing here needs to survive a crash, and the
// durable writes of the code under test are what is exercised, not these.
#pragma once

#include <fcntl.h>
#include <unistd.h>

#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

namespace aggscan::fuzz {

/// A fresh directory for this process, created on first use.
inline const std::string& ScratchDir() {
  static const std::string dir = [] {
    const char* tmp = std::getenv("TMPDIR");
    std::string templ = std::string(tmp && *tmp ? tmp : "/tmp") + "/aggscan-fuzz-XXXXXX";
    if (!::mkdtemp(templ.data())) std::abort();
    static struct Cleanup {
      std::string d;
      ~Cleanup() {
        std::error_code ec;
        std::filesystem::remove_all(d, ec);
      }
    } cleanup{templ};
    return templ;
  }();
  return dir;
}

/// Replaces `path` with `data` (directories above it are created).
inline void WriteFile(const std::string& path, std::string_view data) {
  std::error_code ec;
  std::filesystem::create_directories(std::filesystem::path(path).parent_path(), ec);
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) std::abort();
  size_t done = 0;
  while (done < data.size()) {
    const ssize_t n = ::write(fd, data.data() + done, data.size() - done);
    if (n <= 0) std::abort();
    done += static_cast<size_t>(n);
  }
  ::close(fd);
}

/// Empties `dir` (and creates it).
inline void ResetDir(const std::string& dir) {
  std::error_code ec;
  std::filesystem::remove_all(dir, ec);
  std::filesystem::create_directories(dir, ec);
}

inline std::string_view AsView(const uint8_t* data, size_t size) {
  return {reinterpret_cast<const char*>(data), size};
}

/// Splits a fuzz input at `sep` into at most `n` parts (the rest stays in the
/// last one): targets that need several files take them from one input.
inline std::vector<std::string_view> SplitInput(std::string_view in, std::string_view sep,
                                                size_t n) {
  std::vector<std::string_view> parts;
  while (parts.size() + 1 < n) {
    const size_t at = in.find(sep);
    if (at == std::string_view::npos) break;
    parts.push_back(in.substr(0, at));
    in.remove_prefix(at + sep.size());
  }
  parts.push_back(in);
  return parts;
}

}  // namespace aggscan::fuzz
