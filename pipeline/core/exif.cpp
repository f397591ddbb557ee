#include "pipeline/core/exif.h"

#include <libexif/exif-data.h>
#include <libexif/exif-loader.h>

#include <cstdio>
#include <ctime>
#include <memory>

#include "common/fsutil.h"

namespace aggscan {
namespace {

struct ExifDataFree {
  void operator()(ExifData* d) const { exif_data_unref(d); }
};

std::string Trim(std::string s) {
  while (!s.empty() && (s.back() == ' ' || s.back() == '\0')) s.pop_back();
  size_t i = 0;
  while (i < s.size() && s[i] == ' ') ++i;
  return s.substr(i);
}

// The entry of `tag` in whichever IFD holds it.
ExifEntry* Find(ExifData* d, ExifTag tag) { return exif_data_get_entry(d, tag); }

std::optional<std::string> Ascii(ExifData* d, ExifTag tag) {
  ExifEntry* e = Find(d, tag);
  if (!e || e->format != EXIF_FORMAT_ASCII || !e->data || e->size == 0) return std::nullopt;
  return Trim(std::string(reinterpret_cast<const char*>(e->data), e->size));
}

std::optional<double> Number(ExifData* d, ExifTag tag) {
  ExifEntry* e = Find(d, tag);
  if (!e || !e->data || e->components < 1) return std::nullopt;
  const ExifByteOrder o = exif_data_get_byte_order(d);
  switch (e->format) {
    case EXIF_FORMAT_SHORT:
      return exif_get_short(e->data, o);
    case EXIF_FORMAT_LONG:
      return exif_get_long(e->data, o);
    case EXIF_FORMAT_RATIONAL: {
      const ExifRational r = exif_get_rational(e->data, o);
      if (r.denominator == 0) return std::nullopt;
      return static_cast<double>(r.numerator) / r.denominator;
    }
    case EXIF_FORMAT_SRATIONAL: {
      const ExifSRational r = exif_get_srational(e->data, o);
      if (r.denominator == 0) return std::nullopt;
      return static_cast<double>(r.numerator) / r.denominator;
    }
    default:
      return std::nullopt;
  }
}

}  // namespace

std::string PhotoExif::Camera() const { return Trim(make + " " + model); }

std::optional<double> PhotoExif::SensorWidthMm() const {
  if (!focal_plane_x_res_per_mm || *focal_plane_x_res_per_mm <= 0 || !pixel_x || *pixel_x <= 0)
    return std::nullopt;
  return *pixel_x / *focal_plane_x_res_per_mm;
}

std::optional<double> ExifTimeSeconds(const std::string& s) {
  std::tm tm{};
  int y = 0, mo = 0, d = 0, h = 0, mi = 0, se = 0;
  if (std::sscanf(s.c_str(), "%4d:%2d:%2d %2d:%2d:%2d", &y, &mo, &d, &h, &mi, &se) != 6)
    return std::nullopt;
  if (y < 1970 || mo < 1 || mo > 12 || d < 1 || d > 31 || h > 23 || mi > 59 || se > 60)
    return std::nullopt;
  tm.tm_year = y - 1900;
  tm.tm_mon = mo - 1;
  tm.tm_mday = d;
  tm.tm_hour = h;
  tm.tm_min = mi;
  tm.tm_sec = se;
  return static_cast<double>(timegm(&tm));
}

Result<PhotoExif> ReadExif(const std::string& path) {
  if (!PathExists(path)) return MakeError(ErrorClass::kNotFound, path + ": no such file");
  PhotoExif x;
  std::unique_ptr<ExifData, ExifDataFree> d(exif_data_new_from_file(path.c_str()));
  if (!d) return x;  // no EXIF (or not a JPEG)
  x.make = Ascii(d.get(), EXIF_TAG_MAKE).value_or("");
  x.model = Ascii(d.get(), EXIF_TAG_MODEL).value_or("");
  if (auto o = Number(d.get(), EXIF_TAG_ORIENTATION); o && *o >= 1 && *o <= 8)
    x.orientation = static_cast<int>(*o);
  if (auto f = Number(d.get(), EXIF_TAG_FOCAL_LENGTH); f && *f > 0) x.focal_mm = *f;
  if (auto f = Number(d.get(), EXIF_TAG_FOCAL_LENGTH_IN_35MM_FILM); f && *f > 0) x.focal_35mm = *f;
  if (auto px = Number(d.get(), EXIF_TAG_PIXEL_X_DIMENSION); px && *px > 0)
    x.pixel_x = static_cast<int>(*px);
  if (auto py = Number(d.get(), EXIF_TAG_PIXEL_Y_DIMENSION); py && *py > 0)
    x.pixel_y = static_cast<int>(*py);
  if (auto r = Number(d.get(), EXIF_TAG_FOCAL_PLANE_X_RESOLUTION); r && *r > 0) {
    // FocalPlaneResolutionUnit: 2 inch (the default), 3 cm, 4 mm, 5 um.
    const double unit = Number(d.get(), EXIF_TAG_FOCAL_PLANE_RESOLUTION_UNIT).value_or(2.0);
    const double per_mm = unit == 3 ? 10.0 : unit == 4 ? 1.0 : unit == 5 ? 1e-3 : 25.4;
    x.focal_plane_x_res_per_mm = *r / per_mm;
  }
  x.datetime_original = Ascii(d.get(), EXIF_TAG_DATE_TIME_ORIGINAL);
  if (!x.datetime_original) x.datetime_original = Ascii(d.get(), EXIF_TAG_DATE_TIME);
  if (x.datetime_original) {
    x.time_s = ExifTimeSeconds(*x.datetime_original);
    if (x.time_s) {
      if (auto sub = Ascii(d.get(), EXIF_TAG_SUB_SEC_TIME_ORIGINAL); sub && !sub->empty()) {
        // "123" = .123 s: the digits are a decimal fraction.
        double frac = 0, scale = 0.1;
        for (char c : *sub) {
          if (c < '0' || c > '9') break;
          frac += (c - '0') * scale;
          scale /= 10;
        }
        *x.time_s += frac;
      }
    }
  }
  x.exposure_s = Number(d.get(), EXIF_TAG_EXPOSURE_TIME);
  x.f_number = Number(d.get(), EXIF_TAG_FNUMBER);
  if (auto iso = Number(d.get(), EXIF_TAG_ISO_SPEED_RATINGS)) x.iso = static_cast<int>(*iso);
  return x;
}

}  // namespace aggscan
