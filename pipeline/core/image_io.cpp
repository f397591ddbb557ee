#include "pipeline/core/image_io.h"

#include <malloc.h>
#include <sys/stat.h>
#include <turbojpeg.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <vector>

#include "common/fsutil.h"

namespace aggscan {
namespace {

Error Bad(const std::string& what, const std::string& msg, std::string detail = {}) {
  return MakeError(ErrorClass::kCorrupt, "image " + what + ": " + msg, std::move(detail));
}

uint32_t Be16(const unsigned char* p) { return (uint32_t{p[0]} << 8) | p[1]; }
uint32_t Be32(const unsigned char* p) { return (Be16(p) << 16) | Be16(p + 2); }
uint32_t Le16(const unsigned char* p) { return (uint32_t{p[1]} << 8) | p[0]; }
uint32_t Le32(const unsigned char* p) { return (Le16(p + 2) << 16) | Le16(p); }

bool IsSof(unsigned m) {
  // SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC).
  return m >= 0xC0 && m <= 0xCF && m != 0xC4 && m != 0xC8 && m != 0xCC;
}

// Walks the marker segments up to the frame header (ITU T.81 B.1.1).
Result<ImageHeader> JpegHeader(const unsigned char* d, size_t n, const std::string& what) {
  size_t pos = 2;
  while (pos < n) {
    if (d[pos] != 0xFF)
      return Bad(what, "malformed JPEG: no marker at byte " + std::to_string(pos));
    while (pos < n && d[pos] == 0xFF) ++pos;  // fill bytes
    if (pos >= n) break;
    const unsigned m = d[pos++];
    if (m == 0x01 || (m >= 0xD0 && m <= 0xD8)) continue;  // no length
    if (m == 0xD9 || m == 0xDA)
      return Bad(what, "malformed JPEG: no frame header before the image data");
    if (pos + 2 > n) break;
    const uint32_t len = Be16(d + pos);
    if (len < 2 || pos + len > n) break;
    if (IsSof(m)) {
      if (len < 8) return Bad(what, "malformed JPEG: frame header too short");
      ImageHeader h;
      h.format = "jpeg";
      h.height = static_cast<int>(Be16(d + pos + 3));
      h.width = static_cast<int>(Be16(d + pos + 5));
      h.channels = d[pos + 7];
      if (h.height == 0)
        return Bad(what, "JPEG whose height is given after the image data (DNL) is not supported");
      return h;
    }
    pos += len;
  }
  return Bad(what, "truncated JPEG: the file ends before its frame header");
}

Result<ImageHeader> PngHeader(const unsigned char* d, size_t n, const std::string& what) {
  // Signature (8), IHDR length (4) and type (4), width, height, depth, colour type.
  if (n < 26 || std::string_view(reinterpret_cast<const char*>(d + 12), 4) != "IHDR")
    return Bad(what, "malformed PNG: no IHDR chunk");
  const uint32_t w = Be32(d + 16), h = Be32(d + 20);
  if (w > 0x7FFFFFFF || h > 0x7FFFFFFF) return Bad(what, "malformed PNG: dimensions out of range");
  ImageHeader out;
  out.format = "png";
  out.width = static_cast<int>(w);
  out.height = static_cast<int>(h);
  switch (d[25]) {
    case 0:
    case 3:
      out.channels = 1;
      break;
    case 4:
      out.channels = 2;
      break;
    case 2:
      out.channels = 3;
      break;
    case 6:
      out.channels = 4;
      break;
    default:
      return Bad(what, "malformed PNG: unknown colour type " + std::to_string(d[25]));
  }
  return out;
}

Result<ImageHeader> PnmHeader(const unsigned char* d, size_t n, const std::string& what) {
  // "P5 <ws> width <ws> height ...", '#' comments to the end of the line.
  size_t pos = 2;
  long vals[2] = {0, 0};
  for (long& v : vals) {
    for (;;) {
      while (pos < n && std::isspace(d[pos])) ++pos;
      if (pos < n && d[pos] == '#') {
        while (pos < n && d[pos] != '\n') ++pos;
        continue;
      }
      break;
    }
    size_t digits = 0;
    while (pos < n && std::isdigit(d[pos]) && digits < 10) {
      v = v * 10 + (d[pos++] - '0');
      ++digits;
    }
    if (digits == 0 || digits == 10 || v > 0x7FFFFFFF) return Bad(what, "malformed PNM header");
  }
  ImageHeader h;
  h.format = "pnm";
  h.width = static_cast<int>(vals[0]);
  h.height = static_cast<int>(vals[1]);
  h.channels = (d[1] == '3' || d[1] == '6') ? 3 : 1;
  return h;
}

Result<ImageHeader> BmpHeader(const unsigned char* d, size_t n, const std::string& what) {
  if (n < 26) return Bad(what, "malformed BMP: header too short");
  const uint32_t dib = Le32(d + 14);
  ImageHeader h;
  h.format = "bmp";
  if (dib == 12) {
    h.width = static_cast<int>(Le16(d + 18));
    h.height = static_cast<int>(Le16(d + 20));
  } else {
    if (dib < 40 || n < 30) return Bad(what, "malformed BMP: unknown header");
    const int32_t w = static_cast<int32_t>(Le32(d + 18)), ht = static_cast<int32_t>(Le32(d + 22));
    // A negative height is a top-down bitmap.
    if (w <= 0 || ht == INT32_MIN) return Bad(what, "malformed BMP: dimensions out of range");
    h.width = w;
    h.height = std::abs(ht);
  }
  return h;
}

struct TjDeleter {
  void operator()(void* h) const { tjDestroy(h); }
};

Result<cv::Mat> DecodeJpeg(std::string_view bytes, const ImageHeader& hdr, ImageMode mode,
                           const std::string& what) {
  std::unique_ptr<void, TjDeleter> tj(tjInitDecompress());
  if (!tj)
    return MakeError(ErrorClass::kInternal, "cannot start the JPEG decoder",
                     tjGetErrorStr2(nullptr));
  auto* src = reinterpret_cast<const unsigned char*>(bytes.data());
  const auto size = static_cast<unsigned long>(bytes.size());
  int w = 0, h = 0, subsamp = 0, colorspace = 0;
  if (tjDecompressHeader3(tj.get(), src, size, &w, &h, &subsamp, &colorspace) != 0)
    return Bad(what, "malformed JPEG header", tjGetErrorStr2(tj.get()));
  if (w != hdr.width || h != hdr.height)
    return Bad(what, "malformed JPEG: two frame headers disagree");
  if (colorspace == TJCS_CMYK || colorspace == TJCS_YCCK)
    return Bad(what, "CMYK JPEG is not supported");
  const bool gray_src = colorspace == TJCS_GRAY;
  int pf = TJPF_BGR;
  if (mode == ImageMode::kGray || mode == ImageMode::kGrayHalf ||
      (mode == ImageMode::kUnchanged && gray_src))
    pf = TJPF_GRAY;
  if (mode == ImageMode::kGrayHalf) {
    const tjscalingfactor half{1, 2};
    w = TJSCALED(w, half);
    h = TJSCALED(h, half);
  }
  cv::Mat out(h, w, pf == TJPF_GRAY ? CV_8UC1 : CV_8UC3);
  // Warnings are errors: libjpeg reports a truncated file or damaged
  // entropy-coded data only as a warning and decodes grey in their place.
  if (tjDecompress2(tj.get(), src, size, out.data, w, static_cast<int>(out.step), h, pf,
                    TJFLAG_STOPONWARNING) != 0) {
    const std::string msg = tjGetErrorStr2(tj.get());
    const bool warning = tjGetErrorCode(tj.get()) == TJERR_WARNING;
    return Bad(what,
               std::string(warning ? "damaged JPEG data" : "JPEG cannot be decoded") +
                   " (libjpeg: " + msg + ")",
               msg);
  }
  return out;
}

}  // namespace

Result<ImageHeader> ReadImageHeader(std::string_view bytes, const std::string& what) {
  const auto* d = reinterpret_cast<const unsigned char*>(bytes.data());
  const size_t n = bytes.size();
  if (n >= 3 && d[0] == 0xFF && d[1] == 0xD8 && d[2] == 0xFF) return JpegHeader(d, n, what);
  if (n >= 8 && bytes.substr(0, 8) == std::string_view("\x89PNG\r\n\x1a\n", 8))
    return PngHeader(d, n, what);
  if (n >= 3 && d[0] == 'P' && d[1] >= '1' && d[1] <= '6' && std::isspace(d[2]))
    return PnmHeader(d, n, what);
  if (n >= 2 && d[0] == 'B' && d[1] == 'M') return BmpHeader(d, n, what);
  if (n == 0) return Bad(what, "the file is empty");
  return Bad(what, "not a JPEG, PNG, PNM or BMP file");
}

Status CheckImageLimits(const ImageHeader& h, const ImageLimits& limits, const std::string& what) {
  const std::string dims = std::to_string(h.width) + "x" + std::to_string(h.height);
  const int64_t px = int64_t{h.width} * h.height;
  if (h.width < limits.min_side_px || h.height < limits.min_side_px) {
    return Bad(what, "is " + dims + ": too small to measure (at least " +
                         std::to_string(limits.min_side_px) + " px a side)");
  }
  const double aspect =
      static_cast<double>(std::max(h.width, h.height)) / std::min(h.width, h.height);
  if (aspect > limits.max_aspect) {
    char a[32];
    std::snprintf(a, sizeof a, "%.0f", limits.max_aspect);
    return Bad(what, "is " + dims + ": a strip, not a photo (sides more than " + a + ":1 apart)");
  }
  if (px > limits.max_pixels) {
    char m[64];
    std::snprintf(m, sizeof m, "%.1f MP, more than the %.1f MP limit",
                  static_cast<double>(px) / 1e6, static_cast<double>(limits.max_pixels) / 1e6);
    return Bad(what,
               "is " + dims + " (" + m + "): a corrupt header, or a photo to be scaled down first");
  }
  return OkStatus();
}

Result<cv::Mat> DecodeImage(std::string_view bytes, ImageMode mode, const std::string& what,
                            const ImageLimits& limits) {
  auto hdr = ReadImageHeader(bytes, what);
  if (!hdr) return hdr.error();
  if (Status s = CheckImageLimits(*hdr, limits, what); !s) return s.error();
  if (hdr->format == "jpeg") return DecodeJpeg(bytes, *hdr, mode, what);
  int flags = cv::IMREAD_UNCHANGED;
  switch (mode) {
    case ImageMode::kColor:
      flags = cv::IMREAD_COLOR;
      break;
    case ImageMode::kGray:
      flags = cv::IMREAD_GRAYSCALE;
      break;
    case ImageMode::kGrayHalf:
      flags = cv::IMREAD_REDUCED_GRAYSCALE_2;
      break;
    case ImageMode::kUnchanged:
      break;
  }
  cv::Mat out;
  try {
    const cv::Mat buf(1, static_cast<int>(bytes.size()), CV_8UC1, const_cast<char*>(bytes.data()));
    out = cv::imdecode(buf, flags);
  } catch (const cv::Exception& e) {
    return Bad(what, hdr->format + " data cannot be decoded", e.what());
  }
  if (out.empty()) return Bad(what, hdr->format + " data cannot be decoded (damaged or truncated)");
  const int ew = mode == ImageMode::kGrayHalf ? (hdr->width + 1) / 2 : hdr->width;
  const int eh = mode == ImageMode::kGrayHalf ? (hdr->height + 1) / 2 : hdr->height;
  if (out.cols != ew || out.rows != eh) return Bad(what, "decoded size differs from its header's");
  return out;
}

Result<cv::Mat> LoadImage(const std::string& path, ImageMode mode, const ImageLimits& limits) {
  struct stat st {};
  if (::stat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode)) {
    // No image within the pixel limit is larger than uncompressed 16-bit RGBA
    // plus headers; a larger file is not read into memory at all.
    const double most = static_cast<double>(limits.max_pixels) * 8 + (1 << 20);
    if (static_cast<double>(st.st_size) > most) {
      return Bad(path, "the file is " + std::to_string(st.st_size) +
                           " bytes, larger than any image within the " +
                           std::to_string(limits.max_pixels / 1000000) + " MP limit");
    }
  }
  auto bytes = ReadFile(path);
  if (!bytes) {
    Error e = bytes.error();
    e.message = "cannot read image " + path + ": " + e.message;
    return e;
  }
  return DecodeImage(*bytes, mode, path, limits);
}

void KeepFreedImageMemory() {
  // Blocks up to 256 MiB (a float copy of a 20 MP photo) come from the heap,
  // and the heap is returned to the kernel only when 1 GiB of its top is free.
  mallopt(M_MMAP_THRESHOLD, 256 << 20);
  mallopt(M_TRIM_THRESHOLD, 1 << 30);
}

}  // namespace aggscan
