// JPEG encode/decode (libturbojpeg) for the sim camera's stills, and tiny
// PGM/PPM writers for ground-truth masks and debugging images.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <vector>

#include "common/error.h"

namespace aggscan::sim {

struct RgbImage {
  int width = 0;
  int height = 0;
  std::vector<uint8_t> rgb;  // width*height*3
};

/// Encodes packed RGB8 as a baseline JPEG, 4:2:0 subsampling, quality 1..100.
Result<std::vector<unsigned char>> EncodeJpeg(const uint8_t* rgb, int width, int height,
                                              int quality);
/// Decodes a JPEG to packed RGB8.
Result<RgbImage> DecodeJpeg(std::span<const unsigned char> bytes);
/// Writes an 8-bit greyscale binary PGM (P5) atomically (mask: 0/255).
Status WritePgm(const std::vector<uint8_t>& gray, int width, int height, const std::string& path);
/// Writes an RGB8 binary PPM (P6) atomically.
Status WritePpm(const std::vector<uint8_t>& rgb, int width, int height, const std::string& path);

}  // namespace aggscan::sim
