// Smaller copies of the camera's JPEGs for screens: the live preview and the
// view thumbnails. The DCT-domain scaling of libjpeg-turbo decodes straight to
// 1/2, 3/8, 1/4 or 1/8 of the size, so a 2016x1512 still becomes a 252x189
// thumbnail without ever being decoded at full size.
#pragma once

#include <cstdint>
#include <list>
#include <mutex>
#include <span>
#include <string>
#include <unordered_map>

#include "common/error.h"

namespace aggscan {

struct ScaledJpeg {
  std::string jpeg;
  int width = 0;
  int height = 0;
};

/// Re-encodes `jpeg` at the largest of libjpeg-turbo's scaling factors (at
/// most 1) whose longer side is at most `max_side` pixels (1/8 when even that
/// is larger). kCorrupt when `jpeg` is not a readable JPEG.
Result<ScaledJpeg> ScaleJpeg(std::span<const unsigned char> jpeg, int max_side, int quality);

/// Thumbnails of stored views, made on first request and kept (least recently
/// used first out) up to a byte budget. A file rewritten since (size or
/// modification time changed) is scaled again. Safe from any thread.
class ThumbnailCache {
 public:
  ThumbnailCache(int max_side, int quality, size_t budget_bytes);
  /// The thumbnail of the JPEG file at `path`; kNotFound when it does not
  /// exist, kCorrupt when it is not a readable JPEG.
  Result<ScaledJpeg> Get(const std::string& path);
  size_t bytes() const;
  int max_side() const { return max_side_; }

 private:
  struct Entry {
    int64_t mtime_ns = 0;
    int64_t size = 0;
    ScaledJpeg thumb;
    std::list<std::string>::iterator lru;
  };

  const int max_side_;
  const int quality_;
  const size_t budget_;
  mutable std::mutex mu_;
  std::unordered_map<std::string, Entry> entries_;
  std::list<std::string> lru_;  // most recent first
  size_t bytes_ = 0;
};

}  // namespace aggscan
