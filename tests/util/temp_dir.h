// A fresh directory under /tmp for one test, removed afterwards
// (kept when AGGSCAN_KEEP_TMP is set, for debugging).
#pragma once

#include <stdlib.h>

#include <cstdlib>
#include <filesystem>
#include <string>

namespace aggscan::test {

class TempDir {
 public:
  TempDir() {
    char tmpl[] = "/tmp/aggscan-test-XXXXXX";
    path_ = ::mkdtemp(tmpl);
  }
  ~TempDir() {
    if (!std::getenv("AGGSCAN_KEEP_TMP")) std::filesystem::remove_all(path_);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  const std::string& path() const { return path_; }

 private:
  std::string path_;
};

}  // namespace aggscan::test
