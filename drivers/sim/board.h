// The calibration board of the sim's "charuco" scene: the [calibration]
// ChArUco board printed on paper and lying flat on the disc. The sim does not
// link OpenCV (aggscand links the drivers), so it reads the board as a
// greyscale image file that `aggscan calibrate board --out FILE.pgm
// --margin-mm 0` writes, and maps it onto the squares area of the board.
//
// Board frame (as in config.h, CalibrationConfig): origin at the centre of the
// squares area, x along the image's columns, y towards the image's top row, z
// up out of the paper. Image pixel (c, r) covers x in [c, c+1) * width_mm / W
// - width_mm / 2 and y in (H/2 - [r, r+1)) * height_mm / H. Turntable frame:
// p_turntable = Rz(yaw_deg) * p_board + (x_mm, y_mm, 0).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "common/error.h"
#include "config/config.h"

namespace aggscan::sim {

inline constexpr double kBoardPaperMarginMm = 10.0;  // white paper around the squares area
inline constexpr float kPaperAlbedo = 0.85f;         // printer paper
inline constexpr float kInkAlbedo = 0.05f;           // laser-printer black

struct GrayImage {
  int width = 0;
  int height = 0;
  std::vector<uint8_t> pixels;  // width*height, row-major
};

/// Reads an 8-bit binary PGM (P5, maxval <= 255; comments allowed).
Result<GrayImage> ReadPgm(const std::string& path);

struct SimBoard {
  GrayImage image;                         // the squares area, no margin
  double width_mm = 0, height_mm = 0;      // squares_x * square_mm, squares_y * square_mm
  double x_mm = 0, y_mm = 0, yaw_deg = 0;  // pose on the disc (turntable frame)
};

/// Loads sim.board_image for the [calibration] board; kInvalidConfig when the
/// file is unreadable or its aspect ratio is not the board's (a margin, or
/// another board), with what to do.
Result<SimBoard> LoadSimBoard(const Config& config);

/// One ArUco scale marker of rig.aruco_markers as the sim draws it: its black
/// square (the marker image, x along its columns, y towards its top row) on a
/// white paper square kArucoPaperMarginFrac * size_mm wider on every side.
struct SimArucoMarker {
  GrayImage image;  // the black square only, no margin
  double size_mm = 0;
  double x_mm = 0, y_mm = 0, yaw_deg = 0;  // pose on the disc (turntable frame)
};

/// Loads sim.aruco_image (the markers side by side, in rig.aruco_markers
/// order, each size x size pixels: `aggscan calibrate aruco --out FILE.pgm`)
/// and cuts it into the markers; empty when rig.aruco_markers is. kInvalidConfig
/// when the file is missing, unreadable or not N squares wide, with what to do.
Result<std::vector<SimArucoMarker>> LoadSimArucoMarkers(const Config& config);

}  // namespace aggscan::sim
