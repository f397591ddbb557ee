#include "drivers/sim/board.h"

#include <algorithm>
#include <cctype>
#include <cmath>

#include "common/fsutil.h"

namespace aggscan::sim {

namespace {

// Next header token of a PNM file: skips whitespace and '#' comments.
bool NextToken(const std::string& s, size_t* pos, std::string* tok) {
  size_t i = *pos;
  for (;;) {
    while (i < s.size() && std::isspace(static_cast<unsigned char>(s[i]))) ++i;
    if (i < s.size() && s[i] == '#') {
      while (i < s.size() && s[i] != '\n') ++i;
      continue;
    }
    break;
  }
  const size_t start = i;
  while (i < s.size() && !std::isspace(static_cast<unsigned char>(s[i]))) ++i;
  if (i == start) return false;
  *tok = s.substr(start, i - start);
  *pos = i;
  return true;
}

bool ToInt(const std::string& t, int* out) {
  if (t.empty() || t.size() > 9) return false;
  int v = 0;
  for (char c : t) {
    if (c < '0' || c > '9') return false;
    v = v * 10 + (c - '0');
  }
  *out = v;
  return true;
}

}  // namespace

Result<GrayImage> ReadPgm(const std::string& path) {
  Result<std::string> data = ReadFile(path);
  if (!data) return data.error();
  const std::string& s = *data;
  auto bad = [&](const std::string& why) {
    return MakeError(ErrorClass::kCorrupt, path + " is not an 8-bit binary PGM (P5): " + why);
  };
  size_t pos = 0;
  std::string magic, ws, hs, ms;
  if (!NextToken(s, &pos, &magic) || magic != "P5") return bad("wrong magic number");
  GrayImage img;
  int maxval = 0;
  if (!NextToken(s, &pos, &ws) || !NextToken(s, &pos, &hs) || !NextToken(s, &pos, &ms) ||
      !ToInt(ws, &img.width) || !ToInt(hs, &img.height) || !ToInt(ms, &maxval)) {
    return bad("damaged header");
  }
  if (img.width <= 0 || img.height <= 0 || img.width > 65535 || img.height > 65535) {
    return bad("bad size " + ws + "x" + hs);
  }
  if (maxval <= 0 || maxval > 255) return bad("maxval " + ms + " (16-bit PGM is not supported)");
  ++pos;  // the single whitespace after maxval
  const size_t n = static_cast<size_t>(img.width) * img.height;
  if (s.size() < pos + n) return bad("truncated pixel data");
  img.pixels.assign(s.begin() + static_cast<std::ptrdiff_t>(pos),
                    s.begin() + static_cast<std::ptrdiff_t>(pos + n));
  if (maxval != 255) {
    for (auto& p : img.pixels)
      p = static_cast<uint8_t>(
          std::lround(std::min(p, static_cast<uint8_t>(maxval)) * 255.0 / maxval));
  }
  return img;
}

Result<SimBoard> LoadSimBoard(const Config& config) {
  const CalibrationConfig& b = config.calibration;
  const std::string& path = config.sim.board_image;
  if (path.empty()) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "sim.scene = \"charuco\" needs sim.board_image; write one with `aggscan "
                     "calibrate board --out FILE.pgm --margin-mm 0`");
  }
  Result<GrayImage> img = ReadPgm(path);
  if (!img) {
    return MakeError(ErrorClass::kInvalidConfig, "sim.board_image: cannot use " + path,
                     img.error().ToString());
  }
  SimBoard board;
  board.width_mm = b.squares_x * b.square_mm;
  board.height_mm = b.squares_y * b.square_mm;
  const double want = board.width_mm / board.height_mm;
  const double got = static_cast<double>(img->width) / img->height;
  if (std::abs(got / want - 1.0) > 0.01) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "sim.board_image " + path + " is " + std::to_string(img->width) + "x" +
                         std::to_string(img->height) + " px, not the " +
                         std::to_string(b.squares_x) + "x" + std::to_string(b.squares_y) +
                         " squares area of the [calibration] board; write it with `aggscan "
                         "calibrate board --out FILE.pgm --margin-mm 0` from the same config");
  }
  board.image = std::move(img).value();
  board.x_mm = config.sim.board_x_mm;
  board.y_mm = config.sim.board_y_mm;
  board.yaw_deg = config.sim.board_yaw_deg;
  return board;
}

Result<std::vector<SimArucoMarker>> LoadSimArucoMarkers(const Config& config) {
  const RigConfig& rig = config.rig;
  std::vector<SimArucoMarker> out;
  if (rig.aruco_markers.empty()) return out;
  const std::string& path = config.sim.aruco_image;
  if (path.empty()) {
    return MakeError(
        ErrorClass::kInvalidConfig,
        "rig.aruco_markers needs sim.aruco_image for the sim camera to draw them; "
        "write one with `aggscan calibrate aruco --out FILE.pgm` from the same config");
  }
  Result<GrayImage> img = ReadPgm(path);
  if (!img) {
    return MakeError(ErrorClass::kInvalidConfig, "sim.aruco_image: cannot use " + path,
                     img.error().ToString());
  }
  const int n = static_cast<int>(rig.aruco_markers.size());
  const int side = img->height;
  if (img->width != n * side) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "sim.aruco_image " + path + " is " + std::to_string(img->width) + "x" +
                         std::to_string(img->height) + " px, not the " + std::to_string(n) +
                         " square markers of rig.aruco_markers side by side; write it with "
                         "`aggscan calibrate aruco --out FILE.pgm` from the same config");
  }
  for (int k = 0; k < n; ++k) {
    const ArucoMarker& m = rig.aruco_markers[static_cast<size_t>(k)];
    SimArucoMarker s;
    s.image.width = side;
    s.image.height = side;
    s.image.pixels.resize(static_cast<size_t>(side) * side);
    for (int r = 0; r < side; ++r) {
      const auto* row =
          &img->pixels[static_cast<size_t>(r) * img->width + static_cast<size_t>(k) * side];
      std::copy(row, row + side, &s.image.pixels[static_cast<size_t>(r) * side]);
    }
    s.size_mm = rig.aruco_size_mm;
    s.x_mm = m.x_mm;
    s.y_mm = m.y_mm;
    s.yaw_deg = m.yaw_deg;
    out.push_back(std::move(s));
  }
  return out;
}

}  // namespace aggscan::sim
