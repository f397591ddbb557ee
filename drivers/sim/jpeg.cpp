#include "drivers/sim/jpeg.h"

#include <turbojpeg.h>

#include <memory>

#include "common/fsutil.h"

namespace aggscan::sim {

namespace {

struct TjDeleter {
  void operator()(void* h) const { tjDestroy(h); }
};
using TjHandle = std::unique_ptr<void, TjDeleter>;

Status WritePnm(const char* magic, const std::vector<uint8_t>& data, int width, int height,
                int channels, const std::string& path) {
  if (width <= 0 || height <= 0 || data.size() != static_cast<size_t>(width) * height * channels) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "image size does not match its dimensions: " + path);
  }
  std::string out =
      std::string(magic) + "\n" + std::to_string(width) + " " + std::to_string(height) + "\n255\n";
  out.append(reinterpret_cast<const char*>(data.data()), data.size());
  return WriteFileAtomic(path, std::string_view(out));
}

}  // namespace

Result<std::vector<unsigned char>> EncodeJpeg(const uint8_t* rgb, int width, int height,
                                              int quality) {
  if (!rgb || width <= 0 || height <= 0 || quality < 1 || quality > 100) {
    return MakeError(ErrorClass::kInvalidArgument, "EncodeJpeg: bad image or quality");
  }
  TjHandle h(tjInitCompress());
  if (!h) return MakeError(ErrorClass::kInternal, "cannot create a JPEG encoder", tjGetErrorStr());
  unsigned char* buf = nullptr;
  unsigned long size = 0;
  if (tjCompress2(h.get(), rgb, width, 0, height, TJPF_RGB, &buf, &size, TJSAMP_420, quality,
                  TJFLAG_FASTDCT) != 0) {
    std::string detail = tjGetErrorStr2(h.get());
    tjFree(buf);
    return MakeError(ErrorClass::kInternal, "JPEG encoding failed", detail);
  }
  std::vector<unsigned char> out(buf, buf + size);
  tjFree(buf);
  return out;
}

Result<RgbImage> DecodeJpeg(std::span<const unsigned char> bytes) {
  TjHandle h(tjInitDecompress());
  if (!h) return MakeError(ErrorClass::kInternal, "cannot create a JPEG decoder", tjGetErrorStr());
  int w = 0, ht = 0, subsamp = 0, colorspace = 0;
  if (tjDecompressHeader3(h.get(), bytes.data(), static_cast<unsigned long>(bytes.size()), &w, &ht,
                          &subsamp, &colorspace) != 0) {
    return MakeError(ErrorClass::kCorrupt, "not a readable JPEG", tjGetErrorStr2(h.get()));
  }
  RgbImage img;
  img.width = w;
  img.height = ht;
  img.rgb.resize(static_cast<size_t>(w) * ht * 3);
  if (tjDecompress2(h.get(), bytes.data(), static_cast<unsigned long>(bytes.size()), img.rgb.data(),
                    w, 0, ht, TJPF_RGB, 0) != 0) {
    return MakeError(ErrorClass::kCorrupt, "JPEG decoding failed", tjGetErrorStr2(h.get()));
  }
  return img;
}

Status WritePgm(const std::vector<uint8_t>& gray, int width, int height, const std::string& path) {
  return WritePnm("P5", gray, width, height, 1, path);
}

Status WritePpm(const std::vector<uint8_t>& rgb, int width, int height, const std::string& path) {
  return WritePnm("P6", rgb, width, height, 3, path);
}

}  // namespace aggscan::sim
