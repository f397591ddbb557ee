#include "common/log.h"

#include <atomic>
#include <cstdio>
#include <vector>

namespace aggscan {

static std::atomic<int> g_level{static_cast<int>(LogLevel::kInfo)};
static std::mutex g_write_mu;

void SetLogLevel(LogLevel level) { g_level = static_cast<int>(level); }
LogLevel GetLogLevel() { return static_cast<LogLevel>(g_level.load()); }

bool ParseLogLevel(const std::string& s, LogLevel* out) {
  static const std::pair<const char*, LogLevel> kNames[] = {{"error", LogLevel::kError},
                                                            {"warning", LogLevel::kWarning},
                                                            {"notice", LogLevel::kNotice},
                                                            {"info", LogLevel::kInfo},
                                                            {"debug", LogLevel::kDebug}};
  for (const auto& [name, lvl] : kNames) {
    if (s == name) {
      *out = lvl;
      return true;
    }
  }
  return false;
}

void LogLine(LogLevel level, const char* category, const std::string& sample,
             const std::string& text) {
  if (static_cast<int>(level) > g_level.load()) return;
  // Appended piecewise (also avoids a GCC 12 -Wrestrict false positive on
  // "literal" + std::string at -O2).
  std::string line;
  line.reserve(text.size() + sample.size() + 32);
  line += '<';
  line += std::to_string(static_cast<int>(level));
  line += '>';
  line += category;
  line += ": ";
  if (!sample.empty()) {
    line += '[';
    line += sample;
    line += "] ";
  }
  line += text;
  line += '\n';
  std::lock_guard<std::mutex> lock(g_write_mu);
  std::fwrite(line.data(), 1, line.size(), stderr);
}

void Logf(LogLevel level, const char* category, const char* fmt, ...) {
  if (static_cast<int>(level) > g_level.load()) return;
  va_list ap;
  va_start(ap, fmt);
  va_list ap2;
  va_copy(ap2, ap);
  const int n = std::vsnprintf(nullptr, 0, fmt, ap);
  va_end(ap);
  std::vector<char> buf(n > 0 ? static_cast<size_t>(n) + 1 : 1);
  std::vsnprintf(buf.data(), buf.size(), fmt, ap2);
  va_end(ap2);
  LogLine(level, category, {}, buf.data());
}

bool RateLimitedLog::Error(const std::string& key, const std::string& text) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = suppressed_.find(key);
  if (it != suppressed_.end()) {
    ++it->second;
    return false;
  }
  suppressed_[key] = 0;
  LogLine(LogLevel::kError, category_, {},
          text + " (further errors of this kind suppressed until it recovers)");
  return true;
}

void RateLimitedLog::Clear(const std::string& key, const std::string& recovered_text) {
  std::lock_guard<std::mutex> lock(mu_);
  auto it = suppressed_.find(key);
  if (it == suppressed_.end()) return;
  LogLine(LogLevel::kNotice, category_, {},
          recovered_text + " (" + std::to_string(it->second) + " repeats suppressed)");
  suppressed_.erase(it);
}

void RateLimitedLog::ClearPrefix(const std::string& prefix, const std::string& recovered_text) {
  std::lock_guard<std::mutex> lock(mu_);
  long total = 0;
  bool any = false;
  for (auto it = suppressed_.lower_bound(prefix);
       it != suppressed_.end() && it->first.rfind(prefix, 0) == 0;) {
    any = true;
    total += it->second;
    it = suppressed_.erase(it);
  }
  if (!any) return;
  LogLine(LogLevel::kNotice, category_, {},
          recovered_text + " (" + std::to_string(total) + " repeats suppressed)");
}

}  // namespace aggscan
