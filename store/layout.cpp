#include "store/layout.h"

#include <cstdio>
#include <filesystem>

namespace aggscan::layout {

std::string ViewStem(int view) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "view_%03d", view);
  return buf;
}

bool IsValidSampleId(const std::string& id) {
  if (id.empty() || id.size() > 64) return false;
  if (id[0] == '.' || id[0] == '-') return false;
  for (char c : id) {
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                    c == '.' || c == '_' || c == '-';
    if (!ok) return false;
  }
  return true;
}

std::string StateDirOfSample(const std::string& sample_dir) {
  const std::filesystem::path parent =
      std::filesystem::absolute(sample_dir).lexically_normal().parent_path();
  return parent.filename() == kSamplesCollection || parent.filename() == kCalibrationCollection
             ? parent.parent_path().string()
             : std::string();
}

std::string SampleIdOfDir(const std::string& sample_dir) {
  std::filesystem::path p = std::filesystem::path(sample_dir).lexically_normal();
  if (p.filename().empty()) p = p.parent_path();
  return p.filename().string();
}

}  // namespace aggscan::layout
