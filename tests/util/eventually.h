// Waiting for something another thread, process or the kernel does: polls
// `pred` until it holds. The limit is a hang guard, never a speed check.
#pragma once

#include <chrono>
#include <fstream>
#include <string>
#include <thread>

namespace aggscan::test {

template <typename P>
bool Eventually(P pred, double seconds = 20) {
  const auto end = std::chrono::steady_clock::now() +
                   std::chrono::milliseconds(static_cast<int>(seconds * 1000));
  while (std::chrono::steady_clock::now() < end) {
    if (pred()) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  return pred();
}

/// Writes a sysfs / configfs attribute (or any file) in one go; false on failure.
inline bool WriteFile(const std::string& path, const std::string& value) {
  std::ofstream f(path, std::ios::binary);
  f << value;
  f.flush();
  return static_cast<bool>(f);
}

}  // namespace aggscan::test
