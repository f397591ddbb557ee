// What a phone or a DSLR writes into its photos that a measurement needs:
// the camera, the lens's focal length (real and 35 mm equivalent), the focal
// plane's resolution (its sensor size), the orientation the pixels must be
// turned by, and when the photo was taken. Read with libexif from JPEG files
// (the EXIF APP1 segment); a photo without EXIF has none of them.
#pragma once

#include <optional>
#include <string>

#include "common/error.h"

namespace aggscan {

struct PhotoExif {
  std::string make, model;         // "" when absent
  std::optional<int> orientation;  // 1..8 (TIFF/EXIF Orientation)
  std::optional<double> focal_mm;
  std::optional<double> focal_35mm;                // FocalLengthIn35mmFilm
  std::optional<double> focal_plane_x_res_per_mm;  // FocalPlaneXResolution in pixels per mm
  std::optional<int> pixel_x, pixel_y;             // PixelXDimension, PixelYDimension
  std::optional<std::string> datetime_original;    // "YYYY:MM:DD HH:MM:SS"
  std::optional<double> time_s;                    // DateTimeOriginal (+SubSecTimeOriginal),
                                                   // seconds of the camera's clock (as UTC)
  std::optional<double> exposure_s, f_number;
  std::optional<int> iso;

  /// "Make Model", trimmed; "" when neither is known.
  std::string Camera() const;
  /// The sensor's width in mm along the EXIF pixel x axis, from the focal
  /// plane resolution and PixelXDimension; none when either is missing.
  std::optional<double> SensorWidthMm() const;
};

/// Reads the EXIF of a JPEG file. A file without EXIF (or not a JPEG) gives
/// an empty PhotoExif; a file that cannot be read is kNotFound / kIo.
Result<PhotoExif> ReadExif(const std::string& path);

/// Seconds from "YYYY:MM:DD HH:MM:SS" (taken as UTC); none when malformed.
std::optional<double> ExifTimeSeconds(const std::string& datetime);

}  // namespace aggscan
