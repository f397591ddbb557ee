#include "store/layout.h"

#include <cstdio>

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
    const bool ok = (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '.' ||
                    c == '_' || c == '-';
    if (!ok) return false;
  }
  return true;
}

}  // namespace aggscan::layout
