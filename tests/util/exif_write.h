// Test fixtures: EXIF written into a JPEG as a phone writes it (libexif's own
// writer; the APP1 segment put right after the JPEG's start marker).
#pragma once

#include <libexif/exif-data.h>

#include <cstdlib>
#include <cstring>
#include <optional>
#include <string>
#include <vector>

namespace aggscan::test {

struct PhoneExif {
  std::string make = "Simphone", model = "S1";
  int orientation = 1;
  double focal_mm = 0;  // 0: not written
  int focal_35mm = 0;   // 0: not written
  int pixel_x = 0, pixel_y = 0;
  std::string datetime_original;  // "YYYY:MM:DD HH:MM:SS"
  std::string subsec;             // "250"
  double exposure_s = 0;
  int iso = 0;
};

namespace exif_detail {

inline ExifEntry* Add(ExifData* ed, ExifIfd ifd, ExifTag tag, ExifFormat fmt,
                      unsigned long components) {
  ExifMem* mem = exif_mem_new_default();
  ExifEntry* e = exif_entry_new_mem(mem);
  const size_t size = exif_format_get_size(fmt) * components;
  e->data = static_cast<unsigned char*>(exif_mem_alloc(mem, static_cast<ExifLong>(size)));
  e->size = static_cast<unsigned int>(size);
  e->tag = tag;
  e->components = components;
  e->format = fmt;
  exif_content_add_entry(ed->ifd[ifd], e);
  exif_mem_unref(mem);
  exif_entry_unref(e);
  return e;
}

inline void Ascii(ExifData* ed, ExifIfd ifd, ExifTag tag, const std::string& s) {
  ExifEntry* e = Add(ed, ifd, tag, EXIF_FORMAT_ASCII, s.size() + 1);
  std::memcpy(e->data, s.c_str(), s.size() + 1);
}

inline void Short(ExifData* ed, ExifIfd ifd, ExifTag tag, int v) {
  ExifEntry* e = Add(ed, ifd, tag, EXIF_FORMAT_SHORT, 1);
  exif_set_short(e->data, exif_data_get_byte_order(ed), static_cast<ExifShort>(v));
}

inline void Rational(ExifData* ed, ExifIfd ifd, ExifTag tag, double v, ExifLong den) {
  ExifEntry* e = Add(ed, ifd, tag, EXIF_FORMAT_RATIONAL, 1);
  exif_set_rational(e->data, exif_data_get_byte_order(ed),
                    {static_cast<ExifLong>(v * den + 0.5), den});
}

}  // namespace exif_detail

/// `jpeg` (a JPEG without EXIF) with `x` as its EXIF.
inline std::vector<unsigned char> JpegWithExif(const std::vector<unsigned char>& jpeg,
                                               const PhoneExif& x) {
  using namespace exif_detail;
  ExifData* ed = exif_data_new();
  exif_data_set_option(ed, EXIF_DATA_OPTION_FOLLOW_SPECIFICATION);
  exif_data_set_data_type(ed, EXIF_DATA_TYPE_COMPRESSED);
  exif_data_set_byte_order(ed, EXIF_BYTE_ORDER_INTEL);
  Ascii(ed, EXIF_IFD_0, EXIF_TAG_MAKE, x.make);
  Ascii(ed, EXIF_IFD_0, EXIF_TAG_MODEL, x.model);
  Short(ed, EXIF_IFD_0, EXIF_TAG_ORIENTATION, x.orientation);
  if (!x.datetime_original.empty()) {
    Ascii(ed, EXIF_IFD_EXIF, EXIF_TAG_DATE_TIME_ORIGINAL, x.datetime_original);
    if (!x.subsec.empty()) Ascii(ed, EXIF_IFD_EXIF, EXIF_TAG_SUB_SEC_TIME_ORIGINAL, x.subsec);
  }
  if (x.focal_mm > 0) Rational(ed, EXIF_IFD_EXIF, EXIF_TAG_FOCAL_LENGTH, x.focal_mm, 100);
  if (x.focal_35mm > 0) Short(ed, EXIF_IFD_EXIF, EXIF_TAG_FOCAL_LENGTH_IN_35MM_FILM, x.focal_35mm);
  if (x.pixel_x > 0) Short(ed, EXIF_IFD_EXIF, EXIF_TAG_PIXEL_X_DIMENSION, x.pixel_x);
  if (x.pixel_y > 0) Short(ed, EXIF_IFD_EXIF, EXIF_TAG_PIXEL_Y_DIMENSION, x.pixel_y);
  if (x.exposure_s > 0) Rational(ed, EXIF_IFD_EXIF, EXIF_TAG_EXPOSURE_TIME, x.exposure_s, 100000);
  if (x.iso > 0) Short(ed, EXIF_IFD_EXIF, EXIF_TAG_ISO_SPEED_RATINGS, x.iso);
  unsigned char* buf = nullptr;
  unsigned int len = 0;
  exif_data_save_data(ed, &buf, &len);
  exif_data_unref(ed);
  std::vector<unsigned char> out(jpeg.begin(), jpeg.begin() + 2);  // SOI
  out.push_back(0xFF);
  out.push_back(0xE1);
  out.push_back(static_cast<unsigned char>((len + 2) >> 8));
  out.push_back(static_cast<unsigned char>((len + 2) & 0xFF));
  out.insert(out.end(), buf, buf + len);
  std::free(buf);
  out.insert(out.end(), jpeg.begin() + 2, jpeg.end());
  return out;
}

}  // namespace aggscan::test
