// Logging to stderr in the form journald understands: "<prio>category: [sample] text".
// Every line carries a category; lines of a capture or reconstruction run carry
// the sample id. Repeated device errors go through RateLimitedLog, which logs
// once per error class and then a summary of how many were suppressed.
#pragma once

#include <cstdarg>
#include <map>
#include <mutex>
#include <string>

#include "common/clock.h"

namespace aggscan {

enum class LogLevel { kError = 3, kWarning = 4, kNotice = 5, kInfo = 6, kDebug = 7 };

/// Minimum level printed (default kInfo). Thread-safe.
void SetLogLevel(LogLevel level);
LogLevel GetLogLevel();
/// Parses "error|warning|notice|info|debug"; returns false if unknown.
bool ParseLogLevel(const std::string& s, LogLevel* out);

/// Writes one line. `sample` may be empty.
void LogLine(LogLevel level, const char* category, const std::string& sample,
             const std::string& text);
/// printf-style convenience.
void Logf(LogLevel level, const char* category, const char* fmt, ...)
    __attribute__((format(printf, 3, 4)));

#define AGG_LOGE(cat, ...) ::aggscan::Logf(::aggscan::LogLevel::kError, cat, __VA_ARGS__)
#define AGG_LOGW(cat, ...) ::aggscan::Logf(::aggscan::LogLevel::kWarning, cat, __VA_ARGS__)
#define AGG_LOGI(cat, ...) ::aggscan::Logf(::aggscan::LogLevel::kInfo, cat, __VA_ARGS__)
#define AGG_LOGD(cat, ...) ::aggscan::Logf(::aggscan::LogLevel::kDebug, cat, __VA_ARGS__)

/// Logs an error once per key (e.g. device + error class) until Clear(key) is
/// called (the device recovered); counts the suppressed repeats and reports
/// them on Clear.
class RateLimitedLog {
 public:
  explicit RateLimitedLog(const char* category) : category_(category) {}
  /// Returns true if the line was printed.
  bool Error(const std::string& key, const std::string& text);
  /// Marks key as recovered; prints how many repeats were suppressed.
  void Clear(const std::string& key, const std::string& recovered_text);
  /// Clears every key starting with `prefix` (a device's error classes) and,
  /// if any was logged, prints `recovered_text` once with the total suppressed.
  void ClearPrefix(const std::string& prefix, const std::string& recovered_text);

 private:
  const char* category_;
  std::mutex mu_;
  std::map<std::string, long> suppressed_;
};

}  // namespace aggscan
