#include "daemon/jpeg_scale.h"

#include <sys/stat.h>
#include <turbojpeg.h>

#include <algorithm>
#include <cerrno>
#include <memory>
#include <vector>

#include "common/fsutil.h"

namespace aggscan {

namespace {

struct TjFree {
  void operator()(void* h) const {
    if (h != nullptr) tjDestroy(h);
  }
};
using TjHandle = std::unique_ptr<void, TjFree>;

}  // namespace

Result<ScaledJpeg> ScaleJpeg(std::span<const unsigned char> jpeg, int max_side, int quality) {
  TjHandle dec(tjInitDecompress());
  if (!dec)
    return MakeError(ErrorClass::kInternal, "cannot create a JPEG decoder", tjGetErrorStr());
  int w = 0, h = 0, subsamp = 0, colorspace = 0;
  const auto* src = jpeg.data();
  const auto size = static_cast<unsigned long>(jpeg.size());
  if (jpeg.empty() || tjDecompressHeader3(dec.get(), src, size, &w, &h, &subsamp, &colorspace) != 0)
    return MakeError(ErrorClass::kCorrupt, "not a readable JPEG",
                     jpeg.empty() ? "empty" : tjGetErrorStr2(dec.get()));
  int n = 0;
  const tjscalingfactor* factors = tjGetScalingFactors(&n);
  // Largest factor <= 1 whose long side fits; the smallest one if none does.
  tjscalingfactor best{1, 8};
  int best_side = 0;
  for (int i = 0; i < n; ++i) {
    const tjscalingfactor f = factors[i];
    if (f.num > f.denom) continue;
    const int side = TJSCALED(std::max(w, h), f);
    if (side <= max_side && side > best_side) {
      best = f;
      best_side = side;
    }
  }
  const int sw = TJSCALED(w, best);
  const int sh = TJSCALED(h, best);
  std::vector<unsigned char> rgb(static_cast<size_t>(sw) * sh * 3);
  if (tjDecompress2(dec.get(), src, size, rgb.data(), sw, 0, sh, TJPF_RGB, TJFLAG_FASTDCT) != 0)
    return MakeError(ErrorClass::kCorrupt, "JPEG decoding failed", tjGetErrorStr2(dec.get()));
  TjHandle enc(tjInitCompress());
  if (!enc)
    return MakeError(ErrorClass::kInternal, "cannot create a JPEG encoder", tjGetErrorStr());
  unsigned char* buf = nullptr;
  unsigned long out_size = 0;
  if (tjCompress2(enc.get(), rgb.data(), sw, 0, sh, TJPF_RGB, &buf, &out_size, TJSAMP_420, quality,
                  TJFLAG_FASTDCT) != 0) {
    std::string detail = tjGetErrorStr2(enc.get());
    tjFree(buf);
    return MakeError(ErrorClass::kInternal, "JPEG encoding failed", detail);
  }
  ScaledJpeg out;
  out.jpeg.assign(reinterpret_cast<const char*>(buf), out_size);
  out.width = sw;
  out.height = sh;
  tjFree(buf);
  return out;
}

ThumbnailCache::ThumbnailCache(int max_side, int quality, size_t budget_bytes)
    : max_side_(max_side), quality_(quality), budget_(budget_bytes) {}

size_t ThumbnailCache::bytes() const {
  std::lock_guard<std::mutex> lock(mu_);
  return bytes_;
}

Result<ScaledJpeg> ThumbnailCache::Get(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return ErrnoError("cannot read " + path, errno);
  const int64_t mtime = static_cast<int64_t>(st.st_mtim.tv_sec) * 1000000000 + st.st_mtim.tv_nsec;
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = entries_.find(path);
    if (it != entries_.end() && it->second.mtime_ns == mtime && it->second.size == st.st_size) {
      lru_.splice(lru_.begin(), lru_, it->second.lru);
      return it->second.thumb;
    }
  }
  // Scaled outside the lock: other thumbnails are served meanwhile.
  Result<std::string> bytes = ReadFile(path);
  if (!bytes) return bytes.error();
  Result<ScaledJpeg> thumb =
      ScaleJpeg(std::span(reinterpret_cast<const unsigned char*>(bytes->data()), bytes->size()),
                max_side_, quality_);
  if (!thumb)
    return MakeError(thumb.error().cls, path + ": " + thumb.error().message, thumb.error().detail);
  std::lock_guard<std::mutex> lock(mu_);
  if (auto it = entries_.find(path); it != entries_.end()) {
    bytes_ -= it->second.thumb.jpeg.size();
    lru_.erase(it->second.lru);
    entries_.erase(it);
  }
  lru_.push_front(path);
  entries_[path] = Entry{mtime, st.st_size, *thumb, lru_.begin()};
  bytes_ += thumb->jpeg.size();
  while (bytes_ > budget_ && lru_.size() > 1) {
    auto last = entries_.find(lru_.back());
    bytes_ -= last->second.thumb.jpeg.size();
    entries_.erase(last);
    lru_.pop_back();
  }
  return thumb;
}

}  // namespace aggscan
