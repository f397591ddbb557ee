#include "cli/import_command.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <set>

#include "common/fsutil.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/core/exif.h"
#include "pipeline/core/stats.h"
#include "pipeline/markers/aruco_scale.h"
#include "pipeline/markers/markers.h"
#include "store/layout.h"
#include "store/sample_store.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr const char* kCmd = "aggscan import";
// A 35 mm frame's diagonal: the "35 mm equivalent" focal length is defined
// against it (CIPA DC-008), whatever the sensor's aspect ratio.
constexpr double kFullFrameDiagonalMm = 43.2666;
// A photo whose fine detail is below this fraction of its side's median is
// out of focus (or shaken); one with more than this fraction of its pixels
// white in every channel is over-exposed; one whose median grey is below
// this is under-exposed.
constexpr double kMinFocusRatio = 0.35;
constexpr double kMaxBlownFraction = 0.05;
constexpr double kMinMedianGrey = 20.0;
// Views of a side that must show two or more scale references (labels or
// ArUco markers): each label is triangulated from at least two views, and
// three labels make the scale.
constexpr int kMinScaleViews = 3;

struct Options {
  std::string dir, id, out, config, calibration;
  std::optional<double> focal_mm, sensor_mm, gap_s;
  int min_views = 8;
  bool no_scale = false, skip_bad = false, moving_camera = false;
};

struct Photo {
  std::string path, name;  // name: relative to DIR
  int folder = -1;         // side folder index, -1 for DIR itself
  PhotoExif exif;
  bool jpeg = false;
  int width = 0, height = 0;  // upright
  double focus = 0, blown = 0, median_grey = 0;
  int references = 0;  // labels + ArUco markers seen
  std::string problem;
};

bool IsPhoto(const fs::path& p) {
  std::string e = p.extension().string();
  std::transform(e.begin(), e.end(), e.begin(), [](unsigned char c) { return std::tolower(c); });
  return e == ".jpg" || e == ".jpeg" || e == ".png" || e == ".tif" || e == ".tiff";
}

bool IsJpeg(const std::string& path) {
  auto head = ReadFile(path);
  return head && head->size() > 3 && static_cast<unsigned char>((*head)[0]) == 0xFF &&
         static_cast<unsigned char>((*head)[1]) == 0xD8;
}

std::vector<fs::path> PhotosIn(const fs::path& dir) {
  std::vector<fs::path> v;
  for (const auto& e : fs::directory_iterator(dir)) {
    if (e.is_regular_file() && IsPhoto(e.path()) && e.path().filename().string()[0] != '.')
      v.push_back(e.path());
  }
  std::sort(v.begin(), v.end());
  return v;
}

std::string Fmt(const char* f, double v) {
  char b[64];
  std::snprintf(b, sizeof b, f, v);
  return b;
}

// Decodes a photo upright (OpenCV applies the EXIF orientation of a JPEG)
// and measures what the checks need.
void Measure(Photo* p, const RigConfig& rig) {
  const cv::Mat bgr = cv::imread(p->path, cv::IMREAD_COLOR);
  if (bgr.empty()) {
    p->problem = "cannot be decoded as an image";
    return;
  }
  p->width = bgr.cols;
  p->height = bgr.rows;
  cv::Mat grey, small, lap;
  cv::cvtColor(bgr, grey, cv::COLOR_BGR2GRAY);
  const double scale = std::min(1.0, 1008.0 / std::max(grey.cols, grey.rows));
  cv::resize(grey, small, cv::Size(), scale, scale, cv::INTER_AREA);
  cv::Laplacian(small, lap, CV_32F);
  cv::Scalar mean, sd;
  cv::meanStdDev(lap, mean, sd);
  p->focus = sd[0] * sd[0];
  std::vector<cv::Mat> ch;
  cv::split(bgr, ch);
  cv::Mat white = (ch[0] >= 254) & (ch[1] >= 254) & (ch[2] >= 254);
  p->blown = static_cast<double>(cv::countNonZero(white)) / static_cast<double>(white.total());
  std::vector<uchar> g(small.begin<uchar>(), small.end<uchar>());
  std::nth_element(g.begin(), g.begin() + static_cast<long>(g.size() / 2), g.end());
  p->median_grey = g.empty() ? 0 : g[g.size() / 2];
  std::vector<std::string> labels;
  for (const RigMarker& m : rig.markers) labels.push_back(m.color);
  const cv::Mat none = cv::Mat::zeros(bgr.size(), CV_8U);
  if (auto vm = DetectViewMarkers(bgr, none, labels, {}, nullptr))
    p->references += static_cast<int>(vm->labels.size());
  if (!rig.aruco_markers.empty()) {
    if (auto a = DetectArucoMarkers(bgr, none, rig, nullptr))
      p->references += static_cast<int>(a->markers.size());
  }
}

// Sides of a flat folder: in the order taken, split at long pauses (the
// operator flipping the rock).
std::vector<std::vector<Photo*>> SplitByTime(std::vector<Photo>& photos,
                                             std::optional<double> gap_s, std::string* how) {
  std::vector<Photo*> order;
  order.reserve(photos.size());
  for (Photo& p : photos) order.push_back(&p);
  const bool timed = std::all_of(order.begin(), order.end(),
                                 [](const Photo* p) { return p->exif.time_s.has_value(); });
  if (!timed) {
    *how = "one side: not every photo has an EXIF time (put each side in a sub-folder to split)";
    return {order};
  }
  std::stable_sort(order.begin(), order.end(), [](const Photo* a, const Photo* b) {
    return *a->exif.time_s < *b->exif.time_s;
  });
  std::vector<double> steps;
  for (size_t i = 1; i < order.size(); ++i)
    steps.push_back(*order[i]->exif.time_s - *order[i - 1]->exif.time_s);
  double limit = 0;
  if (gap_s) {
    limit = *gap_s;
  } else {
    limit = std::max(30.0, 5.0 * Median(steps));
  }
  std::vector<std::vector<Photo*>> sides(1);
  for (size_t i = 0; i < order.size(); ++i) {
    if (i > 0 && steps[i - 1] > limit) sides.emplace_back();
    sides.back().push_back(order[i]);
  }
  *how = std::to_string(sides.size()) + " side(s) by EXIF time, split at pauses over " +
         Fmt("%.0f", limit) + " s";
  return sides;
}

int Usage(std::ostream& err, const std::string& what) {
  err << kCmd << ": " << what << "\nusage:\n";
  PrintImportUsage(err);
  return 2;
}

}  // namespace

void PrintImportUsage(std::ostream& o) {
  o << "  aggscan import DIR --id ID [--out SAMPLE_DIR] [--config FILE] [--calibration FILE]\n"
       "                 [--focal-mm F --sensor-mm W] [--gap SECONDS] [--min-views N]\n"
       "                 [--no-scale] [--skip-bad] [--moving-camera]\n"
       "      photos from a phone or a DSLR (JPEG, PNG, TIFF) made into a sample directory\n"
       "      (SAMPLE_DIR, default ./ID) for `aggscan reconstruct`: one side per sub-folder,\n"
       "      else split at pauses in the EXIF times; EXIF orientation applied; the focal\n"
       "      from --focal-mm/--sensor-mm, the EXIF 35 mm equivalent, or the EXIF focal\n"
       "      length and focal plane resolution. --calibration: a rig calibration of this\n"
       "      camera (the disc's labels then give each view's angle). Refused, with what\n"
       "      to do: too few views, photos out of focus or badly exposed (--skip-bad\n"
       "      leaves them out), mixed cameras without a calibration, no scale reference\n"
       "      in enough views (--no-scale imports anyway: the views can be posed, not\n"
       "      measured). --moving-camera: the rock lay still and the camera was walked\n"
       "      round it (photos in any order): SfM poses every view, the labels or ArUco\n"
       "      markers round the rock give the scale\n";
}

int RunImportCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  // Before anything else, wherever it stands: help does nothing else.
  if (std::any_of(args.begin(), args.end(),
                  [](const std::string& a) { return a == "--help" || a == "-h"; })) {
    out << "usage:\n";
    PrintImportUsage(out);
    return 0;
  }
  Options o;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    const bool has = i + 1 < args.size();
    auto number = [&](std::optional<double>* v, double lo, double hi) {
      char* end = nullptr;
      const double x = std::strtod(args[++i].c_str(), &end);
      if (!end || *end != '\0' || !(x >= lo && x <= hi)) return false;
      *v = x;
      return true;
    };
    if (a == "--id" && has) {
      o.id = args[++i];
    } else if (a == "--out" && has) {
      o.out = args[++i];
    } else if (a == "--config" && has) {
      o.config = args[++i];
    } else if (a == "--calibration" && has) {
      o.calibration = args[++i];
    } else if (a == "--focal-mm" && has) {
      if (!number(&o.focal_mm, 0.5, 2000)) return Usage(err, "--focal-mm expects 0.5..2000");
    } else if (a == "--sensor-mm" && has) {
      if (!number(&o.sensor_mm, 1, 100)) return Usage(err, "--sensor-mm expects 1..100 (width)");
    } else if (a == "--gap" && has) {
      if (!number(&o.gap_s, 0.1, 86400)) return Usage(err, "--gap expects 0.1..86400 seconds");
    } else if (a == "--min-views" && has) {
      std::optional<double> v;
      if (!number(&v, 3, 1000)) return Usage(err, "--min-views expects 3..1000");
      o.min_views = static_cast<int>(*v);
    } else if (a == "--no-scale") {
      o.no_scale = true;
    } else if (a == "--skip-bad") {
      o.skip_bad = true;
    } else if (a == "--moving-camera") {
      o.moving_camera = true;
    } else if (!a.empty() && a[0] != '-' && o.dir.empty()) {
      o.dir = a;
    } else {
      return Usage(err, "unexpected argument '" + a + "'");
    }
  }
  if (o.dir.empty()) return Usage(err, "which folder? give DIR");
  if (o.id.empty()) return Usage(err, "--id ID is needed (the sample's name)");
  if (!layout::IsValidSampleId(o.id))
    return Usage(err, "--id '" + o.id + "' is not a valid sample id (letters, digits, - _ .)");
  if (o.focal_mm.has_value() != o.sensor_mm.has_value())
    return Usage(err, "--focal-mm and --sensor-mm go together (the lens and the sensor's width)");
  if (o.out.empty()) o.out = o.id;
  // The worker knows a sample by its directory's name.
  if (fs::path(o.out).lexically_normal().filename() != o.id &&
      fs::path(o.out).lexically_normal().parent_path().filename() != o.id) {
    return Usage(err, "--out " + o.out + ": a sample directory is named after its id; use " +
                          (fs::path(o.out).parent_path() / o.id).string());
  }
  std::error_code ec;
  if (!fs::is_directory(o.dir, ec)) {
    err << kCmd << ": " << o.dir << " is not a folder\n";
    return 1;
  }
  if (fs::exists(o.out, ec)) {
    err << kCmd << ": " << o.out << " exists; nothing is overwritten: choose another --out\n";
    return 1;
  }

  std::vector<ConfigProblem> problems;
  Config config;
  if (!o.config.empty()) {
    Result<Config> c = LoadConfigFile(o.config, &problems);
    if (!c) {
      err << kCmd << ": --config: " << c.error().ToString() << "\n";
      for (const ConfigProblem& p : problems) err << "  " << p.ToString() << "\n";
      return 78;
    }
    config = *c;
  }
  std::optional<RigCalibration> cal;
  if (!o.calibration.empty()) {
    Result<RigCalibration> c = LoadCalibration(o.calibration);
    if (!c) {
      err << kCmd << ": --calibration: " << c.error().ToString() << "\n";
      return 1;
    }
    cal = *c;
  }

  // The photos: one side per sub-folder, or the folder's own.
  std::vector<Photo> photos;
  std::vector<fs::path> folders;
  for (const auto& e : fs::directory_iterator(o.dir, ec)) {
    if (e.is_directory() && e.path().filename().string()[0] != '.' && !PhotosIn(e.path()).empty())
      folders.push_back(e.path());
  }
  std::sort(folders.begin(), folders.end());
  const std::vector<fs::path> top = PhotosIn(o.dir);
  if (!folders.empty() && !top.empty()) {
    err << kCmd << ": " << o.dir << " has photos both in sub-folders and beside them: put every "
        << "side's photos in a sub-folder of its own, or none in sub-folders\n";
    return 1;
  }
  if (folders.empty()) {
    for (const fs::path& p : top) {
      Photo ph;
      ph.path = p.string();
      ph.name = p.filename().string();
      photos.push_back(std::move(ph));
    }
  } else {
    for (size_t f = 0; f < folders.size(); ++f) {
      for (const fs::path& p : PhotosIn(folders[f])) {
        Photo ph;
        ph.path = p.string();
        ph.name = folders[f].filename().string() + "/" + p.filename().string();
        ph.folder = static_cast<int>(f);
        photos.push_back(std::move(ph));
      }
    }
  }
  if (photos.empty()) {
    err << kCmd << ": no photos (JPEG, PNG, TIFF) in " << o.dir << "\n";
    return 1;
  }
  for (Photo& p : photos) {
    p.jpeg = IsJpeg(p.path);
    if (p.jpeg) {
      Result<PhotoExif> x = ReadExif(p.path);
      if (!x) {
        err << kCmd << ": " << p.name << ": " << x.error().ToString() << "\n";
        return 1;
      }
      p.exif = *x;
    }
    Measure(&p, config.rig);
  }
  std::vector<std::string> refuse;
  for (const Photo& p : photos)
    if (!p.problem.empty()) refuse.push_back(p.name + " " + p.problem + ": remove it");

  // Sides.
  std::vector<std::vector<Photo*>> sides;
  std::string how;
  if (!folders.empty()) {
    sides.resize(folders.size());
    for (Photo& p : photos) sides[static_cast<size_t>(p.folder)].push_back(&p);
    how = std::to_string(folders.size()) + " side(s), one per sub-folder";
  } else {
    sides = SplitByTime(photos, o.gap_s, &how);
  }

  // One camera, one size.
  std::set<std::string> cameras;
  for (const Photo& p : photos) {
    if (p.width > 0)
      cameras.insert((p.exif.Camera().empty() ? std::string("unknown camera") : p.exif.Camera()) +
                     " " + std::to_string(p.width) + "x" + std::to_string(p.height));
  }
  if (cameras.size() > 1 && !cal) {
    std::string list;
    for (const std::string& c : cameras) list += (list.empty() ? "" : "; ") + c;
    refuse.push_back("the photos come from more than one camera or size (" + list +
                     "): import each camera's photos on their own, turn them all the same way, "
                     "or give --calibration");
  }
  if (cal && !photos.empty() &&
      (photos[0].width != cal->camera.width || photos[0].height != cal->camera.height)) {
    refuse.push_back("--calibration is for " + std::to_string(cal->camera.width) + "x" +
                     std::to_string(cal->camera.height) + " photos, these are " +
                     std::to_string(photos[0].width) + "x" + std::to_string(photos[0].height) +
                     ": calibrate this camera at this size");
  }

  // Photos that cannot be measured well, per side; then enough views and
  // enough scale references.
  std::vector<std::string> left_out;
  for (size_t s = 0; s < sides.size(); ++s) {
    std::vector<double> focus;
    for (const Photo* p : sides[s])
      if (p->problem.empty()) focus.push_back(p->focus);
    const double median = Median(std::move(focus));
    std::vector<Photo*> kept;
    for (Photo* p : sides[s]) {
      if (!p->problem.empty()) continue;
      std::string bad;
      if (median > 0 && p->focus < kMinFocusRatio * median) {
        bad = "is out of focus or shaken (fine detail " + Fmt("%.0f", 100 * p->focus / median) +
              " % of its side's median)";
      } else if (p->blown > kMaxBlownFraction) {
        bad = "is over-exposed (" + Fmt("%.1f", 100 * p->blown) + " % of it blown white)";
      } else if (p->median_grey < kMinMedianGrey) {
        bad = "is under-exposed (median grey " + Fmt("%.0f", p->median_grey) + " of 255)";
      }
      if (bad.empty()) {
        kept.push_back(p);
      } else if (o.skip_bad) {
        left_out.push_back(p->name + " " + bad);
      } else {
        refuse.push_back(p->name + " " + bad +
                         ": shoot it again, remove it, or pass --skip-bad to leave it out");
      }
    }
    sides[s] = kept;
    const std::string side = "side " + std::to_string(s + 1);
    if (static_cast<int>(kept.size()) < o.min_views) {
      refuse.push_back(side + " has " + std::to_string(kept.size()) +
                       " usable photo(s); at least " + std::to_string(o.min_views) +
                       " are needed (--min-views): shoot the rock all round, every 30 degrees or "
                       "closer");
    }
    const auto with_scale =
        std::count_if(kept.begin(), kept.end(), [](const Photo* p) { return p->references >= 2; });
    if (!o.no_scale && with_scale < kMinScaleViews) {
      refuse.push_back(side + ": a scale reference (two or more of the disc's labels or [rig] " +
                       "ArUco markers) shows in " + std::to_string(with_scale) + " photo(s), " +
                       std::to_string(kMinScaleViews) +
                       " are needed: keep the labels in view, or pass --no-scale to import the "
                       "photos anyway (the worker then poses the views but has no size to "
                       "measure with)");
    }
  }
  if (!refuse.empty()) {
    err << kCmd << ": " << o.dir << " cannot be imported; nothing was written:\n";
    for (const std::string& r : refuse) err << "  " << r << "\n";
    return 1;
  }

  // The focal: the user's hint, else the EXIF.
  const Photo& first = *sides[0][0];
  std::string focal_source = "none: the worker estimates it (SfM)";
  double lens_mm = 0, sensor_mm = 0;
  if (o.focal_mm) {
    lens_mm = *o.focal_mm;
    sensor_mm = *o.sensor_mm;
    focal_source = "--focal-mm and --sensor-mm";
  } else if (first.exif.focal_35mm) {
    // The sensor width that gives the 35 mm equivalent's field of view
    // across this photo's width.
    lens_mm = *first.exif.focal_35mm;
    sensor_mm = kFullFrameDiagonalMm * first.width /
                std::hypot(static_cast<double>(first.width), static_cast<double>(first.height));
    focal_source = "EXIF FocalLengthIn35mmFilm";
  } else if (first.exif.focal_mm && first.exif.SensorWidthMm()) {
    lens_mm = *first.exif.focal_mm;
    // The focal plane resolution is along the sensor's x; a photo turned
    // upright by a quarter turn has the sensor's height across it.
    const bool turned = first.exif.orientation && *first.exif.orientation >= 5;
    sensor_mm = *first.exif.SensorWidthMm() *
                (turned ? static_cast<double>(first.width) / first.height : 1.0);
    focal_source = "EXIF FocalLength and FocalPlaneXResolution";
  }

  // The sample's config: what the worker reads of the capture.
  size_t most = 0;
  for (const auto& s : sides) most = std::max(most, s.size());
  config.capture.profile = "custom";
  config.capture.sides = static_cast<int>(sides.size());
  config.capture.views_per_side = static_cast<int>(most);
  config.capture.step_deg = 360.0 / static_cast<double>(most);
  config.camera.width = first.width;
  config.camera.height = first.height;
  config.camera.lens_focal_mm = lens_mm;
  config.camera.sensor_width_mm = sensor_mm;
  config.turntable.backend = "manual";  // nothing measured the angles
  // Without a calibration of this camera only SfM can pose the views; a
  // walked camera only SfM, calibrated or not.
  if (!cal) config.worker.poses = "auto";
  if (o.moving_camera) {
    config.capture.mode = "moving_camera";
    config.worker.poses = "auto";
  }

  const fs::path out_path = fs::absolute(o.out);
  const std::string staging = (out_path.parent_path() / (".aggscan-import-" + o.id)).string();
  fs::remove_all(staging, ec);
  config.daemon.state_dir = staging;
  SampleStore store(staging);
  auto fail = [&](const std::string& what, const Error& e) {
    err << kCmd << ": " << what << ": " << e.ToString() << "\n";
    fs::remove_all(staging, ec);
    return 1;
  };
  if (Status s = store.Init(); !s) return fail("cannot prepare " + staging, s.error());
  if (cal) {
    if (Status s = SaveCalibration(CalibrationPath(staging), *cal); !s)
      return fail("cannot copy the calibration", s.error());
  }
  SamplePlan plan{"custom", config.capture.sides, config.capture.views_per_side,
                  config.capture.step_deg, 0};
  json meta = {{"notes", "imported from " + fs::absolute(o.dir).string()}};
  if (Status s = store.CreateOrResume(o.id, plan, ConfigToToml(config), meta); !s)
    return fail("cannot create the sample", s.error());
  for (size_t s = 0; s < sides.size(); ++s) {
    const int side = static_cast<int>(s) + 1;
    if (Status st = store.BeginSide(o.id, side); !st)
      return fail("cannot start a side", st.error());
    for (size_t v = 0; v < sides[s].size(); ++v) {
      const Photo& p = *sides[s][v];
      std::vector<unsigned char> bytes;
      // A JPEG already upright is kept byte for byte; anything else is
      // turned upright and encoded.
      if (p.jpeg && p.exif.orientation.value_or(1) == 1) {
        auto f = ReadFile(p.path);
        if (!f) return fail(p.name, f.error());
        bytes.assign(f->begin(), f->end());
      } else {
        const cv::Mat bgr = cv::imread(p.path, cv::IMREAD_COLOR);
        if (bgr.empty() || !cv::imencode(".jpg", bgr, bytes, {cv::IMWRITE_JPEG_QUALITY, 95})) {
          return fail(p.name, MakeError(ErrorClass::kIo, "cannot be decoded and encoded again"));
        }
      }
      json car = {{"sample_id", o.id},
                  {"side", side},
                  {"view", static_cast<int>(v)},
                  {"image", layout::ViewImageName(static_cast<int>(v))},
                  {"commanded_angle_deg", static_cast<double>(v) * config.capture.step_deg},
                  {"width", p.width},
                  {"height", p.height},
                  {"camera_id", p.exif.Camera().empty() ? "unknown" : p.exif.Camera()},
                  {"camera_backend", "import"},
                  {"turntable_backend", "manual"},
                  {"source_file", p.name}};
      if (o.moving_camera) car["capture_mode"] = "moving_camera";
      if (p.exif.datetime_original) car["capture_utc"] = *p.exif.datetime_original;
      if (p.exif.orientation) car["exif_orientation"] = *p.exif.orientation;
      if (p.exif.focal_mm) car["exif_focal_mm"] = *p.exif.focal_mm;
      if (p.exif.focal_35mm) car["exif_focal_35mm"] = *p.exif.focal_35mm;
      if (p.exif.exposure_s) car["exposure_us"] = *p.exif.exposure_s * 1e6;
      if (p.exif.iso) car["iso"] = *p.exif.iso;
      if (Status st = store.WriteView(o.id, side, static_cast<int>(v), bytes, car); !st)
        return fail(p.name, st.error());
    }
    if (Status st = store.FinishSide(o.id, side); !st)
      return fail("cannot finish a side", st.error());
  }
  // How the photos became this sample, beside its record.
  const json how_json = {
      {"format", "aggscan-import-1"},
      {"source", fs::absolute(o.dir).string()},
      {"sides", how},
      {"focal", focal_source},
      {"lens_focal_mm", lens_mm},
      {"sensor_width_mm", sensor_mm},
      {"calibration", o.calibration.empty() ? json(nullptr) : json(o.calibration)},
      {"capture_mode", config.capture.mode},
      {"left_out", left_out}};
  if (Status s = WriteFileAtomic(store.SampleDir(o.id) + "/import.json", how_json.dump(2) + "\n");
      !s) {
    return fail("cannot record the import", s.error());
  }
  if (Status s = store.SetSampleState(o.id, "captured"); !s)
    return fail("cannot mark the sample captured", s.error());
  if (Status s = RenameDurable(store.SampleDir(o.id), out_path.string()); !s)
    return fail("cannot move the sample to " + out_path.string(), s.error());
  fs::remove_all(staging, ec);

  out << "imported " << photos.size() - left_out.size() << " photo(s) of " << o.dir << " as sample "
      << o.id << " in " << out_path.string() << "\n  " << how << ":";
  for (const auto& s : sides) out << " " << s.size();
  out << " views\n  focal: " << focal_source;
  if (lens_mm > 0)
    out << " (" << Fmt("%.2f", lens_mm) << " mm on " << Fmt("%.2f", sensor_mm) << " mm)";
  out << "\n  poses: "
      << (o.moving_camera ? "SfM (a camera walked round the rock), every pair of views matched"
          : cal           ? "the rig calibration; each view's angle from the disc's labels"
                          : "SfM (no calibration given)")
      << "\n";
  for (const std::string& l : left_out) out << "  left out: " << l << "\n";
  out << "next: aggscan reconstruct " << out_path.string() << "\n";
  return 0;
}

}  // namespace aggscan
