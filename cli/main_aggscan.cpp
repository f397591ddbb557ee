// aggscan: the command-line tool. Talks to a running aggscand (status, arm,
// press, ...) and runs offline work (2D morphology of an image or mask,
// simulated captures).
#include <algorithm>
#include <cstdlib>
#include <iostream>
#include <string>
#include <vector>

#include "cli/calibrate_command.h"
#include "cli/client.h"
#include "cli/empty_turntable_command.h"
#include "cli/import_command.h"
#include "cli/masks_command.h"
#include "cli/morph2d_command.h"
#include "cli/morph_command.h"
#include "cli/reconstruct_command.h"
#include "cli/report_command.h"
#include "cli/selftest_command.h"
#include "cli/sim_capture.h"
#include "cli/user_command.h"
#include "cli/validate_command.h"
#include "common/version.h"
#include "pipeline/core/image_io.h"

namespace {

void PrintSelftestUsage(std::ostream& o) {
  o << "  aggscan selftest --config FILE [--json]\n"
       "      open each device of FILE, exercise it briefly (camera: open+configure, turntable:\n"
       "      read status, button: open), report and close; stop aggscand first (it holds them)\n";
}

void PrintCalibrateBoardUsage(std::ostream& o) {
  o << "  aggscan calibrate board --out FILE.png|FILE.pgm [--dpi N] [--margin-mm M] [--config "
       "FILE]\n"
       "      the printable ChArUco board of [calibration] (default 7x5 squares of 30 mm)\n";
}

void PrintCalibrateArucoUsage(std::ostream& o) {
  o << "  aggscan calibrate aruco --out FILE.pgm|FILE.png --config FILE [--dpi N]\n"
       "      the ArUco scale markers of [[rig.aruco_markers]] side by side ([sim] aruco_image)\n";
}

void PrintCalibrateSolveUsage(std::ostream& o) {
  o << "  aggscan calibrate SAMPLE_DIR [--side N] [--state-dir DIR | --out FILE] [--config FILE]\n"
       "                    [--json]\n"
       "      rig calibration (lens, turntable axis, camera pose) from a side captured with the\n"
       "      board lying on the turntable; writes calibration.json, keeps the previous one\n";
}

void PrintCalibrateUsage(std::ostream& o) {
  PrintCalibrateBoardUsage(o);
  PrintCalibrateArucoUsage(o);
  PrintCalibrateSolveUsage(o);
}

void PrintReconstructUsage(std::ostream& o) {
  o << "  aggscan reconstruct SAMPLE_DIR [--state-dir DIR] [--config FILE] [--surface "
       "hull|hull+photo]\n"
       "                      [--poses turntable|turntable+ba|sfm|auto] [--from STAGE]\n"
       "                      [--sfm-whole-frame]\n"
       "      run the worker's stages on a sample now (masks, 2d, calibration, poses, stitch,\n"
       "      surface, morphology) and print results/morphology.json; a stage finished with\n"
       "      the same options and inputs is kept, a changed one runs again with all after\n"
       "      it; --from runs STAGE and every later one again. Without --config: the config\n"
       "      the sample was armed with (SAMPLE_DIR/config.toml), as the worker used it;\n"
       "      --sfm-whole-frame: SfM's features on the whole photos, not the rock's window\n"
       "      (slower; for comparison)\n";
}

void PrintMorphUsage(std::ostream& o) {
  o << "  aggscan morph MESH [--unit mm|cm|m] [--json]\n"
       "      3D morphology of a closed mesh (PLY/OBJ/STL): volume, area, a<=b<=c of the\n"
       "      minimum-volume box, FER, sphericity; open or non-manifold meshes are refused\n";
}

void PrintMorph2dUsage(std::ostream& o) {
  o << "  aggscan morph2d IMAGE_OR_MASK [--text] [--max-megapixels N (100)]\n"
       "      2D morphology of the largest silhouette (JSON: l_max_px, l_min_px, fer_2d,\n"
       "      area_px, perimeter_px, circularity); a photo is segmented first\n";
}

void PrintSimUsage(std::ostream& o) {
  o << "  aggscan sim capture (--seed N | --mesh FILE --unit mm|cm|m) --out DIR\n"
       "                      [--profile paper|full-turn] [--views N] [--width W --height H]\n"
       "                      [--config FILE] [--scene rock|charuco] [--calibration FILE]\n"
       "      capture a simulated rock into a new sample directory, as aggscand would,\n"
       "      plus truth.json and truth/ (ground-truth masks and poses); --scene charuco: the\n"
       "      [calibration] board on the disc instead of a rock (one side over a full turn),\n"
       "      input for `aggscan calibrate`; --calibration: recorded in the sample as\n"
       "      aggscand records state_dir/calibration.json\n";
}

void Usage(std::ostream& o) {
  o << "usage: aggscan COMMAND [ARGS]\n"
       "       aggscan COMMAND --help\n"
       "       aggscan --version\n\n"
       "Daemon commands (talk to aggscand over its HTTP API):\n";
  aggscan::PrintClientUsage(o);
  o << "\nOffline commands:\n";
  PrintSelftestUsage(o);
  PrintCalibrateUsage(o);
  PrintReconstructUsage(o);
  PrintMorphUsage(o);
  PrintMorph2dUsage(o);
  PrintSimUsage(o);
  aggscan::PrintEmptyTurntableUsage(o);
  aggscan::PrintImportUsage(o);
  aggscan::PrintUserUsage(o);
  aggscan::PrintMasksUsage(o);
  aggscan::PrintValidateUsage(o);
  aggscan::PrintReportUsage(o);
}

// --help anywhere after the command word wins over the rest of the line: a
// half-typed command asking for its usage must not start work or fail on the
// options it has so far.
bool AsksForHelp(const std::vector<std::string>& a) {
  return std::any_of(a.begin() + (a.empty() ? 0 : 1), a.end(),
                     [](const std::string& s) { return s == "--help" || s == "-h"; });
}

int Help(void (*print)(std::ostream&)) {
  std::cout << "usage:\n";
  print(std::cout);
  return 0;
}

int SimCommand(const std::vector<std::string>& a) {
  if (AsksForHelp(a)) return Help(PrintSimUsage);
  if (a.size() < 2 || a[1] != "capture") {
    std::cerr << "aggscan sim: expected 'aggscan sim capture ...'\n";
    return 2;
  }
  aggscan::SimCaptureOptions o;
  for (size_t i = 2; i < a.size(); ++i) {
    auto val = [&](const char* name) -> std::string {
      if (i + 1 >= a.size()) {
        std::cerr << "aggscan sim capture: " << name << " needs a value\n";
        std::exit(2);
      }
      return a[++i];
    };
    auto num = [&](const char* name) -> long long {
      const std::string v = val(name);
      char* end = nullptr;
      const long long n = std::strtoll(v.c_str(), &end, 10);
      if (end == v.c_str() || *end != '\0' || n < 0) {
        std::cerr << "aggscan sim capture: " << name << " expects a non-negative integer, got '"
                  << v << "'\n";
        std::exit(2);
      }
      return n;
    };
    if (a[i] == "--seed")
      o.seed = static_cast<uint64_t>(num("--seed"));
    else if (a[i] == "--mesh")
      o.mesh = val("--mesh");
    else if (a[i] == "--unit")
      o.unit = val("--unit");
    else if (a[i] == "--out")
      o.out = val("--out");
    else if (a[i] == "--profile")
      o.profile = val("--profile");
    else if (a[i] == "--config")
      o.config_path = val("--config");
    else if (a[i] == "--width")
      o.width = static_cast<int>(num("--width"));
    else if (a[i] == "--height")
      o.height = static_cast<int>(num("--height"));
    else if (a[i] == "--views")
      o.views_per_side = static_cast<int>(num("--views"));
    else if (a[i] == "--scene")
      o.scene = val("--scene");
    else if (a[i] == "--calibration")
      o.calibration = val("--calibration");
    else {
      std::cerr << "aggscan sim capture: unknown option '" << a[i] << "'\n";
      return 2;
    }
  }
  if (!o.scene.empty() && o.scene != "rock" && o.scene != "charuco") {
    std::cerr << "aggscan sim capture: --scene must be rock or charuco\n";
    return 2;
  }
  if (o.unit != "mm" && o.unit != "cm" && o.unit != "m") {
    std::cerr << "aggscan sim capture: --unit must be mm, cm or m\n";
    return 2;
  }
  return aggscan::RunSimCapture(o, std::cout, std::cerr);
}

}  // namespace

int main(int argc, char** argv) {
  aggscan::KeepFreedImageMemory();  // reconstruct, validate, masks: photo after photo
  std::vector<std::string> args(argv + 1, argv + argc);
  // Global client options may precede the command word.
  std::string cmd;
  for (size_t i = 0; i < args.size(); ++i) {
    if (args[i] == "--url") {
      ++i;
      continue;
    }
    if (args[i] == "--version") {
      std::cout << "aggscan " << aggscan::SoftwareVersion() << "\n";
      return 0;
    }
    if (args[i].rfind("--", 0) == 0) continue;
    cmd = args[i];
    break;
  }
  if (cmd.empty() || cmd == "help" || args[0] == "-h" || args[0] == "--help") {
    Usage(cmd.empty() && args.empty() ? std::cerr : std::cout);
    return args.empty() ? 2 : 0;
  }
  if (cmd == "selftest" && aggscan::IsOfflineSelftest(args)) {
    if (AsksForHelp(args)) return Help(PrintSelftestUsage);
    return aggscan::RunOfflineSelftest(args, std::cout, std::cerr);
  }
  if (aggscan::IsClientCommand(cmd)) return aggscan::RunClientCommand(args, std::cout, std::cerr);
  if (cmd == "morph2d") {
    if (AsksForHelp(args)) return Help(PrintMorph2dUsage);
    std::string path;
    bool json = true;
    aggscan::ImageLimits limits;
    for (size_t i = 1; i < args.size(); ++i) {
      if (args[i] == "--text")
        json = false;
      else if (args[i] == "--json")
        json = true;
      else if (args[i] == "--max-megapixels" && i + 1 < args.size()) {
        char* end = nullptr;
        const double mp = std::strtod(args[++i].c_str(), &end);
        if (end == args[i].c_str() || *end != '\0' || !(mp > 0 && mp <= 10000)) {
          std::cerr << "aggscan morph2d: --max-megapixels expects a number from 0 to 10000, got '"
                    << args[i] << "'\n";
          return 2;
        }
        limits.max_pixels = static_cast<int64_t>(mp * 1e6);
      } else if (path.empty())
        path = args[i];
      else {
        std::cerr << "aggscan morph2d: unexpected argument '" << args[i] << "'\n";
        return 2;
      }
    }
    if (path.empty()) {
      std::cerr << "aggscan morph2d: give an image or mask file\n";
      return 2;
    }
    return aggscan::RunMorph2dCommand(path, json, std::cout, std::cerr, limits);
  }
  if (cmd == "morph") {
    if (AsksForHelp(args)) return Help(PrintMorphUsage);
    std::string path, unit = "mm";
    bool json = false;
    for (size_t i = 1; i < args.size(); ++i) {
      if (args[i] == "--json")
        json = true;
      else if (args[i] == "--unit" && i + 1 < args.size())
        unit = args[++i];
      else if (args[i].rfind("--", 0) == 0) {
        std::cerr << "aggscan morph: unknown option '" << args[i] << "'\n";
        return 2;
      } else if (path.empty())
        path = args[i];
      else {
        std::cerr << "aggscan morph: unexpected argument '" << args[i] << "'\n";
        return 2;
      }
    }
    if (path.empty()) {
      std::cerr << "aggscan morph: give a mesh file (PLY, OBJ or STL)\n";
      return 2;
    }
    return aggscan::RunMorphCommand(path, unit, json, std::cout, std::cerr);
  }
  if (cmd == "reconstruct") {
    if (AsksForHelp(args)) return Help(PrintReconstructUsage);
    return aggscan::RunReconstructCommand({args.begin() + 1, args.end()}, std::cout, std::cerr);
  }
  if (cmd == "sim") return SimCommand(args);
  if (cmd == "user")
    return aggscan::RunUserCommand({args.begin() + 1, args.end()}, std::cin, std::cout, std::cerr);
  if (cmd == "empty-turntable")
    return aggscan::RunEmptyTurntableCommand({args.begin() + 1, args.end()}, std::cout, std::cerr);
  if (cmd == "import")
    return aggscan::RunImportCommand({args.begin() + 1, args.end()}, std::cout, std::cerr);
  if (cmd == "masks")
    return aggscan::RunMasksCommand({args.begin() + 1, args.end()}, std::cout, std::cerr);
  if (cmd == "validate")
    return aggscan::RunValidateCommand({args.begin() + 1, args.end()}, std::cout, std::cerr);
  if (cmd == "report")
    return aggscan::RunReportCommand({args.begin() + 1, args.end()}, std::cout, std::cerr);
  if (cmd == "calibrate") {
    if (AsksForHelp(args)) {
      const std::string form = args.size() > 1 ? args[1] : "";
      if (form == "board") return Help(PrintCalibrateBoardUsage);
      if (form == "aruco") return Help(PrintCalibrateArucoUsage);
      if (!form.empty() && form[0] != '-') return Help(PrintCalibrateSolveUsage);
      return Help(PrintCalibrateUsage);
    }
    return aggscan::RunCalibrateCommand({args.begin() + 1, args.end()}, std::cout, std::cerr);
  }
  std::cerr << "aggscan: unknown command '" << cmd << "'\n\n";
  Usage(std::cerr);
  return 2;
}
