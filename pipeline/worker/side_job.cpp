#include "pipeline/worker/side_job.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <map>
#include <mutex>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <set>
#include <vector>

#include "common/clock.h"
#include "common/fsutil.h"
#include "common/log.h"
#include "pipeline/core/image_io.h"
#include "pipeline/core/parallel_for.h"
#include "pipeline/core/stage.h"
#include "pipeline/morph/morph2d.h"
#include "pipeline/worker/options_json.h"
#include "store/empty_turntable.h"
#include "store/layout.h"
#include "store/sample_files.h"

namespace aggscan {
namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr const char* kCat = "worker";

// The figures summarised per side and per sample.
constexpr const char* kStatFields[] = {"fer_2d", "circularity", "l_max_px", "l_min_px"};

std::string ResultsDir(const std::string& sample_dir) {
  return sample_dir + "/" + layout::kResultsDir;
}
std::string MasksDir(const std::string& sample_dir, int side) {
  return ResultsDir(sample_dir) + "/masks/" + layout::SideDirName(side);
}

json StatsJson(const Stats& s) {
  return {{"mean", s.mean}, {"min", s.min}, {"max", s.max},
          {"std", s.std},   {"cov", s.cov}, {"n", s.n}};
}

json StatsBlock(const std::map<std::string, std::vector<double>>& values) {
  json out = json::object();
  for (const char* f : kStatFields) {
    auto it = values.find(f);
    out[f] = StatsJson(ComputeStats(it == values.end() ? std::vector<double>{} : it->second));
  }
  return out;
}

struct ManifestView {
  int view = 0;
  std::string image;
  std::string sidecar;
};

Result<std::vector<ManifestView>> ReadManifest(const std::string& side_dir, int side,
                                               const std::string& sample_id) {
  const std::string path = side_dir + "/" + layout::kManifest;
  auto m = ReadSideManifest(side_dir);
  if (!m) {
    if (m.error().cls != ErrorClass::kNotFound) return m.error();
    return MakeError(ErrorClass::kNotFound,
                     "side " + std::to_string(side) + " of sample " + sample_id +
                         " has no manifest (not captured, or the capture did not finish): " + path);
  }
  auto corrupt = [&](const std::string& what) {
    return MakeError(ErrorClass::kCorrupt,
                     "manifest " + path + " is inconsistent: " + what + "; re-capture the side");
  };
  if (m->side != side) return corrupt("\"side\" is not " + std::to_string(side));
  if (m->sample_id && *m->sample_id != sample_id)
    return corrupt("\"sample_id\" does not match the sample directory " + sample_id);
  if (m->views.empty()) return corrupt("\"views\" is empty");
  std::vector<ManifestView> views;
  for (const SideManifest::Entry& v : m->views) {
    ManifestView mv;
    mv.view = v.view;
    mv.image = v.image;
    mv.sidecar = v.sidecar.value_or("");
    const std::string img = side_dir + "/" + mv.image;
    std::error_code ec;
    const auto size = fs::file_size(img, ec);
    if (ec) return corrupt("listed image " + mv.image + " is missing");
    if (v.bytes && static_cast<uint64_t>(*v.bytes) != size)
      return corrupt("image " + mv.image + " has " + std::to_string(size) +
                     " bytes, the manifest says " + std::to_string(*v.bytes));
    views.push_back(std::move(mv));
  }
  std::sort(views.begin(), views.end(),
            [](const auto& a, const auto& b) { return a.view < b.view; });
  return views;
}

// Rock pixels on the photo's outermost row or column.
int FramePixels(const cv::Mat& mask) {
  if (mask.empty()) return 0;
  const int r = mask.rows - 1, c = mask.cols - 1;
  return cv::countNonZero(mask.row(0)) + cv::countNonZero(mask.row(r)) +
         cv::countNonZero(mask.col(0).rowRange(1, std::max(1, r))) +
         cv::countNonZero(mask.col(c).rowRange(1, std::max(1, r)));
}

std::string ViewList(const std::vector<int>& v) {
  std::string s;
  for (size_t i = 0; i < v.size(); ++i) s += (i ? ", " : "") + std::to_string(v[i]);
  return s;
}

}  // namespace

std::string CheckSideMasks(std::vector<records::View2D>* views) {
  double largest = 0;
  for (const records::View2D& v : *views) {
    if (v.ok) largest = std::max(largest, v.mask_area_fraction.value_or(0.0));
  }
  std::vector<int> cut, small;
  for (records::View2D& v : *views) {
    if (!v.ok) continue;
    const int view = v.view;
    const int frame_px = v.mask_frame_px.value_or(0);
    const double area = v.mask_area_fraction.value_or(0.0);
    if (frame_px >= kMaskFrameMinPx) {
      cut.push_back(view);
      v.ok = false;
      // Its silhouette is cut, its features are not: SfM may still pose it.
      v.extra["cut_by_frame"] = true;
      v.error = "the rock reaches the edge of the photo (" + std::to_string(frame_px) +
                " px on its border): its silhouette is cut";
    } else if (area < kMaskMinAreaOfLargest * largest) {
      small.push_back(view);
      v.ok = false;
      v.error = "the mask covers " +
                std::to_string(static_cast<int>(std::lround(100 * area / largest))) +
                " % of the side's largest: the segmentation lost the rock";
    }
  }
  std::string msg;
  if (!cut.empty()) {
    msg = "the rock reaches the edge of the photo in view" +
          std::string(cut.size() > 1 ? "s " : " ") + ViewList(cut) +
          " (left out): move the camera back or use a wider lens so the whole rock is in every "
          "photo, then "
          "re-capture";
  }
  if (!small.empty()) {
    msg += std::string(msg.empty() ? "" : "; ") + "the rock was lost by the segmentation in view" +
           (small.size() > 1 ? "s " : " ") + ViewList(small) + " (masks under " +
           std::to_string(static_cast<int>(100 * kMaskMinAreaOfLargest)) +
           " % of the side's largest; left out): check those photos (rock leaving the frame, "
           "background of the "
           "rock's colour, lighting)";
  }
  return msg;
}

Status SideHasEnoughWholeViews(const records::SideResult& side_result) {
  std::string problems = side_result.mask_problems;
  const std::string& damaged = side_result.image_problems;
  if (!damaged.empty()) problems += (problems.empty() ? "" : "; ") + damaged;
  const int total = side_result.views_total, ok = side_result.views_ok;
  if (problems.empty() || 3 * int64_t{ok} >= 2 * int64_t{total}) return OkStatus();
  return MakeError(ErrorClass::kCorrupt,
                   "side " + std::to_string(side_result.side) + ": only " + std::to_string(ok) +
                       " of " + std::to_string(total) +
                       " views show the whole rock, too few for its model: " + problems);
}

namespace {

Status WriteJson(const std::string& path, const json& j) {
  return WriteFileAtomic(path, j.dump(2) + "\n");
}

}  // namespace

std::string SideResultPath(const std::string& sample_dir, int side) {
  return layout::ResultsPath(sample_dir, layout::SideResultName(side));
}
std::string SampleResultPath(const std::string& sample_dir) {
  return layout::ResultsPath(sample_dir, layout::kSampleMorph2d);
}
std::string ViewMaskPath(const std::string& sample_dir, int side, int view) {
  return MasksDir(sample_dir, side) + "/" + layout::ViewStem(view) + ".png";
}

double MeasuredAngle(const std::string& side_dir, const std::string& sidecar) {
  if (sidecar.empty()) return std::nan("");
  auto sc = ReadViewSidecarFile(side_dir + "/" + sidecar);
  return sc && sc->measured_angle_deg ? *sc->measured_angle_deg : std::nan("");
}

cv::Mat EmptyTurntablePhoto(const std::string& sample_dir, const EmptyTurntableSet& set,
                            double angle_deg, const cv::Mat& photo, const WorkerOptions& opts,
                            std::string* why) {
  if (!std::isfinite(angle_deg)) {
    *why = "no measured turntable angle to match an empty-turntable photo by";
    return cv::Mat();
  }
  double d = 0;
  const EmptyTurntableView* v = set.Nearest(angle_deg, &d);
  if (!v || d > opts.empty_turntable_max_angle_deg) {
    char buf[200];
    std::snprintf(buf, sizeof buf,
                  "the nearest empty-turntable photo was shot %.2f deg away (more than %.2f)", d,
                  opts.empty_turntable_max_angle_deg);
    *why = buf;
    return cv::Mat();
  }
  const std::string path = sample_dir + "/" + layout::kEmptyDir + "/" + v->image;
  auto img = LoadImage(path, ImageMode::kColor, opts.image_limits);
  if (!img.ok()) {
    *why = img.error().message;
    return cv::Mat();
  }
  if (img->size() != photo.size()) {
    *why = "the empty-turntable photo " + v->image + " is " + std::to_string(img->cols) + "x" +
           std::to_string(img->rows) + ", the view " + std::to_string(photo.cols) + "x" +
           std::to_string(photo.rows);
    return cv::Mat();
  }
  return std::move(*img);
}

namespace {

Status ProcessSideStage(const std::string& sample_dir, int side, const WorkerOptions& opts) {
  const std::string sample_id = layout::SampleIdOfDir(sample_dir);
  if (side < 1)
    return MakeError(ErrorClass::kInvalidArgument,
                     "side must be >= 1, got " + std::to_string(side));
  const std::string result_path = SideResultPath(sample_dir, side);
  if (PathExists(result_path)) {
    StageLog(LogLevel::kInfo, kCat, sample_id,
             "side " + std::to_string(side) + ": already done, skipped");
    return OkStatus();
  }
  const std::string side_dir = sample_dir + "/" + layout::SideDirName(side);
  auto views = ReadManifest(side_dir, side, sample_id);
  if (!views.ok()) return views.error();

  const std::string masks_dir = MasksDir(sample_dir, side);
  if (Status s = MakeDirsDurable(masks_dir); !s.ok()) return s;
  RemoveTempFiles(masks_dir);
  RemoveTempFiles(ResultsDir(sample_dir));

  const TimeNs t_start = MonotonicNs();
  std::vector<records::View2D> side_views;
  std::map<std::string, std::vector<double>> values;
  int reused = 0;
  std::vector<int> image_problems;  // views whose photo cannot be decoded or is of an unusable size
  std::string image_reasons;
  // The sample's empty-turntable photos (linked in when it was armed), if any.
  Result<EmptyTurntableSet> empty_set = LoadEmptyTurntableSet(sample_dir + "/" + layout::kEmptyDir);
  int empty_used = 0;  // views masked against an empty-turntable photo
  std::vector<std::string>
      empty_problems;  // views of a sample with a set masked without one, and why
  if (!empty_set && empty_set.error().cls != ErrorClass::kNotFound) {
    empty_problems.push_back(empty_set.error().message);
  }
  // Views are independent: the rig's cores take them in turn (a view is
  // ~0.1 s of mask work on one core). Each view's outcome goes to its own
  // slot and is gathered in view order afterwards, so the side result and
  // its log read the same whatever the threads did.
  struct ViewOutcome {
    bool started = false;
    records::View2D v2;
    std::optional<Error> fatal;
    bool reused = false, image_problem = false, empty_used = false;
    std::string image_reason, empty_problem;
    std::vector<std::string> warnings;
  };
  const size_t view_count = views->size();
  std::vector<ViewOutcome> outcomes(view_count);
  // Views finished, shown as the side's progress when a view starts (so the
  // last shown is N-1 of N until the side's result is written), under one
  // lock so that the figure never goes back.
  int views_done = 0;
  std::mutex progress_mu;
  std::atomic<bool> stop{false};
  auto do_view = [&](size_t i) {
    const ManifestView& v = (*views)[i];
    ViewOutcome& o = outcomes[i];
    if (stop.load() || (opts.cancel && opts.cancel->load())) {
      stop = true;
      return;
    }
    o.started = true;
    {
      const std::lock_guard<std::mutex> lock(progress_mu);
      ReportStageProgress(views_done, static_cast<int>(view_count));
    }
    const StageScope view_stage(
        "masks side " + std::to_string(side) + " view " + std::to_string(v.view),
        /*concurrent=*/true);
    const TimeNs t0 = MonotonicNs();
    // The view's sidecar, read once: its angles go into the side result and
    // the measured one picks the empty-turntable photo.
    std::optional<ViewSidecar> sidecar;
    if (!v.sidecar.empty()) {
      auto sc = ReadViewSidecarFile(side_dir + "/" + v.sidecar);
      if (sc) {
        sidecar = std::move(*sc);
      } else {
        o.warnings.push_back("sidecar " + v.sidecar + ": " + sc.error().message);
      }
    }
    const std::string mask_path = ViewMaskPath(sample_dir, side, v.view);
    cv::Mat mask;
    if (opts.reuse_masks && PathExists(mask_path)) {
      auto reuse = LoadImage(mask_path, ImageMode::kGray, opts.image_limits);
      if (reuse) {
        mask = std::move(*reuse);
        o.reused = true;
      }
    }
    cv::Size image_size = mask.size();
    if (mask.empty()) {
      auto bytes = ReadFile(side_dir + "/" + v.image);
      if (!bytes.ok()) {
        o.fatal = bytes.error();
        stop = true;
        return;
      }
      auto img = DecodeImage(*bytes, ImageMode::kColor, layout::SideDirName(side) + "/" + v.image,
                             opts.image_limits);
      if (!img.ok()) {
        // A photo damaged in the camera, on the link or in storage: the view
        // is left out (a grey, half-decoded photo would carve rock away) and
        // named with what to do.
        o.image_problem = true;
        o.image_reason = img.error().message;
        o.v2.view = v.view;
        o.v2.image = v.image;
        o.v2.ok = false;
        o.v2.image_problem = img.error().message;
        o.v2.error = img.error().message +
                     ": re-shoot the side (arm the sample again) and check the camera's link and "
                     "the storage";
        o.warnings.push_back("side " + std::to_string(side) + " view " + std::to_string(v.view) +
                             ": " + img.error().ToString());
        const std::lock_guard<std::mutex> lock(progress_mu);
        ++views_done;
        return;
      }
      image_size = img->size();
      cv::Mat empty;
      if (empty_set) {
        std::string why;
        const double angle =
            sidecar && sidecar->measured_angle_deg ? *sidecar->measured_angle_deg : std::nan("");
        empty = EmptyTurntablePhoto(sample_dir, *empty_set, angle, *img, opts, &why);
        if (empty.empty()) {
          o.empty_problem = layout::ViewStem(v.view) + ": " + why;
        } else {
          o.empty_used = true;
        }
      }
      if (opts.mask_net) {
        auto m = opts.mask_net->Mask(*img, opts.mask, empty);
        if (!m.ok()) {
          o.fatal = m.error();
          stop = true;
          return;
        }
        mask = std::move(*m);
      } else {
        mask = ComputeForegroundMask(*img, empty, opts.mask);
      }
      std::vector<unsigned char> png;
      if (!cv::imencode(".png", mask, png)) {
        o.fatal = MakeError(ErrorClass::kInternal, "PNG encoding of the mask of view " +
                                                       std::to_string(v.view) + " failed");
        stop = true;
        return;
      }
      if (Status st = WriteFileAtomic(mask_path, std::span<const unsigned char>(png)); !st.ok()) {
        o.fatal = st.error();
        stop = true;
        return;
      }
    }
    const double mask_ms = static_cast<double>(MonotonicNs() - t0) / 1e6;

    records::View2D rv;
    rv.view = v.view;
    rv.image = v.image;
    rv.mask = layout::ViewMaskName(side, v.view);
    if (sidecar) {
      rv.commanded_angle_deg = sidecar->commanded_angle_deg;
      rv.measured_angle_deg = sidecar->measured_angle_deg;
    }
    const double total_px = static_cast<double>(image_size.area());
    rv.mask_area_fraction = total_px > 0 ? cv::countNonZero(mask) / total_px : 0.0;
    rv.mask_frame_px = FramePixels(mask);
    auto m = ComputeMorph2D(mask);
    if (m.ok()) {
      rv.ok = true;
      rv.l_max_px = m->l_max_px;
      rv.l_min_px = m->l_min_px;
      rv.fer_2d = m->fer_2d;
      rv.area_px = m->area_px;
      rv.perimeter_px = m->perimeter_px;
      rv.circularity = m->circularity;
      rv.l_max_angle_deg = m->l_max_angle_deg;
    } else {
      rv.ok = false;
      rv.error = "no rock found in this view";
      o.warnings.push_back("side " + std::to_string(side) + " view " + std::to_string(v.view) +
                           ": no rock found in the mask");
    }
    rv.timing_ms = mask_ms;
    o.v2 = std::move(rv);
    const std::lock_guard<std::mutex> lock(progress_mu);
    ++views_done;
  };
  ReportStageProgress(0, static_cast<int>(view_count));
  ParallelFor(view_count, opts.threads, do_view);
  // What the views said is logged even when the side stops here.
  for (const ViewOutcome& o : outcomes)
    for (const std::string& w : o.warnings) StageLog(LogLevel::kWarning, kCat, sample_id, w);
  // A view's failure stops the others from starting: it is the error, not
  // the views it left unstarted.
  for (const ViewOutcome& o : outcomes)
    if (o.fatal) return *o.fatal;
  for (size_t i = 0; i < view_count; ++i) {
    if (!outcomes[i].started) {
      // Views already finished keep their masks; the rerun takes them up.
      return MakeError(ErrorClass::kCancelled, "interrupted: side " + std::to_string(side) +
                                                   " of " + sample_id + " will resume from view " +
                                                   std::to_string((*views)[i].view));
    }
  }
  for (ViewOutcome& o : outcomes) {
    if (o.reused) ++reused;
    if (o.image_problem) {
      image_problems.push_back(o.v2.view);
      image_reasons += (image_reasons.empty() ? "" : "; ") + o.image_reason;
    }
    if (o.empty_used) ++empty_used;
    if (!o.empty_problem.empty()) empty_problems.push_back(o.empty_problem);
    side_views.push_back(std::move(o.v2));
  }
  // Masks that cannot be the rock's whole silhouette: cut by the photo's
  // edge, or a small fraction of the side's largest (the segmentation lost
  // the rock). Either would make the 2D figures wrong and carve rock away
  // from the model, so such views are left out, and said so.
  const std::string lost = CheckSideMasks(&side_views);
  if (!lost.empty()) {
    StageLog(LogLevel::kWarning, kCat, sample_id, "side " + std::to_string(side) + ": " + lost);
  }
  std::string damaged;
  if (!image_problems.empty()) {
    damaged = "the photo of view" + std::string(image_problems.size() > 1 ? "s " : " ") +
              ViewList(image_problems) + " cannot be used (" + image_reasons +
              "; left out): re-shoot the side (arm the sample again) and check the camera's link "
              "and the storage";
    StageLog(LogLevel::kWarning, kCat, sample_id, "side " + std::to_string(side) + ": " + damaged);
  }
  for (const records::View2D& v : side_views) {
    if (!v.ok) continue;
    values["fer_2d"].push_back(v.fer_2d);
    values["circularity"].push_back(v.circularity);
    values["l_max_px"].push_back(v.l_max_px);
    values["l_min_px"].push_back(v.l_min_px);
  }
  const int ok_views = static_cast<int>(values["fer_2d"].size());
  if (ok_views == 0)
    return MakeError(ErrorClass::kCorrupt,
                     "side " + std::to_string(side) + " of " + sample_id +
                         ": no rock found in any view (empty turntable or wrong exposure?)" +
                         (lost.empty() ? "" : "; " + lost) +
                         (damaged.empty() ? "" : "; " + damaged));
  const double total_ms = static_cast<double>(MonotonicNs() - t_start) / 1e6;
  records::SideResult out;
  out.sample_id = sample_id;
  out.side = side;
  out.views = std::move(side_views);
  out.views_total = static_cast<int>(views->size());
  out.views_ok = ok_views;
  out.mask_problems = lost;
  out.image_problems = damaged;
  for (const char* f : kStatFields) {
    auto it = values.find(f);
    out.stats[f] = ComputeStats(it == values.end() ? std::vector<double>{} : it->second);
  }
  out.mask_method = opts.mask_net ? "onnx" : "classical";
  if (empty_set) out.mask_empty_turntable = empty_set->id;
  out.mask_empty_turntable_views = empty_used;
  out.timing_ms = total_ms;
  if (!empty_problems.empty()) {
    out.mask_empty_turntable_problems = empty_problems;
    std::string list;
    for (const std::string& p : empty_problems) list += (list.empty() ? "" : "; ") + p;
    StageLog(LogLevel::kWarning, kCat, sample_id,
             "side " + std::to_string(side) + ": " + std::to_string(empty_problems.size()) +
                 " view(s) masked without an empty-turntable photo (" + list +
                 "); shoot the empty turntable again at the sample's angles and camera settings "
                 "(aggscan empty-turntable)");
  }
  if (Status s = records::Write(result_path, out); !s.ok()) return s;
  StageLog(LogLevel::kInfo, kCat, sample_id,
           "side " + std::to_string(side) + ": " + std::to_string(ok_views) + "/" +
               std::to_string(views->size()) + " views measured (" + std::to_string(reused) +
               " masks reused) in " + std::to_string(static_cast<long>(total_ms)) + " ms");
  return OkStatus();
}

Status ProcessSampleStage(const std::string& sample_dir, const WorkerOptions& opts) {
  const std::string sample_id = layout::SampleIdOfDir(sample_dir);
  const std::string result_path = SampleResultPath(sample_dir);
  if (PathExists(result_path)) {
    StageLog(LogLevel::kInfo, kCat, sample_id, "sample morphology already done, skipped");
    return OkStatus();
  }
  auto sides = CapturedSides(sample_dir);
  if (!sides) return sides.error();

  json jsides = json::array();
  std::map<std::string, std::vector<double>> all;
  int views_ok = 0;
  for (int side : *sides) {
    const std::string side_result = SideResultPath(sample_dir, side);
    if (!PathExists(side_result)) {
      if (Status s = ProcessSide(sample_dir, side, opts); !s.ok()) return s;
    }
    auto sr = records::Read<records::SideResult>(side_result, "side result",
                                                 "delete it to recompute the side's masks");
    if (!sr) return sr.error();
    std::map<std::string, std::vector<double>> vals;
    for (const records::View2D& v : sr->views) {
      if (!v.ok) continue;
      for (const auto& [f, x] : {std::pair<const char*, double>{"fer_2d", v.fer_2d},
                                 {"circularity", v.circularity},
                                 {"l_max_px", v.l_max_px},
                                 {"l_min_px", v.l_min_px}}) {
        vals[f].push_back(x);
        all[f].push_back(x);
      }
    }
    views_ok += static_cast<int>(vals["fer_2d"].size());
    jsides.push_back(
        {{"side", side}, {"views_ok", vals["fer_2d"].size()}, {"stats", StatsBlock(vals)}});
  }
  json out = {{"sample_id", sample_id},
              {"sides", jsides},
              {"overall", {{"views_ok", views_ok}, {"stats", StatsBlock(all)}}},
              {"std_kind", "sample"}};
  if (Status s = WriteJson(result_path, out); !s.ok()) return s;
  StageLog(LogLevel::kInfo, kCat, sample_id,
           "sample morphology written: " + std::to_string(sides->size()) + " sides, " +
               std::to_string(views_ok) + " views");
  return OkStatus();
}

}  // namespace

Status ProcessSide(const std::string& sample_dir, int side, const WorkerOptions& opts) {
  return RunStage("masks side " + std::to_string(side),
                  [&] { return ProcessSideStage(sample_dir, side, opts); });
}

Status ProcessSample(const std::string& sample_dir, const WorkerOptions& opts) {
  return RunStage("2D figures", [&] { return ProcessSampleStage(sample_dir, opts); });
}

Result<std::vector<int>> CapturedSides(const std::string& sample_dir) {
  std::vector<int> sides;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(sample_dir, ec)) {
    const std::string n = e.path().filename().string();
    if (!e.is_directory() || n.size() <= 4 || n.rfind("side", 0) != 0) continue;
    const std::string num = n.substr(4);
    if (!std::all_of(num.begin(), num.end(), [](char c) { return c >= '0' && c <= '9'; }) ||
        num.size() > 4)
      continue;
    sides.push_back(std::stoi(num));
  }
  if (ec) return ErrnoError("cannot list sample directory " + sample_dir, ec.value());
  std::sort(sides.begin(), sides.end());
  if (sides.empty())
    return MakeError(ErrorClass::kNotFound,
                     "sample " + layout::SampleIdOfDir(sample_dir) + " has no captured side");
  return sides;
}

Result<std::string> MasksFingerprint(const std::string& sample_dir, int side,
                                     const WorkerOptions& opts) {
  Fingerprint f;
  f.Add("stage", std::string_view("masks")).Add("side", json(side));
  if (Status s = f.AddFile("manifest",
                           sample_dir + "/" + layout::SideDirName(side) + "/" + layout::kManifest);
      !s) {
    return s.error();
  }
  f.Add("image_limits", OptionsJson(opts.image_limits));
  if (opts.mask_net) {
    // The network and, after it, the refinement with these options.
    f.Add("net", OptionsJson(opts.mask_net->options()));
    if (Status s = f.AddFile("model", opts.mask_net->options().model_path); !s) return s.error();
  }
  f.Add("mask", OptionsJson(opts.mask));
  auto set = LoadEmptyTurntableSet(sample_dir + "/" + layout::kEmptyDir);
  f.Add("empty", set ? set->ToJson() : json(ErrorClassName(set.error().cls)));
  f.Add("empty_max_angle", json(opts.empty_turntable_max_angle_deg));
  return f.Hex();
}

Result<StageDecl> MasksStage(const std::string& sample_dir, int side, const WorkerOptions& opts) {
  if (side < 1)
    return MakeError(ErrorClass::kInvalidArgument,
                     "side must be >= 1, got " + std::to_string(side));
  auto fp = MasksFingerprint(sample_dir, side, opts);
  if (!fp) return fp.error();
  const std::string results = layout::kResultsDir;
  return StageDecl{
      "masks side " + std::to_string(side),
      "masks",
      *fp,
      {results + "/masks/" + layout::SideDirName(side),
       results + "/" + layout::SideResultName(side)},
      {},
      [sample_dir, side, opts](StageContext&) { return ProcessSide(sample_dir, side, opts); }};
}

Status RunSideJob(const std::string& sample_dir, int side, const WorkerOptions& opts) {
  auto d = MasksStage(sample_dir, side, opts);
  if (!d) return d.error();
  StageRunOptions ro;
  ro.cancel = opts.cancel;
  auto r = RunStages(sample_dir, {*d}, ro);
  return r ? OkStatus() : Status(r.error());
}

}  // namespace aggscan
