#include "cli/calibrate_command.h"

#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <ctime>
#include <filesystem>

#include "common/fsutil.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/calib/calibrate.h"
#include "pipeline/markers/aruco_scale.h"
#include "store/layout.h"

namespace aggscan {

namespace {

namespace fs = std::filesystem;

std::string F(double v, int digits) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", digits, v);
  return buf;
}

bool ParseNumber(const std::string& s, double* out) {
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(s.c_str(), &end);
  if (s.empty() || *end != '\0' || errno != 0 || !std::isfinite(v)) return false;
  *out = v;
  return true;
}

// Loads a config file; prints its problems.
bool LoadBoardConfig(const std::string& path, Config* config, std::ostream& err) {
  std::vector<ConfigProblem> problems;
  Result<Config> c = LoadConfigFile(path, &problems);
  if (!c) {
    err << "aggscan calibrate: invalid configuration " << path << ":\n";
    for (const auto& p : problems) err << "  " << p.ToString() << "\n";
    if (problems.empty()) err << "  " << c.error().ToString() << "\n";
    return false;
  }
  *config = *c;
  return true;
}

// Options of the printable sheets (`calibrate board`, `calibrate aruco`):
// --out, --config, --dpi, and --margin-mm where the sheet has one.
struct SheetArgs {
  std::string path, config_path;
  double dpi = 300, margin_mm = 10;
};

// 0 when parsed, else the exit code (2, usage) after saying what is wrong.
int ParseSheetArgs(const std::vector<std::string>& a, const std::string& cmd, bool margin,
                   SheetArgs* o, std::ostream& err) {
  for (size_t i = 1; i < a.size(); ++i) {
    auto val = [&](const char* name, std::string* v) {
      if (i + 1 >= a.size()) {
        err << "aggscan calibrate " << cmd << ": " << name << " needs a value\n";
        return false;
      }
      *v = a[++i];
      return true;
    };
    std::string v;
    if (a[i] == "--out") {
      if (!val("--out", &o->path)) return 2;
    } else if (a[i] == "--config") {
      if (!val("--config", &o->config_path)) return 2;
    } else if (a[i] == "--dpi") {
      if (!val("--dpi", &v)) return 2;
      if (!ParseNumber(v, &o->dpi) || o->dpi < 50 || o->dpi > 2400) {
        err << "aggscan calibrate " << cmd << ": --dpi expects 50..2400, got '" << v << "'\n";
        return 2;
      }
    } else if (margin && a[i] == "--margin-mm") {
      if (!val("--margin-mm", &v)) return 2;
      if (!ParseNumber(v, &o->margin_mm) || o->margin_mm < 0 || o->margin_mm > 200) {
        err << "aggscan calibrate " << cmd << ": --margin-mm expects 0..200, got '" << v << "'\n";
        return 2;
      }
    } else {
      err << "aggscan calibrate " << cmd << ": unknown argument '" << a[i] << "'\n";
      return 2;
    }
  }
  return 0;
}

int BoardCommand(const std::vector<std::string>& a, std::ostream& out, std::ostream& err) {
  SheetArgs o;
  if (int rc = ParseSheetArgs(a, "board", true, &o, err); rc != 0) return rc;
  const std::string& path = o.path;
  const std::string& config_path = o.config_path;
  const double dpi = o.dpi, margin_mm = o.margin_mm;
  if (path.empty()) {
    err << "aggscan calibrate board: --out FILE.png (or FILE.pgm) is required\n";
    return 2;
  }
  Config config;
  if (!config_path.empty() && !LoadBoardConfig(config_path, &config, err)) return 78;
  const CalibrationConfig& b = config.calibration;
  if (Status s = WriteBoardImage(b, path, dpi / 25.4, margin_mm); !s) {
    err << "aggscan calibrate board: " << s.error().ToString() << "\n";
    return s.error().cls == ErrorClass::kInvalidArgument ? 2 : 1;
  }
  out << "board written to " << path << ": " << b.squares_x << "x" << b.squares_y << " squares of "
      << F(b.square_mm, 1) << " mm (" << F(b.squares_x * b.square_mm, 1) << " x "
      << F(b.squares_y * b.square_mm, 1) << " mm), markers " << F(b.marker_mm, 1) << " mm, "
      << b.dictionary << ", " << F(dpi, 0) << " dpi, margin " << F(margin_mm, 1) << " mm\n"
      << "print it at 100 % (no fit-to-page), measure a square and write the true size into\n"
      << "[calibration] square_mm / marker_mm; lay it flat on the turntable.\n";
  return 0;
}

// The ArUco scale markers of rig.aruco_markers side by side (the sim draws
// them from this image; printed, cut apart and laid on the disc they are the
// rig's markers).
int ArucoCommand(const std::vector<std::string>& a, std::ostream& out, std::ostream& err) {
  SheetArgs o;
  if (int rc = ParseSheetArgs(a, "aruco", false, &o, err); rc != 0) return rc;
  const std::string& path = o.path;
  const std::string& config_path = o.config_path;
  const double dpi = o.dpi;
  if (path.empty()) {
    err << "aggscan calibrate aruco: --out FILE.pgm (or FILE.png) is required\n";
    return 2;
  }
  if (config_path.empty()) {
    err << "aggscan calibrate aruco: --config FILE is required: its [[rig.aruco_markers]] name the "
           "markers to draw\n";
    return 2;
  }
  Config config;
  if (!LoadBoardConfig(config_path, &config, err)) return 78;
  const RigConfig& rig = config.rig;
  if (rig.aruco_markers.empty()) {
    err << "aggscan calibrate aruco: " << config_path
        << " lists no [[rig.aruco_markers]]; add them (id, x_mm, y_mm) first\n";
    return 2;
  }
  if (Status s = WriteArucoSheet(rig, path, dpi / 25.4); !s) {
    err << "aggscan calibrate aruco: " << s.error().ToString() << "\n";
    return s.error().cls == ErrorClass::kInvalidArgument ? 2 : 1;
  }
  out << rig.aruco_markers.size() << " ArUco marker(s) of " << rig.aruco_dictionary
      << " written to " << path << " side by side, ids";
  for (const ArucoMarker& m : rig.aruco_markers) out << " " << m.id;
  out << ", " << F(rig.aruco_size_mm, 1) << " mm each at " << F(dpi, 0) << " dpi\n"
      << "name it in [sim] aruco_image for the sim camera; for the rig print it at 100 %, cut\n"
      << "each marker out with a white margin of at least a quarter of its side, measure the\n"
      << "black squares into rig.aruco_size_mm and lay them flat at the configured centres.\n";
  return 0;
}

int SolveCommand(const std::vector<std::string>& a, std::ostream& out, std::ostream& err) {
  std::string sample, state_dir, out_path, config_path;
  int side = 1;
  bool json = false;
  for (size_t i = 0; i < a.size(); ++i) {
    auto val = [&](const char* name, std::string* v) {
      if (i + 1 >= a.size()) {
        err << "aggscan calibrate: " << name << " needs a value\n";
        return false;
      }
      *v = a[++i];
      return true;
    };
    std::string v;
    if (a[i] == "--side") {
      if (!val("--side", &v)) return 2;
      double d = 0;
      if (!ParseNumber(v, &d) || d < 1 || d > 4 || d != std::floor(d)) {
        err << "aggscan calibrate: --side expects 1..4, got '" << v << "'\n";
        return 2;
      }
      side = static_cast<int>(d);
    } else if (a[i] == "--state-dir") {
      if (!val("--state-dir", &state_dir)) return 2;
    } else if (a[i] == "--out") {
      if (!val("--out", &out_path)) return 2;
    } else if (a[i] == "--config") {
      if (!val("--config", &config_path)) return 2;
    } else if (a[i] == "--json") {
      json = true;
    } else if (a[i].rfind("--", 0) == 0) {
      err << "aggscan calibrate: unknown option '" << a[i] << "'\n";
      return 2;
    } else if (sample.empty()) {
      sample = a[i];
    } else {
      err << "aggscan calibrate: unexpected argument '" << a[i] << "'\n";
      return 2;
    }
  }
  if (sample.empty()) {
    err << "aggscan calibrate: give the sample directory of a board capture (or 'board --out "
           "FILE')\n";
    return 2;
  }
  if (!state_dir.empty() && !out_path.empty()) {
    err << "aggscan calibrate: give --state-dir DIR or --out FILE, not both\n";
    return 2;
  }
  while (sample.size() > 1 && sample.back() == '/') sample.pop_back();
  if (!fs::is_directory(sample)) {
    err << "aggscan calibrate: " << sample << " is not a sample directory\n";
    return 1;
  }
  if (out_path.empty()) {
    // STATE_DIR/samples/ID: the calibration belongs to that state directory.
    if (state_dir.empty()) state_dir = layout::StateDirOfSample(sample);
    if (state_dir.empty()) {
      err << "aggscan calibrate: " << sample
          << " is not inside a state directory (STATE_DIR/samples/ID); say where the calibration "
             "goes "
             "with --state-dir DIR or --out FILE\n";
      return 2;
    }
    out_path = CalibrationPath(state_dir);
  }

  // The board: --config, else the one the sample was captured with.
  Config config;
  if (!config_path.empty()) {
    if (!LoadBoardConfig(config_path, &config, err)) return 78;
  } else if (PathExists(sample + "/" + layout::kConfigCopy)) {
    if (!LoadBoardConfig(sample + "/" + layout::kConfigCopy, &config, err)) {
      err << "  (the sample's config copy is unusable: give the board with --config FILE)\n";
      return 78;
    }
  }
  const CalibrationConfig& b = config.calibration;

  Result<CalibrationResult> r = CalibrateSampleSide(sample, side, b);
  if (!r) {
    err << "aggscan calibrate: " << r.error().ToString() << "\n";
    return 1;
  }
  Result<std::string> prev = InstallRigCalibration(out_path, r->cal);
  if (!prev) {
    err << "aggscan calibrate: cannot install " << out_path << ": " << prev.error().ToString()
        << "\n";
    return 1;
  }
  const RigCalibration& cal = r->cal;
  if (json) {
    out << CalibrationToJson(cal).dump(2) << "\n";
  } else {
    const CameraModel& m = cal.camera;
    const auto C = cal.CameraCentreTable0();
    const double horiz = std::hypot(C[0], C[1]);
    const double dist = std::hypot(horiz, C[2]);
    const double elev = std::atan2(C[2], horiz) * 180 / M_PI;
    // Optical axis in the table frame: the third row of R.
    const double down = std::asin(std::clamp(-cal.R_cam_table0[8], -1.0, 1.0)) * 180 / M_PI;
    out << "calibration written to " << out_path << "\n"
        << "  views used " << cal.views_used << " of " << r->views_total << ", corners "
        << cal.corners_used << ", reprojection RMS " << F(cal.reprojection_rms_px, 3)
        << " px (worst view " << F(r->max_view_rms_px, 3) << " px)\n"
        << "  lens " << m.width << "x" << m.height << ": fx = fy = " << F(m.fx, 1)
        << " px, centre (" << F(m.cx, 1) << ", " << F(m.cy, 1) << ") px (fixed: one plane), k1 "
        << F(m.k1, 4) << ", k2 " << F(m.k2, 4)
        << (r->k2_estimated ? ""
                            : " (fixed: the board covers too little of the image to measure it)")
        << "\n"
        << "  standard deviations: fx " << F(r->sigma_fx_px, 2) << " px, k1 " << F(r->sigma_k1, 4)
        << "\n"
        << "  camera " << F(dist, 1) << " mm from the table origin, " << F(C[2], 1)
        << " mm above the disc, elevation " << F(elev, 2) << " deg; optical axis " << F(down, 2)
        << " deg below horizontal\n"
        << "  board on the disc: centre (" << F(r->board_x_mm, 1) << ", " << F(r->board_y_mm, 1)
        << ") mm, yaw " << F(r->board_yaw_deg, 2) << " deg\n"
        << "  " << F(r->seconds, 1) << " s\n";
  }
  for (const auto& s : r->skipped) err << "aggscan calibrate: not used: " << s << "\n";
  if (r->outlier_corners > 0) {
    err << "aggscan calibrate: " << r->outlier_corners
        << " corner(s) off by more than 2 px were down-weighted (glare, a crease in the paper?)\n";
  }
  if (!prev->empty())
    err << "aggscan calibrate: the previous calibration is kept as " << *prev << "\n";
  return 0;
}

}  // namespace

int RunCalibrateCommand(const std::vector<std::string>& args, std::ostream& out,
                        std::ostream& err) {
  if (!args.empty() && args[0] == "board") return BoardCommand(args, out, err);
  if (!args.empty() && args[0] == "aruco") return ArucoCommand(args, out, err);
  return SolveCommand(args, out, err);
}

}  // namespace aggscan
