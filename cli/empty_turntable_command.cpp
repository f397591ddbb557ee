#include "cli/empty_turntable_command.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>

#include "common/fsutil.h"
#include "pipeline/core/image_io.h"
#include "store/empty_turntable.h"
#include "store/layout.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;

void PrintSet(std::ostream& out, const EmptyTurntableSet& s) {
  double lo = 360, hi = -360;
  for (const auto& v : s.views) lo = std::min(lo, v.angle_deg), hi = std::max(hi, v.angle_deg);
  char buf[160];
  std::snprintf(buf, sizeof buf, "%zu photos of %dx%d, angles %.1f .. %.1f deg", s.views.size(),
                s.width, s.height, lo, hi);
  out << "empty-turntable set " << s.id << ": " << buf << "\n"
      << "  from " << s.source << (s.captured_utc.empty() ? "" : ", captured " + s.captured_utc)
      << "\n";
}

}  // namespace

void PrintEmptyTurntableUsage(std::ostream& o) {
  o << "  aggscan empty-turntable SAMPLE_DIR [--side N] [--state-dir DIR]\n"
       "      side N (1) of a capture with nothing on the disc becomes the rig's empty-turntable\n"
       "      photos: samples armed from then on are masked against the photo shot at each view's\n"
       "      angle (a wooden disc, a dark mat or a gravel floor drop out); shoot them again when\n"
       "      the lights, the disc or the camera settings change\n"
       "  aggscan empty-turntable --state-dir DIR\n"
       "      the set in use\n";
}

int RunEmptyTurntableCommand(const std::vector<std::string>& args, std::ostream& out,
                             std::ostream& err) {
  // Before anything else: with a sample named, the command installs a set.
  if (std::any_of(args.begin(), args.end(),
                  [](const std::string& a) { return a == "--help" || a == "-h"; })) {
    out << "usage:\n";
    PrintEmptyTurntableUsage(out);
    return 0;
  }
  std::string sample, state_dir;
  int side = 1;
  for (size_t i = 0; i < args.size(); ++i) {
    const bool has = i + 1 < args.size();
    if (args[i] == "--side" && has) {
      char* end = nullptr;
      const long v = std::strtol(args[++i].c_str(), &end, 10);
      if (*end != '\0' || v < 1 || v > 8) {
        err << "aggscan empty-turntable: --side expects 1..8, got '" << args[i] << "'\n";
        return 2;
      }
      side = static_cast<int>(v);
    } else if (args[i] == "--state-dir" && has) {
      state_dir = args[++i];
    } else if (!args[i].empty() && args[i][0] == '-') {
      err << "aggscan empty-turntable: unknown option or missing value '" << args[i] << "'\n";
      PrintEmptyTurntableUsage(err);
      return 2;
    } else if (sample.empty()) {
      sample = args[i];
    } else {
      err << "aggscan empty-turntable: unexpected argument '" << args[i] << "'\n";
      return 2;
    }
  }
  if (sample.empty()) {
    if (state_dir.empty()) {
      err << "aggscan empty-turntable: give the sample directory of a capture of the empty "
             "turntable, or "
             "--state-dir DIR to show the set in use\n";
      PrintEmptyTurntableUsage(err);
      return 2;
    }
    Result<EmptyTurntableSet> cur = CurrentEmptyTurntableSet(state_dir);
    if (!cur) {
      err << "aggscan empty-turntable: " << cur.error().message << "\n";
      return cur.error().cls == ErrorClass::kNotFound ? 3 : 1;
    }
    PrintSet(out, *cur);
    return 0;
  }
  while (sample.size() > 1 && sample.back() == '/') sample.pop_back();
  if (!fs::is_directory(sample)) {
    err << "aggscan empty-turntable: " << sample << " is not a sample directory\n";
    return 1;
  }
  if (state_dir.empty()) state_dir = layout::StateDirOfSample(sample);
  if (state_dir.empty()) {
    err << "aggscan empty-turntable: " << sample
        << " is not inside a state directory (STATE_DIR/samples/ID); say which rig's photos these "
           "are "
           "with --state-dir DIR\n";
    return 2;
  }
  // Every photo decodes and all are of one size: the masks compare them with
  // the rock's photos pixel by pixel.
  const std::string side_dir = sample + "/" + layout::SideDirName(side);
  int width = 0, height = 0;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(side_dir, ec)) {
    const std::string name = e.path().filename().string();
    if (!name.starts_with("view_") || !name.ends_with(".jpg")) continue;
    Result<cv::Mat> img = LoadImage(e.path().string(), ImageMode::kColor);
    if (!img) {
      err << "aggscan empty-turntable: " << img.error().message
          << "; shoot the empty turntable again\n";
      return 1;
    }
    if (width == 0) width = img->cols, height = img->rows;
    if (img->cols != width || img->rows != height) {
      err << "aggscan empty-turntable: " << e.path().string() << " is " << img->cols << "x"
          << img->rows << ", other photos of the side " << width << "x" << height
          << "; shoot the empty turntable again with one camera mode\n";
      return 1;
    }
  }
  if (ec || width == 0) {
    err << "aggscan empty-turntable: " << side_dir << " holds no photos (view_NNN.jpg)\n";
    return 1;
  }
  Result<EmptyTurntableSet> set = InstallEmptyTurntableSet(state_dir, sample, side, width, height);
  if (!set) {
    err << "aggscan empty-turntable: " << set.error().ToString() << "\n";
    return 1;
  }
  out << "installed for " << state_dir << "\n";
  PrintSet(out, *set);
  out << "  samples armed from now on are masked against it\n";
  return 0;
}

}  // namespace aggscan
