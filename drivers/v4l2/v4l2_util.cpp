#include "drivers/v4l2/v4l2_util.h"

#include <linux/videodev2.h>
#include <sys/stat.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <utility>

#include "drivers/sim/jpeg.h"

namespace aggscan::v4l2 {
namespace {

struct NamedFormat {
  const char* name;
  uint32_t fourcc;
};
// Config names; also the "auto" preference among raw formats (after MJPEG).
constexpr NamedFormat kFormats[] = {
    {"mjpeg", V4L2_PIX_FMT_MJPEG}, {"yuyv", V4L2_PIX_FMT_YUYV},   {"uyvy", V4L2_PIX_FMT_UYVY},
    {"nv12", V4L2_PIX_FMT_NV12},   {"rgb24", V4L2_PIX_FMT_RGB24}, {"bgr24", V4L2_PIX_FMT_BGR24},
    {"grey", V4L2_PIX_FMT_GREY},
};

uint8_t Clamp8(int v) { return static_cast<uint8_t>(std::clamp(v, 0, 255)); }

// BT.601 limited range (what UVC cameras and vivid's default colorspace send
// for YUV): 16..235 luma, 16..240 chroma; fixed point with 8 fractional bits.
void YuvToRgb(int y, int u, int v, uint8_t* out) {
  const int c = (y - 16) * 298;
  const int d = u - 128;
  const int e = v - 128;
  out[0] = Clamp8((c + 409 * e + 128) >> 8);
  out[1] = Clamp8((c - 100 * d - 208 * e + 128) >> 8);
  out[2] = Clamp8((c + 516 * d + 128) >> 8);
}

// The JPEG standard's example Huffman tables (ITU T.81 Annex K.3), which
// motion-JPEG streams assume when they carry no DHT segment: per table, the
// class/id byte, the 16 code-length counts, then the symbol values.
// clang-format off
constexpr uint8_t kStdDht[] = {
    // DC luminance (class 0, id 0)
    0x00, 0, 1, 5, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0, 0, 0,
    0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11,
    // DC chrominance (class 0, id 1)
    0x01, 0, 3, 1, 1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0, 0, 0,
    0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11,
    // AC luminance (class 1, id 0)
    0x10, 0, 2, 1, 3, 3, 2, 4, 3, 5, 5, 4, 4, 0, 0, 1, 0x7d,
    0x01, 0x02, 0x03, 0x00, 0x04, 0x11, 0x05, 0x12, 0x21, 0x31, 0x41, 0x06, 0x13, 0x51, 0x61, 0x07,
    0x22, 0x71, 0x14, 0x32, 0x81, 0x91, 0xa1, 0x08, 0x23, 0x42, 0xb1, 0xc1, 0x15, 0x52, 0xd1, 0xf0,
    0x24, 0x33, 0x62, 0x72, 0x82, 0x09, 0x0a, 0x16, 0x17, 0x18, 0x19, 0x1a, 0x25, 0x26, 0x27, 0x28,
    0x29, 0x2a, 0x34, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48, 0x49,
    0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68, 0x69,
    0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x83, 0x84, 0x85, 0x86, 0x87, 0x88, 0x89,
    0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5, 0xa6, 0xa7,
    0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6, 0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3, 0xc4, 0xc5,
    0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda, 0xe1, 0xe2,
    0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8, 0xe9, 0xea, 0xf1, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8,
    0xf9, 0xfa,
    // AC chrominance (class 1, id 1)
    0x11, 0, 2, 1, 2, 4, 4, 3, 4, 7, 5, 4, 4, 0, 1, 2, 0x77,
    0x00, 0x01, 0x02, 0x03, 0x11, 0x04, 0x05, 0x21, 0x31, 0x06, 0x12, 0x41, 0x51, 0x07, 0x61, 0x71,
    0x13, 0x22, 0x32, 0x81, 0x08, 0x14, 0x42, 0x91, 0xa1, 0xb1, 0xc1, 0x09, 0x23, 0x33, 0x52, 0xf0,
    0x15, 0x62, 0x72, 0xd1, 0x0a, 0x16, 0x24, 0x34, 0xe1, 0x25, 0xf1, 0x17, 0x18, 0x19, 0x1a, 0x26,
    0x27, 0x28, 0x29, 0x2a, 0x35, 0x36, 0x37, 0x38, 0x39, 0x3a, 0x43, 0x44, 0x45, 0x46, 0x47, 0x48,
    0x49, 0x4a, 0x53, 0x54, 0x55, 0x56, 0x57, 0x58, 0x59, 0x5a, 0x63, 0x64, 0x65, 0x66, 0x67, 0x68,
    0x69, 0x6a, 0x73, 0x74, 0x75, 0x76, 0x77, 0x78, 0x79, 0x7a, 0x82, 0x83, 0x84, 0x85, 0x86, 0x87,
    0x88, 0x89, 0x8a, 0x92, 0x93, 0x94, 0x95, 0x96, 0x97, 0x98, 0x99, 0x9a, 0xa2, 0xa3, 0xa4, 0xa5,
    0xa6, 0xa7, 0xa8, 0xa9, 0xaa, 0xb2, 0xb3, 0xb4, 0xb5, 0xb6, 0xb7, 0xb8, 0xb9, 0xba, 0xc2, 0xc3,
    0xc4, 0xc5, 0xc6, 0xc7, 0xc8, 0xc9, 0xca, 0xd2, 0xd3, 0xd4, 0xd5, 0xd6, 0xd7, 0xd8, 0xd9, 0xda,
    0xe2, 0xe3, 0xe4, 0xe5, 0xe6, 0xe7, 0xe8, 0xe9, 0xea, 0xf2, 0xf3, 0xf4, 0xf5, 0xf6, 0xf7, 0xf8,
    0xf9, 0xfa,
};
// clang-format on

Error NotJpeg(const std::string& why) {
  return MakeError(ErrorClass::kDeviceFault,
                   "the camera sent an MJPEG frame that is not a JPEG: " + why);
}

}  // namespace

Result<std::vector<unsigned char>> CompleteMjpeg(std::span<const uint8_t> jpeg) {
  if (jpeg.size() < 4 || jpeg[0] != 0xFF || jpeg[1] != 0xD8)
    return NotJpeg("no start-of-image marker");
  size_t pos = 2;
  while (pos + 4 <= jpeg.size()) {
    if (jpeg[pos] != 0xFF)
      return NotJpeg("garbage between segments at byte " + std::to_string(pos));
    const uint8_t m = jpeg[pos + 1];
    if (m == 0xFF) {  // fill byte
      ++pos;
      continue;
    }
    if (m == 0xC4) return std::vector<unsigned char>(jpeg.begin(), jpeg.end());  // has its tables
    if (m == 0xDA) {
      std::vector<unsigned char> out;
      out.reserve(jpeg.size() + sizeof(kStdDht) + 4);
      out.insert(out.end(), jpeg.begin(), jpeg.begin() + static_cast<std::ptrdiff_t>(pos));
      const size_t len = sizeof(kStdDht) + 2;
      out.push_back(0xFF);
      out.push_back(0xC4);
      out.push_back(static_cast<unsigned char>(len >> 8));
      out.push_back(static_cast<unsigned char>(len & 0xFF));
      out.insert(out.end(), std::begin(kStdDht), std::end(kStdDht));
      out.insert(out.end(), jpeg.begin() + static_cast<std::ptrdiff_t>(pos), jpeg.end());
      return out;
    }
    if ((m >= 0xD0 && m <= 0xD7) || m == 0x01) {  // markers without a length
      pos += 2;
      continue;
    }
    pos += 2 + ((static_cast<size_t>(jpeg[pos + 2]) << 8) | jpeg[pos + 3]);
  }
  return NotJpeg("no start-of-scan marker");
}

Result<std::vector<unsigned char>> EncodeStill(uint32_t fourcc, std::span<const uint8_t> data,
                                               int width, int height, int stride, int quality) {
  if (fourcc == V4L2_PIX_FMT_MJPEG || fourcc == V4L2_PIX_FMT_JPEG) return CompleteMjpeg(data);
  Result<std::vector<uint8_t>> rgb = ToRgb(fourcc, data, width, height, stride);
  if (!rgb) return rgb.error();
  return sim::EncodeJpeg(rgb->data(), width, height, quality);
}

Result<std::shared_ptr<Frame>> EncodeStillFrame(const std::string& who, uint32_t fourcc,
                                                std::span<const uint8_t> data, int width,
                                                int height, int stride, int quality,
                                                uint64_t request_id, uint64_t sequence) {
  Result<std::vector<unsigned char>> still =
      EncodeStill(fourcc, data, width, height, stride, quality);
  if (!still) {
    Error e = still.error();
    e.message = "camera " + who + ": " + e.message;
    return e;
  }
  auto frame = std::make_shared<Frame>();
  frame->data = std::move(*still);
  frame->request_id = request_id;
  frame->sequence = sequence;
  frame->width = width;
  frame->height = height;
  frame->encoding = "jpeg";
  return frame;
}

std::string FourCcName(uint32_t fourcc) {
  std::string s(4, '?');
  for (int i = 0; i < 4; ++i) {
    const char ch = static_cast<char>((fourcc >> (8 * i)) & 0xff);
    if (ch >= 0x20 && ch < 0x7f) s[i] = ch;
  }
  return s;
}

std::optional<uint32_t> FormatFromName(const std::string& name) {
  for (const auto& f : kFormats)
    if (name == f.name) return f.fourcc;
  return std::nullopt;
}

bool IsSupportedFormat(uint32_t fourcc) {
  for (const auto& f : kFormats)
    if (fourcc == f.fourcc) return true;
  // Some UVC cameras announce their motion-JPEG stream as JPEG.
  return fourcc == V4L2_PIX_FMT_JPEG;
}

Result<uint32_t> ChooseFormat(const std::vector<uint32_t>& offered, const std::string& wanted) {
  auto has = [&](uint32_t f) {
    return std::find(offered.begin(), offered.end(), f) != offered.end();
  };
  std::string list;
  for (uint32_t f : offered) {
    if (!list.empty()) list += ", ";
    list += FourCcName(f);
  }
  if (list.empty()) list = "none";
  if (wanted != "auto") {
    std::optional<uint32_t> f = FormatFromName(wanted);
    if (!f)
      return MakeError(ErrorClass::kInvalidConfig,
                       "camera.v4l2.pixel_format \"" + wanted + "\" is not known");
    if (has(*f)) return *f;
    if (*f == V4L2_PIX_FMT_MJPEG && has(V4L2_PIX_FMT_JPEG))
      return static_cast<uint32_t>(V4L2_PIX_FMT_JPEG);
    return MakeError(ErrorClass::kInvalidConfig,
                     "the camera does not offer pixel format " + wanted + " (offers: " + list +
                         "); set camera.v4l2.pixel_format to one of them or \"auto\"");
  }
  if (has(V4L2_PIX_FMT_MJPEG)) return static_cast<uint32_t>(V4L2_PIX_FMT_MJPEG);
  if (has(V4L2_PIX_FMT_JPEG)) return static_cast<uint32_t>(V4L2_PIX_FMT_JPEG);
  for (const auto& f : kFormats)
    if (has(f.fourcc)) return f.fourcc;
  return MakeError(ErrorClass::kDeviceFault,
                   "the camera offers no pixel format this backend can use (offers: " + list +
                       "; usable: MJPEG, YUYV, UYVY, NV12, RGB3, BGR3, GREY)");
}

Result<std::vector<uint8_t>> ToRgb(uint32_t fourcc, std::span<const uint8_t> data, int width,
                                   int height, int stride) {
  if (width <= 0 || height <= 0 || (width % 2) != 0)
    return MakeError(ErrorClass::kInvalidArgument, "frame size " + std::to_string(width) + "x" +
                                                       std::to_string(height) +
                                                       " cannot be converted");
  const size_t w = static_cast<size_t>(width);
  const size_t h = static_cast<size_t>(height);
  size_t bpp_num = 0;  // bytes per pixel of the first plane
  switch (fourcc) {
    case V4L2_PIX_FMT_YUYV:
    case V4L2_PIX_FMT_UYVY:
      bpp_num = 2;
      break;
    case V4L2_PIX_FMT_RGB24:
    case V4L2_PIX_FMT_BGR24:
      bpp_num = 3;
      break;
    case V4L2_PIX_FMT_GREY:
    case V4L2_PIX_FMT_NV12:
      bpp_num = 1;
      break;
    default:
      return MakeError(ErrorClass::kInvalidArgument, "no conversion from " + FourCcName(fourcc));
  }
  const size_t line = stride > 0 ? static_cast<size_t>(stride) : w * bpp_num;
  if (line < w * bpp_num)
    return MakeError(ErrorClass::kDeviceFault,
                     "bytesperline " + std::to_string(line) + " is shorter than a row");
  size_t need = line * (h - 1) + w * bpp_num;
  if (fourcc == V4L2_PIX_FMT_NV12)
    need = line * h + line * (h / 2 - 1) + w;  // Y plane + interleaved UV, half height
  if (data.size() < need)
    return MakeError(ErrorClass::kDeviceFault,
                     "short frame: " + std::to_string(data.size()) + " bytes of " +
                         std::to_string(need) + " for " + FourCcName(fourcc) + " " +
                         std::to_string(width) + "x" + std::to_string(height));
  std::vector<uint8_t> rgb(w * h * 3);
  for (size_t y = 0; y < h; ++y) {
    const uint8_t* row = data.data() + y * line;
    uint8_t* out = rgb.data() + y * w * 3;
    switch (fourcc) {
      case V4L2_PIX_FMT_YUYV:
        for (size_t x = 0; x < w; x += 2, row += 4) {
          YuvToRgb(row[0], row[1], row[3], out + x * 3);
          YuvToRgb(row[2], row[1], row[3], out + x * 3 + 3);
        }
        break;
      case V4L2_PIX_FMT_UYVY:
        for (size_t x = 0; x < w; x += 2, row += 4) {
          YuvToRgb(row[1], row[0], row[2], out + x * 3);
          YuvToRgb(row[3], row[0], row[2], out + x * 3 + 3);
        }
        break;
      case V4L2_PIX_FMT_NV12: {
        const uint8_t* uv = data.data() + line * h + (y / 2) * line;
        for (size_t x = 0; x < w; ++x)
          YuvToRgb(row[x], uv[x & ~size_t{1}], uv[(x & ~size_t{1}) + 1], out + x * 3);
        break;
      }
      case V4L2_PIX_FMT_RGB24:
        std::memcpy(out, row, w * 3);
        break;
      case V4L2_PIX_FMT_BGR24:
        for (size_t x = 0; x < w; ++x) {
          out[x * 3] = row[x * 3 + 2];
          out[x * 3 + 1] = row[x * 3 + 1];
          out[x * 3 + 2] = row[x * 3];
        }
        break;
      case V4L2_PIX_FMT_GREY:
        for (size_t x = 0; x < w; ++x) out[x * 3] = out[x * 3 + 1] = out[x * 3 + 2] = row[x];
        break;
    }
  }
  return rgb;
}

Result<int64_t> QuantizeControl(const ControlRange& r, double value, const std::string& what) {
  const int64_t step = r.step > 0 ? r.step : 1;
  const double steps =
      std::round((value - static_cast<double>(r.minimum)) / static_cast<double>(step));
  const double v = static_cast<double>(r.minimum) + steps * static_cast<double>(step);
  if (!std::isfinite(v) || v < static_cast<double>(r.minimum) ||
      v > static_cast<double>(r.maximum)) {
    return MakeError(ErrorClass::kInvalidConfig,
                     what + ": device value " +
                         std::to_string(static_cast<long long>(std::llround(value))) +
                         " is outside the control's range " + std::to_string(r.minimum) + ".." +
                         std::to_string(r.maximum));
  }
  return static_cast<int64_t>(v);
}

// V4L2_CID_EXPOSURE_ABSOLUTE counts 100 microsecond units (V4L2 spec, camera
// control reference).
double ExposureUsToV4l2(double exposure_us) { return exposure_us / 100.0; }
double V4l2ToExposureUs(int64_t value) { return static_cast<double>(value) * 100.0; }

Result<double> UnitlessToDevice(const ControlRange& r, double factor, int unit,
                                const std::string& what) {
  const double reference = unit > 0 ? unit : static_cast<double>(r.default_value);
  if (reference <= 0) {
    return MakeError(ErrorClass::kInvalidConfig,
                     what + ": the control's default value is " + std::to_string(r.default_value) +
                         ", so a factor cannot be mapped onto it; set camera.v4l2.gain_unit");
  }
  return factor * reference;
}

Result<std::string> ResolveDevice(const std::string& configured,
                                  const std::vector<std::string>& by_dirs) {
  namespace fs = std::filesystem;
  if (configured.empty())
    return MakeError(ErrorClass::kInvalidConfig,
                     "camera.device is empty; set a /dev/videoN path or a /dev/v4l/by-id name");
  std::vector<std::string> candidates;
  if (configured.find('/') != std::string::npos) {
    candidates.push_back(configured);
  } else {
    for (const auto& d : by_dirs) candidates.push_back(d + "/" + configured);
  }
  std::string tried;
  for (const auto& c : candidates) {
    std::error_code ec;
    fs::path real = fs::canonical(c, ec);  // follows udev's by-id / by-path symlinks
    if (!ec) {
      struct stat st {};
      if (::stat(real.c_str(), &st) == 0 && !S_ISCHR(st.st_mode)) {
        return MakeError(ErrorClass::kDeviceMissing,
                         c + " (" + real.string() + ") is not a device node");
      }
      return real.string();
    }
    tried += (tried.empty() ? "" : ", ") + c;
  }
  return MakeError(ErrorClass::kDeviceMissing, "camera " + configured + " not found (looked at " +
                                                   tried + ") — check the cable and camera.device");
}

ErrorClass ClassifyErrno(int err, bool streaming) {
  switch (err) {
    case ENOENT:
    case ENXIO:
    case ENODEV:  // the node stays but the device is gone (USB unplug, vivid's "Disconnect")
    case EPIPE:
      return streaming ? ErrorClass::kDisconnected : ErrorClass::kDeviceMissing;
    case ETIMEDOUT:
    case EAGAIN:
      return ErrorClass::kTimeout;
    case EINVAL:  // the device refused a request it should support
    case ENOTTY:
    case ENOMEM:
    case EBUSY:
    case EIO:
      return ErrorClass::kDeviceFault;
    default:
      return ErrorClass::kIo;
  }
}

Error V4l2Error(const std::string& device, const std::string& what, int err, bool streaming) {
  const ErrorClass cls = ClassifyErrno(err, streaming);
  std::string hint;
  switch (cls) {
    case ErrorClass::kDeviceMissing:
      hint = " — check the cable and camera.device";
      break;
    case ErrorClass::kDisconnected:
      hint = " — the camera went away; check the cable, it is reopened on reset";
      break;
    case ErrorClass::kTimeout:
      hint = " — the camera sends no frames";
      break;
    case ErrorClass::kDeviceFault:
      if (err == EBUSY) hint = " — another program is using the camera";
      if (err == EIO)
        hint = " — the driver reports an I/O error; the camera is reconfigured on reset";
      break;
    default:
      break;
  }
  return MakeError(cls, "camera " + device + ": " + what + " failed" + hint, std::strerror(err));
}

}  // namespace aggscan::v4l2
