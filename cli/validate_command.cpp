#include "cli/validate_command.h"

#include <stdlib.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <sstream>

#include "cli/blender_render.h"
#include "cli/sim_capture.h"
#include "common/fsutil.h"
#include "common/mesh.h"
#include "common/mesh_check.h"
#include "common/mesh_props.h"
#include "common/rig_calibration.h"
#include "config/config.h"
#include "drivers/sim/world.h"
#include "pipeline/calib/calibrate.h"
#include "pipeline/core/records.h"
#include "pipeline/worker/reconstruct.h"
#include "pipeline/worker/side_job.h"

namespace aggscan {

namespace {

namespace fs = std::filesystem;
using nlohmann::json;

// Riprap the rig takes (the disc is 305 mm): a mesh used at its own size must
// have its longest dimension in this range, otherwise --scale-to-mm is needed.
constexpr double kMinRockMm = 50.0;
constexpr double kMaxRockMm = 300.0;
// The study's protocol: the turntable turns ~30 deg between shots.
constexpr double kStepDeg = 30.0;

double Seconds(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

double Pct(double rec, double truth) { return truth != 0 ? 100.0 * (rec - truth) / truth : 0.0; }

json BoxJson(const BoxDims& b) {
  return {{"a_mm", b.a_mm}, {"b_mm", b.b_mm}, {"c_mm", b.c_mm}, {"volume_ratio", b.volume_ratio}};
}

json FiguresJson(const RockFigures& f) {
  json j = {{"volume_mm3", f.volume_mm3},
            {"surface_area_mm2", f.area_mm2},
            {"a_mm", f.a_mm},
            {"b_mm", f.b_mm},
            {"c_mm", f.c_mm},
            {"sphericity", f.sphericity}};
  if (!f.near_boxes.empty()) {
    j["near_minimal_boxes"] = json::array();
    for (const BoxDims& b : f.near_boxes) j["near_minimal_boxes"].push_back(BoxJson(b));
  }
  return j;
}

// Box k of a rock: 0 its minimum box, k its near_boxes[k - 1].
BoxDims BoxOf(const RockFigures& f, int k) {
  return k == 0 ? BoxDims{f.a_mm, f.b_mm, f.c_mm, 1.0} : f.near_boxes[static_cast<size_t>(k - 1)];
}

std::string BoxName(const char* whose, const RockFigures& f, int k) {
  const BoxDims b = BoxOf(f, k);
  char t[160];
  if (k == 0) {
    std::snprintf(t, sizeof t, "%s minimum box", whose);
  } else {
    std::snprintf(t, sizeof t, "%s box %.1f / %.1f / %.1f mm (%+.2f %% volume)", whose, b.a_mm,
                  b.b_mm, b.c_mm, 100 * (b.volume_ratio - 1));
  }
  return t;
}

// What the sim rig does to the photos and the turntable (config.h defaults):
// reported so the table says under which conditions it was measured.
json Realism(const Config& c, int sides) {
  return {{"sensor_noise_sigma_levels", c.sim.noise_sigma},
          {"lens_distortion_k1", c.sim.k1},
          {"lens_distortion_k2", c.sim.k2},
          {"jpeg_quality", c.camera.jpeg_quality},
          {"turntable_repeatability_deg", c.turntable.repeatability_deg},
          {"turntable_backlash_deg", c.turntable.backlash_deg},
          {"turntable_settle_amplitude_deg", c.turntable.settle_amplitude_deg},
          {"settle_before_shot_ms", static_cast<double>(c.capture.settle) / 1e6},
          {"flip_between_sides", sides > 1},
          {"note",
           "angles in the sidecars are the sim encoder's readings (they carry the repeatability "
           "and backlash "
           "errors); the flip puts the rock on its next stable rest for each side"}};
}

// The sim rig's set-up where it differs from the config's (the tripod moved
// back for big rocks; no lens distortion under Blender, whose camera is a
// pinhole), as a [sim] table; empty when it does not.
std::string RigToml(const ValidateOptions& o) {
  const bool blender = o.renderer == "blender";
  if (o.camera_distance_mm <= 0 && !blender) return "";
  std::ostringstream t;
  t << "[sim]\n";
  if (o.camera_distance_mm > 0) t << "camera_distance_mm = " << o.camera_distance_mm << "\n";
  if (blender) t << "k1 = 0.0\nk2 = 0.0\n";
  return t.str();
}

BlenderOptions BlenderOpts(const ValidateOptions& o) {
  BlenderOptions b;
  b.samples = o.samples;
  b.empty_plates = o.backgrounds;
  b.denoise = o.denoise;
  return b;
}

// The look of rock i: the one given, or the batch's variety.
BlenderLook LookFor(const ValidateOptions& o, int i) {
  if (!o.look.empty()) {
    auto l = ParseBlenderLook(o.look);
    if (l) return *l;  // checked when the options were parsed
  }
  const int k = o.look_index + i;
  return BatchLook(k, o.seed + static_cast<uint64_t>(k));
}

// The worker's masks of a reconstructed sample against its truth masks.
void MaskIou(const std::string& sample_dir, const json& truth, double* iou_min, double* iou_mean) {
  double sum = 0, lo = 1;
  int n = 0;
  for (const json& v : truth.value("views", json::array())) {
    if (!v.is_object() || !v.contains("side") || !v.contains("view") || !v.contains("mask"))
      continue;
    const cv::Mat t =
        cv::imread(sample_dir + "/" + v["mask"].get<std::string>(), cv::IMREAD_GRAYSCALE);
    const cv::Mat m = cv::imread(
        ViewMaskPath(sample_dir, v["side"].get<int>(), v["view"].get<int>()), cv::IMREAD_GRAYSCALE);
    if (t.empty() || m.empty() || t.size() != m.size()) continue;
    const cv::Mat a = t > 127, b = m > 127;
    const int uni = cv::countNonZero(a | b);
    const double iou = uni > 0 ? static_cast<double>(cv::countNonZero(a & b)) / uni : 1.0;
    sum += iou;
    lo = std::min(lo, iou);
    ++n;
  }
  *iou_min = n > 0 ? lo : 0;
  *iou_mean = n > 0 ? sum / n : 0;
}

// Writes the capture config: the study's protocol with the chosen sides and views.
Status WriteCaptureConfig(const std::string& path, const ValidateOptions& o) {
  std::ostringstream t;
  t << "[capture]\nprofile = \"custom\"\nsides = " << o.sides
    << "\nviews_per_side = " << o.views_per_side << "\nstep_deg = " << kStepDeg << "\n"
    << RigToml(o);
  return WriteFileAtomic(path, t.str());
}

// The calibration every rock is captured and reconstructed with.
Result<json> MakeCalibration(const ValidateOptions& o, const std::string& work,
                             const std::string& out_path, std::ostream& log) {
  const Config defaults;
  const int w = o.width > 0 ? o.width : defaults.camera.width;
  const int h = o.height > 0 ? o.height : defaults.camera.height;
  Config c;
  if (o.camera_distance_mm > 0) c.sim.camera_distance_mm = o.camera_distance_mm;
  if (o.renderer == "blender") c.sim.k1 = c.sim.k2 = 0;
  sim::SimWorld world(c);  // the rig geometry does not depend on the rock
  const RigCalibration truth = world.TruthCalibration(w, h);
  if (o.calibration == "truth") {
    if (Status s = SaveCalibration(out_path, truth); !s) return s.error();
    return json{{"method", "sim-truth"}, {"note", "the sim's exact lens and camera pose"}};
  }
  // As on the real rig: the board on the disc, one side over a full turn,
  // then `aggscan calibrate`'s solver.
  const auto t0 = std::chrono::steady_clock::now();
  SimCaptureOptions cap;
  cap.scene = "charuco";
  cap.seed = 1;
  cap.out = work + "/board-capture";
  if (!RigToml(o).empty()) {
    // The board is seen from where the rocks will be.
    cap.config_path = work + "/rig.toml";
    if (Status s = WriteFileAtomic(cap.config_path, RigToml(o)); !s) return s.error();
  }
  cap.width = w;
  cap.height = h;
  std::ostringstream cout_, cerr_;
  if (RunSimCapture(cap, cout_, cerr_) != 0) {
    return MakeError(ErrorClass::kInternal,
                     "the simulated calibration capture failed: " + cerr_.str() +
                         "; try --calibration truth to validate without it");
  }
  json rendered;
  if (o.renderer == "blender") {
    // The board's photos drawn by Blender as well, in the first rock's look.
    auto b = RerenderWithBlender(cap.out, LookFor(o, 0), BlenderOpts(o), log);
    if (!b) {
      return MakeError(b.error().cls,
                       "the Blender calibration capture failed: " + b.error().message +
                           "; try --calibration truth to validate without it");
    }
    rendered = b->ToJson();
  }
  auto r = CalibrateSampleSide(cap.out, 1, c.calibration);
  if (!r) {
    return MakeError(r.error().cls,
                     "calibration from the simulated board failed: " + r.error().message +
                         "; try --calibration truth to validate without it");
  }
  if (Status s = SaveCalibration(out_path, r->cal); !s) return s.error();
  const double fx_err = Pct(r->cal.camera.fx, truth.camera.fx);
  const auto cc = r->cal.CameraCentreTable0(), ct = truth.CameraCentreTable0();
  const double centre_err =
      std::sqrt((cc[0] - ct[0]) * (cc[0] - ct[0]) + (cc[1] - ct[1]) * (cc[1] - ct[1]) +
                (cc[2] - ct[2]) * (cc[2] - ct[2]));
  char line[256];
  std::snprintf(line, sizeof line,
                "calibration: charuco, %d views, reprojection RMS %.3f px, fx %+.3f %% vs truth, "
                "camera centre "
                "%.2f mm from truth, k2 %s (%.1f s)\n",
                r->cal.views_used, r->cal.reprojection_rms_px, fx_err, centre_err,
                r->k2_estimated ? "estimated" : "fixed at 0", Seconds(t0));
  log << line << std::flush;
  json out{{"method", "charuco"},
           {"note", "simulated ChArUco capture on the disc, solved by aggscan calibrate's solver"},
           {"views_used", r->cal.views_used},
           {"reprojection_rms_px", r->cal.reprojection_rms_px},
           {"fx_error_pct", fx_err},
           {"camera_centre_error_mm", centre_err},
           {"k1", r->cal.camera.k1},
           {"k2", r->cal.camera.k2},
           {"k2_estimated", r->k2_estimated},
           {"seconds", Seconds(t0)}};
  if (!rendered.is_null()) out["renderer"] = rendered;
  return out;
}

struct RockInput {
  std::string id, source;
  std::optional<uint64_t> seed;
  std::string mesh_file;  // the scaled mesh in mm (mesh rocks)
  double scale = 1;
  std::string skip;  // non-empty: unusable input, why
};

std::vector<std::string> MeshFiles(const std::string& dir) {
  std::vector<std::string> files;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(dir, ec)) {
    if (!e.is_regular_file()) continue;
    std::string ext = e.path().extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(),
                   [](unsigned char ch) { return std::tolower(ch); });
    if (ext == ".ply" || ext == ".obj" || ext == ".stl") files.push_back(e.path().string());
  }
  std::sort(files.begin(), files.end());
  return files;
}

// Loads, checks and scales one mesh file; writes the mm mesh the sim renders.
RockInput PrepareMesh(const std::string& file, const ValidateOptions& o, double target_mm,
                      const std::string& work) {
  RockInput in;
  in.id = fs::path(file).stem().string();
  in.source = file;
  auto mesh = LoadMesh(file, o.unit);
  if (!mesh) {
    in.skip = mesh.error().message;
    return in;
  }
  // Scaled first: the closedness check's tolerances are in mm.
  const MeshProps p = ComputeMeshProps(*mesh);
  if (target_mm > 0 && p.c_mm > 0) {
    in.scale = target_mm / p.c_mm;
    for (auto& v : mesh->vertices)
      for (double& x : v) x *= in.scale;
  }
  if (Status s = CheckClosedManifold(*mesh, fs::path(file).filename().string()); !s) {
    in.skip = s.error().message + " (the true morphology needs a closed mesh)";
    return in;
  }
  if (target_mm <= 0 && (p.c_mm < kMinRockMm || p.c_mm > kMaxRockMm)) {
    char b[200];
    std::snprintf(
        b, sizeof b,
        "its longest dimension is %.1f mm in unit %s, outside the rig's %.0f..%.0f mm; give "
        "--scale-to-mm L (or LO:HI)",
        p.c_mm, o.unit.c_str(), kMinRockMm, kMaxRockMm);
    in.skip = b;
    return in;
  }
  in.mesh_file = work + "/" + in.id + ".rock.ply";
  if (Status s = SaveMeshPly(*mesh, in.mesh_file); !s)
    in.skip = "cannot write the scaled mesh: " + s.error().message;
  return in;
}

void RunRock(const RockInput& in, int index, const ValidateOptions& o, const std::string& work,
             const std::string& cfg, const std::string& calibration, ValidateRock* row,
             std::ostream& log) {
  const auto t0 = std::chrono::steady_clock::now();
  row->id = in.id;
  row->source = in.source;
  row->scale = in.scale;
  if (!in.skip.empty()) {
    row->status = "skipped";
    row->message = in.skip;
    log << "rock " << in.id << ": skipped: " << in.skip << "\n" << std::flush;
    return;
  }
  SimCaptureOptions cap;
  cap.seed = in.seed;
  if (!in.mesh_file.empty()) {
    cap.seed = 1;  // texture and noise; the rock is the mesh
    cap.mesh = in.mesh_file;
    cap.unit = "mm";
  }
  cap.out = work + "/" + in.id;
  cap.config_path = cfg;
  cap.width = o.width;
  cap.height = o.height;
  cap.calibration = calibration;
  std::ostringstream cout_, cerr_;
  if (RunSimCapture(cap, cout_, cerr_) != 0) {
    row->status = "failed";
    row->message = "capture: " + cerr_.str();
    while (!row->message.empty() && row->message.back() == '\n') row->message.pop_back();
    log << "rock " << in.id << ": " << row->message << "\n" << std::flush;
    return;
  }
  if (o.renderer == "blender") {
    const BlenderLook look = LookFor(o, index);
    row->look = look.Name();
    auto b = RerenderWithBlender(cap.out, look, BlenderOpts(o), log);
    if (!b) {
      row->status = "failed";
      row->message = "blender: " + b.error().ToString();
      row->seconds = Seconds(t0);
      log << "rock " << in.id << ": " << row->message << "\n" << std::flush;
      return;
    }
    row->render_frame_s = b->mean_frame_s;
    char line[200];
    std::snprintf(line, sizeof line,
                  "rock %s: %d frames rendered (%s), %.1f s a frame, silhouettes vs the sim's IoU "
                  "%.4f min\n",
                  in.id.c_str(), b->frames, look.Name().c_str(), b->mean_frame_s,
                  b->silhouette_iou_min);
    log << line << std::flush;
  }
  auto truth_text = ReadFile(cap.out + "/truth.json");
  json truth = truth_text ? json::parse(*truth_text, nullptr, false) : json();
  if (!truth.is_object()) {
    row->status = "failed";
    row->message = "capture: no readable truth.json in " + cap.out;
    return;
  }
  row->truth = RockFiguresFromJson(truth);
  if (o.render_only) {
    row->status = "rendered";
    row->seconds = Seconds(t0);
    log << "rock " << in.id << ": captured into " << cap.out << " (not reconstructed)\n"
        << std::flush;
    return;
  }
  ReconstructOptions ro;  // the sample carries its calibration; no library CSV
  if (Status s = ReconstructSample(cap.out, ro); !s) {
    // The masks are made before the stitch: how they compare is known even
    // when a later stage failed.
    MaskIou(cap.out, truth, &row->mask_iou_min, &row->mask_iou_mean);
    row->status = "failed";
    row->message = "reconstruction: " + s.error().ToString();
    row->seconds = Seconds(t0);
    log << "rock " << in.id << ": " << row->message << "\n" << std::flush;
    return;
  }
  auto m = ReadMorphology(cap.out);
  if (!m) {
    row->status = "failed";
    row->message = "reconstruction: " + m.error().ToString();
    return;
  }
  row->rec = RockFiguresFromJson(m->value("morphology_3d", json::object()));
  for (const json& f : m->value("quality", json::object()).value("flags", json::array())) {
    if (f.is_object()) row->quality_flags.push_back(f.value("code", ""));
  }
  MaskIou(cap.out, truth, &row->mask_iou_min, &row->mask_iou_mean);
  row->stitch = StitchAgainstTruth(cap.out, truth);
  row->status = "ok";
  row->seconds = Seconds(t0);
  char b[200];
  std::snprintf(b, sizeof b, "rock %s: V %.1f cm3 (true %.1f, %+.2f %%) in %.1f s\n", in.id.c_str(),
                row->rec.volume_mm3 / 1000, row->truth.volume_mm3 / 1000,
                Pct(row->rec.volume_mm3, row->truth.volume_mm3), row->seconds);
  log << b << std::flush;
}

bool ParseDouble(const std::string& s, double* v) {
  char* end = nullptr;
  *v = std::strtod(s.c_str(), &end);
  return end != s.c_str() && *end == '\0' && std::isfinite(*v);
}

bool ParseCount(const std::string& s, long long* v) {
  char* end = nullptr;
  *v = std::strtoll(s.c_str(), &end, 10);
  return end != s.c_str() && *end == '\0' && *v >= 0;
}

// Rotation angle (deg) and displacement RMS (mm) over `pts` between two
// transforms of the same frame.
void TransformError(const Eigen::Isometry3d& est, const Eigen::Isometry3d& truth,
                    const std::vector<Eigen::Vector3d>& pts, double* deg, double* mm) {
  const Eigen::AngleAxisd d((est.linear() * truth.linear().transpose()).eval());
  *deg = std::abs(d.angle()) * 180.0 / M_PI;
  double sum = 0;
  for (const Eigen::Vector3d& p : pts) sum += (est * p - truth * p).squaredNorm();
  *mm = pts.empty() ? 0 : std::sqrt(sum / static_cast<double>(pts.size()));
}

}  // namespace

RockFigures RockFiguresFromJson(const json& j) {
  RockFigures f;
  f.volume_mm3 = j.value("volume_mm3", 0.0);
  f.area_mm2 = j.value("surface_area_mm2", 0.0);
  f.a_mm = j.value("a_mm", 0.0);
  f.b_mm = j.value("b_mm", 0.0);
  f.c_mm = j.value("c_mm", 0.0);
  f.sphericity = j.value("sphericity", 0.0);
  if (const auto it = j.find("near_minimal_boxes"); it != j.end() && it->is_array()) {
    for (const json& b : *it) {
      if (!b.is_object()) continue;
      f.near_boxes.push_back({b.value("a_mm", 0.0), b.value("b_mm", 0.0), b.value("c_mm", 0.0),
                              b.value("volume_ratio", 1.0)});
    }
  } else if (const auto sb = j.find("second_box"); sb != j.end() && sb->is_object()) {
    // Figures written before near_minimal_boxes: the second box, if near.
    const BoxDims b{sb->value("a_mm", 0.0), sb->value("b_mm", 0.0), sb->value("c_mm", 0.0),
                    sb->value("volume_ratio", 0.0)};
    if (b.volume_ratio > 0 && b.volume_ratio <= 1 + kBoxAmbiguousVolume) f.near_boxes.push_back(b);
  }
  return f;
}

StitchTruthError StitchAgainstTruth(const std::string& sample_dir, const json& truth) {
  StitchTruthError e;
  auto st = records::Read<records::StitchRecord>(sample_dir + "/results/stitch.json",
                                                 "stitch record", "");
  auto mesh = LoadMesh(sample_dir + "/results/mesh.ply", "mm");
  if (!st || !mesh) return e;
  std::map<int, Eigen::Isometry3d> rest;  // rock -> turntable, per side
  for (const json& p : truth.value("poses", json::array())) {
    if (!p.is_object() || !p.contains("side") || !p["side"].is_number_integer()) continue;
    auto m = PoseField(p, "rock_to_turntable_4x4", jsonio::Source{"truth", sample_dir, ""});
    if (m) rest[p["side"].get<int>()] = *m;
  }
  if (!rest.count(1)) return e;
  std::vector<Eigen::Vector3d> pts;  // the reconstructed surface, object frame (side 1's turntable)
  const size_t step = std::max<size_t>(1, mesh->vertices.size() / 4000);
  for (size_t i = 0; i < mesh->vertices.size(); i += step) {
    pts.emplace_back(mesh->vertices[i][0], mesh->vertices[i][1], mesh->vertices[i][2]);
  }
  for (const records::SideStitch& s : st->stitches) {
    const int side = s.side;
    if (!rest.count(side)) continue;
    // Object frame = side 1's turntable frame: side s sees it through
    // rest_s * rest_1^-1.
    const Eigen::Isometry3d truth_t = rest[side] * rest[1].inverse();
    const auto found = st->table_from_object.find(side);
    if (found == st->table_from_object.end()) continue;
    const Eigen::Isometry3d& taken = found->second;
    double deg = 0, mm = 0;
    TransformError(taken, truth_t, pts, &deg, &mm);
    if (!e.measured || deg > e.deg) {
      e.measured = true;
      e.deg = deg;
      e.mm = mm;
      e.source = s.source;
      e.silhouette_deficit = st->silhouette_deficit.value_or(0.0);
      e.consistent = s.consistent;
      e.warning = s.warning;
      e.markers_deg = e.markers_mm = e.features_deg = e.features_mm = -1;
      for (const bool markers : {true, false}) {
        const auto& est = markers ? s.markers : s.features;
        if (!est || !est->valid || !est->moving_to_reference) continue;
        double d = 0, m = 0;
        TransformError(est->moving_to_reference->inverse(), truth_t, pts, &d, &m);
        (markers ? e.markers_deg : e.features_deg) = d;
        (markers ? e.markers_mm : e.features_mm) = m;
      }
    }
  }
  return e;
}

double DimErrors::MaxAbs() const {
  return std::max({std::fabs(a_pct), std::fabs(b_pct), std::fabs(c_pct)});
}

DimErrors DimsAgainstMinimumBox(const RockFigures& truth, const RockFigures& rec) {
  return {Pct(rec.a_mm, truth.a_mm), Pct(rec.b_mm, truth.b_mm), Pct(rec.c_mm, truth.c_mm), 0, 0};
}

DimErrors DimsAgainstTruth(const RockFigures& truth, const RockFigures& rec) {
  DimErrors best = DimsAgainstMinimumBox(truth, rec);
  const int nt = static_cast<int>(truth.near_boxes.size()),
            nr = static_cast<int>(rec.near_boxes.size());
  for (int i = 0; i <= nt; ++i) {
    for (int j = 0; j <= nr; ++j) {
      const BoxDims t = BoxOf(truth, i), r = BoxOf(rec, j);
      const DimErrors d{Pct(r.a_mm, t.a_mm), Pct(r.b_mm, t.b_mm), Pct(r.c_mm, t.c_mm), i, j};
      if (d.MaxAbs() < best.MaxAbs()) best = d;
    }
  }
  return best;
}

ValidateSummary Summarize(const std::vector<ValidateRock>& rocks, const ValidateTargets& t) {
  ValidateSummary s;
  double sum = 0, sum_abs = 0, sum_area = 0, sum_iou = 0, sum_render = 0;
  int n_iou = 0, n_render = 0;
  for (const ValidateRock& r : rocks) {
    if (r.render_frame_s > 0) sum_render += r.render_frame_s, ++n_render;
    if (r.status == "skipped") ++s.rocks_skipped;
    if (r.status == "failed") ++s.rocks_failed;
    // Every rock whose masks were made, measured or not.
    if (r.mask_iou_mean > 0) {
      s.mask_iou_min = n_iou == 0 ? r.mask_iou_min : std::min(s.mask_iou_min, r.mask_iou_min);
      sum_iou += r.mask_iou_mean;
      ++n_iou;
    }
    if (r.status != "ok") continue;
    ++s.rocks_ok;
    const double e = Pct(r.rec.volume_mm3, r.truth.volume_mm3);
    sum += e;
    sum_abs += std::fabs(e);
    s.volume_max_abs_pct = std::max(s.volume_max_abs_pct, std::fabs(e));
    sum_area += Pct(r.rec.area_mm2, r.truth.area_mm2);
    const DimErrors d = DimsAgainstTruth(r.truth, r.rec);
    s.a_max_abs_pct = std::max(s.a_max_abs_pct, std::fabs(d.a_pct));
    s.b_max_abs_pct = std::max(s.b_max_abs_pct, std::fabs(d.b_pct));
    s.c_max_abs_pct = std::max(s.c_max_abs_pct, std::fabs(d.c_pct));
    if (d.MaxAbs() <= t.dims_pct) ++s.dims_within;
    if (d.NearBox()) ++s.dims_near_box;
    const double raw = DimsAgainstMinimumBox(r.truth, r.rec).MaxAbs();
    s.dims_raw_max_abs_pct = std::max(s.dims_raw_max_abs_pct, raw);
    if (raw <= t.dims_pct) ++s.dims_raw_within;
    if (r.stitch.measured) {
      ++s.stitch_measured;
      s.stitch_max_deg = std::max(s.stitch_max_deg, r.stitch.deg);
      s.stitch_max_mm = std::max(s.stitch_max_mm, r.stitch.mm);
      if (r.stitch.deg <= s.stitch_target_deg && r.stitch.mm <= s.stitch_target_mm)
        ++s.stitch_within;
    }
    s.sphericity_max_abs =
        std::max(s.sphericity_max_abs, std::fabs(r.rec.sphericity - r.truth.sphericity));
  }
  if (s.rocks_ok > 0) {
    s.volume_mpe_pct = sum / s.rocks_ok;
    s.volume_mape_pct = sum_abs / s.rocks_ok;
    s.area_mpe_pct = sum_area / s.rocks_ok;
  }
  if (n_iou > 0) s.mask_iou_mean = sum_iou / n_iou;
  if (n_render > 0) s.render_frame_s = sum_render / n_render;
  const bool any = s.rocks_ok > 0;
  s.volume_mpe_pass = any && std::fabs(s.volume_mpe_pct) <= t.volume_mpe_pct;
  s.volume_mape_pass = any && s.volume_mape_pct <= t.volume_mape_pct;
  s.dims_pass = any && std::max({s.a_max_abs_pct, s.b_max_abs_pct, s.c_max_abs_pct}) <= t.dims_pct;
  s.sphericity_pass = any && s.sphericity_max_abs <= t.sphericity;
  s.pass = s.volume_mpe_pass && s.volume_mape_pass && s.dims_pass && s.sphericity_pass &&
           s.rocks_failed == 0;
  return s;
}

Result<ValidateReport> RunValidation(const ValidateOptions& o, std::ostream& log) {
  ValidateReport rep;
  rep.options = o;
  std::string work = o.keep;
  bool temporary = false;
  if (work.empty()) {
    const char* tmp = std::getenv("TMPDIR");
    std::string tmpl = std::string(tmp && *tmp ? tmp : "/tmp") + "/aggscan-validate-XXXXXX";
    if (::mkdtemp(tmpl.data()) == nullptr)
      return ErrnoError(
          "cannot create a work folder under " + tmpl + "; set TMPDIR to a writable folder", errno);
    work = tmpl;
    temporary = true;
  } else if (Status s = MakeDirsDurable(work); !s) {
    return s.error();
  }
  struct Cleanup {
    std::string dir;
    ~Cleanup() {
      std::error_code ec;
      if (!dir.empty()) fs::remove_all(dir, ec);
    }
  } cleanup{temporary ? work : std::string()};

  const std::string cfg = work + "/capture.toml";
  if (Status s = WriteCaptureConfig(cfg, o); !s) return s.error();
  const std::string cal_path = work + "/calibration.json";
  auto cal = MakeCalibration(o, work, cal_path, log);
  if (!cal) return cal.error();

  Config effective;
  if (o.renderer == "blender") {
    // Blender's camera has no lens distortion, and its noise is the path
    // tracer's, not the sim's sensor model.
    effective.sim.k1 = effective.sim.k2 = 0;
    effective.sim.noise_sigma = 0;
  }
  rep.settings = {
      {"width", o.width > 0 ? o.width : effective.camera.width},
      {"height", o.height > 0 ? o.height : effective.camera.height},
      {"sides", o.sides},
      {"views_per_side", o.views_per_side},
      {"camera_distance_mm",
       o.camera_distance_mm > 0 ? o.camera_distance_mm : effective.sim.camera_distance_mm},
      {"step_deg", kStepDeg},
      {"calibration", *cal},
      {"masks", "computed by the worker (classical segmentation), not the sim's truth masks"},
      {"renderer",
       o.renderer == "blender"
           ? json{{"name", "blender"},
                  {"samples_per_pixel", o.samples},
                  {"denoise", o.denoise},
                  {"look", o.look.empty() ? json("the batch's variety (BatchLook)") : json(o.look)},
                  {"lens_distortion", "none (pinhole)"}}
           : json{{"name", "sim"}}},
      {"sim_realism", Realism(effective, o.sides)},
      {"work_dir", temporary ? std::string() : work}};

  std::vector<RockInput> inputs;
  if (!o.mesh_dir.empty()) {
    const std::vector<std::string> files = MeshFiles(o.mesh_dir);
    for (size_t i = 0; i < files.size(); ++i) {
      double target = o.scale_min_mm;
      if (o.scale_max_mm > o.scale_min_mm && files.size() > 1) {
        target = o.scale_min_mm +
                 (o.scale_max_mm - o.scale_min_mm) * static_cast<double>(i) / (files.size() - 1);
      }
      inputs.push_back(PrepareMesh(files[i], o, target, work));
    }
  } else {
    for (int i = 0; i < o.count; ++i) {
      RockInput in;
      in.seed = o.seed + static_cast<uint64_t>(i);
      in.id = "seed-" + std::to_string(*in.seed);
      in.source = "procedural seed " + std::to_string(*in.seed);
      inputs.push_back(in);
    }
  }
  for (const RockInput& in : inputs) {
    ValidateRock row;
    RunRock(in, static_cast<int>(rep.rocks.size()), o, work, cfg, cal_path, &row, log);
    rep.rocks.push_back(std::move(row));
  }
  rep.summary = Summarize(rep.rocks, rep.targets);
  return rep;
}

void PrintValidateReport(const ValidateReport& r, std::ostream& out) {
  const json& st = r.settings;
  char b[512];
  std::snprintf(
      b, sizeof b,
      "aggscan validate: %s, %d side(s) x %d views at %dx%d, calibration %s, computed masks, "
      "photos by %s\n",
      r.options.mesh_dir.empty() ? "procedural rocks" : ("meshes in " + r.options.mesh_dir).c_str(),
      r.options.sides, r.options.views_per_side, st.value("width", 0), st.value("height", 0),
      st["calibration"].value("method", "").c_str(),
      r.options.renderer == "blender" ? ("Blender Cycles, " + std::to_string(r.options.samples) +
                                         " samples/px" + (r.options.denoise ? ", denoised" : ""))
                                            .c_str()
                                      : "the sim renderer");
  out << b;
  const json& re = st["sim_realism"];
  std::snprintf(
      b, sizeof b,
      "sim realism: sensor noise %.1f levels, lens k1 %.3f k2 %.3f, JPEG q%d, turntable "
      "repeatability "
      "%.2f deg + backlash %.2f deg + settle ringing %.2f deg, %s\n\n",
      re.value("sensor_noise_sigma_levels", 0.0), re.value("lens_distortion_k1", 0.0),
      re.value("lens_distortion_k2", 0.0), re.value("jpeg_quality", 0),
      re.value("turntable_repeatability_deg", 0.0), re.value("turntable_backlash_deg", 0.0),
      re.value("turntable_settle_amplitude_deg", 0.0),
      re.value("flip_between_sides", false) ? "rock flipped between sides" : "one side (no flip)");
  out << b;
  std::snprintf(b, sizeof b, "%-22s %9s %9s %7s  %8s %8s  %6s %6s  %6s %6s  %6s %6s  %6s %6s\n",
                "rock", "V_true", "V_rec", "V_err%", "A_true", "A_rec", "a_true", "a_rec", "b_true",
                "b_rec", "c_true", "c_rec", "sph_t", "sph_r");
  out << b;
  std::snprintf(b, sizeof b, "%-22s %9s %9s %7s  %8s %8s  %6s %6s  %6s %6s  %6s %6s  %6s %6s\n", "",
                "cm3", "cm3", "", "cm2", "cm2", "mm", "mm", "mm", "mm", "mm", "mm", "", "");
  out << b;
  for (const ValidateRock& k : r.rocks) {
    std::string id = k.id.size() > 22 ? k.id.substr(0, 19) + "..." : k.id;
    if (k.status != "ok") {
      out << id << std::string(id.size() < 23 ? 23 - id.size() : 1, ' ') << k.status << ": "
          << k.message << "\n";
      if (!k.look.empty() || k.mask_iou_mean > 0) {
        std::snprintf(b, sizeof b, "    %s%smasks vs true silhouettes IoU min %.4f mean %.4f\n",
                      k.look.c_str(), k.look.empty() ? "" : ": ", k.mask_iou_min, k.mask_iou_mean);
        out << b;
      }
      continue;
    }
    std::snprintf(b, sizeof b,
                  "%-22s %9.2f %9.2f %+7.2f  %8.2f %8.2f  %6.1f %6.1f  %6.1f %6.1f  %6.1f %6.1f  "
                  "%6.4f %6.4f\n",
                  id.c_str(), k.truth.volume_mm3 / 1000, k.rec.volume_mm3 / 1000,
                  Pct(k.rec.volume_mm3, k.truth.volume_mm3), k.truth.area_mm2 / 100,
                  k.rec.area_mm2 / 100, k.truth.a_mm, k.rec.a_mm, k.truth.b_mm, k.rec.b_mm,
                  k.truth.c_mm, k.rec.c_mm, k.truth.sphericity, k.rec.sphericity);
    out << b;
    if (!k.look.empty() || k.mask_iou_mean > 0) {
      std::snprintf(b, sizeof b, "    %s%smasks vs true silhouettes IoU min %.4f mean %.4f",
                    k.look.c_str(), k.look.empty() ? "" : ": ", k.mask_iou_min, k.mask_iou_mean);
      out << b;
      if (k.render_frame_s > 0) {
        std::snprintf(b, sizeof b, ", %.1f s a frame", k.render_frame_s);
        out << b;
      }
      out << "\n";
    }
    if (!k.quality_flags.empty()) {
      out << "    NOT CONFIDENT (the worker's quality flags):";
      for (const std::string& f : k.quality_flags) out << " " << f;
      out << "\n";
    }
    if (k.stitch.measured) {
      std::snprintf(b, sizeof b, "    stitch vs truth %.2f deg / %.2f mm by %s", k.stitch.deg,
                    k.stitch.mm, k.stitch.source.c_str());
      out << b;
      if (k.stitch.markers_deg >= 0) {
        std::snprintf(b, sizeof b, "; markers alone %.2f deg / %.2f mm", k.stitch.markers_deg,
                      k.stitch.markers_mm);
        out << b;
      }
      if (k.stitch.features_deg >= 0) {
        std::snprintf(b, sizeof b, "; features alone %.2f deg / %.2f mm", k.stitch.features_deg,
                      k.stitch.features_mm);
        out << b;
      }
      std::snprintf(b, sizeof b, "; silhouette deficit %.4f%s%s\n", k.stitch.silhouette_deficit,
                    k.stitch.warning.empty() ? "" : "; warning: ", k.stitch.warning.c_str());
      out << b;
    }
    if (const DimErrors d = DimsAgainstTruth(k.truth, k.rec); d.NearBox()) {
      out << "    a, b, c ill-conditioned: " << BoxName("the truth's", k.truth, d.truth_box)
          << " against " << BoxName("the reconstruction's", k.rec, d.rec_box);
      std::snprintf(b, sizeof b, ": errors %+.1f / %+.1f / %+.1f %%\n", d.a_pct, d.b_pct, d.c_pct);
      out << b;
    }
  }
  const ValidateSummary& s = r.summary;
  const ValidateTargets& t = r.targets;
  auto verdict = [](bool p) { return p ? "PASS" : "FAIL"; };
  std::snprintf(b, sizeof b, "\nrocks: %d measured, %d failed, %d skipped\n", s.rocks_ok,
                s.rocks_failed, s.rocks_skipped);
  out << b;
  std::snprintf(b, sizeof b, "volume MPE        %+7.2f %%   target |MPE| <= %.1f %%   %s\n",
                s.volume_mpe_pct, t.volume_mpe_pct, verdict(s.volume_mpe_pass));
  out << b;
  std::snprintf(
      b, sizeof b,
      "volume MAPE       %7.2f %%   target <= %.1f %%         %s   (max |error| %.2f %%)\n",
      s.volume_mape_pct, t.volume_mape_pct, verdict(s.volume_mape_pass), s.volume_max_abs_pct);
  out << b;
  std::snprintf(b, sizeof b,
                "max |a|,|b|,|c| error %.2f / %.2f / %.2f %%   target <= %.1f %%   %s   (%d of %d "
                "rocks within)\n",
                s.a_max_abs_pct, s.b_max_abs_pct, s.c_max_abs_pct, t.dims_pct, verdict(s.dims_pass),
                s.dims_within, s.rocks_ok);
  out << b;
  if (s.dims_near_box > 0) {
    std::snprintf(b, sizeof b,
                  "  %d rock(s) matched through a near-minimal box (a, b, c ill-conditioned: "
                  "another box within "
                  "%.0f %% of the minimum volume); minimum box against minimum box alone: %d of %d "
                  "within, max "
                  "error %.2f %%\n",
                  s.dims_near_box, 100 * kBoxAmbiguousVolume, s.dims_raw_within, s.rocks_ok,
                  s.dims_raw_max_abs_pct);
    out << b;
  }
  std::snprintf(b, sizeof b, "max |sphericity error| %.4f   target <= %.2f   %s\n",
                s.sphericity_max_abs, t.sphericity, verdict(s.sphericity_pass));
  out << b;
  std::snprintf(b, sizeof b, "area MPE          %+7.2f %%   (no target)\n", s.area_mpe_pct);
  out << b;
  if (s.mask_iou_mean > 0) {
    std::snprintf(b, sizeof b,
                  "masks vs true silhouettes: IoU min %.4f, mean %.4f (per rock mean)\n",
                  s.mask_iou_min, s.mask_iou_mean);
    out << b;
  }
  if (s.stitch_measured > 0) {
    std::snprintf(
        b, sizeof b,
        "stitch vs truth: worst %.2f deg / %.2f mm; %d of %d rocks within %.1f deg and %.1f mm (no "
        "verdict)\n",
        s.stitch_max_deg, s.stitch_max_mm, s.stitch_within, s.stitch_measured, s.stitch_target_deg,
        s.stitch_target_mm);
    out << b;
  }
  if (s.render_frame_s > 0) {
    std::snprintf(b, sizeof b, "render time: %.2f s a frame (mean over rocks)\n", s.render_frame_s);
    out << b;
  }
  out << "result: " << verdict(s.pass);
  if (s.rocks_failed > 0)
    out << " (" << s.rocks_failed << " rock(s) failed to capture or reconstruct)";
  if (s.rocks_ok == 0) out << " (no rock measured)";
  out << "\n";
}

json ValidateReportToJson(const ValidateReport& r) {
  json rocks = json::array();
  for (const ValidateRock& k : r.rocks) {
    json j = {{"id", k.id}, {"source", k.source}, {"status", k.status}};
    if (!k.message.empty()) j["message"] = k.message;
    if (k.scale != 1) j["scale"] = k.scale;
    if (k.status == "ok") {
      j["truth"] = FiguresJson(k.truth);
      j["reconstructed"] = FiguresJson(k.rec);
      const DimErrors d = DimsAgainstTruth(k.truth, k.rec);
      j["errors"] = {{"volume_pct", Pct(k.rec.volume_mm3, k.truth.volume_mm3)},
                     {"surface_area_pct", Pct(k.rec.area_mm2, k.truth.area_mm2)},
                     {"a_pct", d.a_pct},
                     {"b_pct", d.b_pct},
                     {"c_pct", d.c_pct},
                     {"dims_against", BoxName("the truth's", k.truth, d.truth_box) + " against " +
                                          BoxName("the reconstruction's", k.rec, d.rec_box)},
                     {"sphericity", k.rec.sphericity - k.truth.sphericity}};
    }
    if (k.seconds > 0) j["seconds"] = k.seconds;
    if (!k.look.empty()) j["look"] = k.look;
    if (k.status == "ok") j["quality_flags"] = k.quality_flags;
    if (k.render_frame_s > 0) j["render_frame_seconds"] = k.render_frame_s;
    if (k.mask_iou_mean > 0) j["mask_iou"] = {{"min", k.mask_iou_min}, {"mean", k.mask_iou_mean}};
    if (k.stitch.measured) {
      json sj = {
          {"error_deg", k.stitch.deg},         {"error_mm", k.stitch.mm},
          {"source", k.stitch.source},         {"silhouette_deficit", k.stitch.silhouette_deficit},
          {"consistent", k.stitch.consistent}, {"warning", k.stitch.warning}};
      if (k.stitch.markers_deg >= 0)
        sj["markers"] = {{"error_deg", k.stitch.markers_deg}, {"error_mm", k.stitch.markers_mm}};
      if (k.stitch.features_deg >= 0) {
        sj["features"] = {{"error_deg", k.stitch.features_deg}, {"error_mm", k.stitch.features_mm}};
      }
      j["stitch_vs_truth"] = sj;
    }
    rocks.push_back(std::move(j));
  }
  const ValidateSummary& s = r.summary;
  const ValidateTargets& t = r.targets;
  return {{"format", "aggscan-validate-1"},
          {"settings", r.settings},
          {"rocks", rocks},
          {"summary",
           {{"rocks_measured", s.rocks_ok},
            {"rocks_failed", s.rocks_failed},
            {"rocks_skipped", s.rocks_skipped},
            {"volume_mpe_pct", s.volume_mpe_pct},
            {"volume_mape_pct", s.volume_mape_pct},
            {"volume_max_abs_error_pct", s.volume_max_abs_pct},
            {"surface_area_mpe_pct", s.area_mpe_pct},
            {"a_max_abs_error_pct", s.a_max_abs_pct},
            {"b_max_abs_error_pct", s.b_max_abs_pct},
            {"c_max_abs_error_pct", s.c_max_abs_pct},
            {"dims_within_target", s.dims_within},
            {"dims_matched_through_near_minimal_box", s.dims_near_box},
            {"dims_within_target_minimum_boxes_only", s.dims_raw_within},
            {"dims_max_abs_error_against_minimum_box_pct", s.dims_raw_max_abs_pct},
            {"sphericity_max_abs_error", s.sphericity_max_abs},
            {"mask_iou_min", s.mask_iou_min},
            {"mask_iou_mean", s.mask_iou_mean},
            {"render_frame_seconds", s.render_frame_s},
            {"stitch_max_error_deg", s.stitch_max_deg},
            {"stitch_max_error_mm", s.stitch_max_mm},
            {"stitch_rocks_measured", s.stitch_measured},
            {"stitch_rocks_within_target", s.stitch_within}}},
          {"targets",
           {{"volume_abs_mpe_pct", t.volume_mpe_pct},
            {"volume_mape_pct", t.volume_mape_pct},
            {"dims_pct", t.dims_pct},
            {"sphericity", t.sphericity}}},
          {"verdicts",
           {{"volume_mpe", s.volume_mpe_pass},
            {"volume_mape", s.volume_mape_pass},
            {"dims", s.dims_pass},
            {"sphericity", s.sphericity_pass}}},
          {"pass", s.pass}};
}

void PrintValidateUsage(std::ostream& o) {
  o << "  aggscan validate [--count N] [--seed S] [--mesh-dir DIR --unit mm|cm|m [--scale-to-mm "
       "L|LO:HI]]\n"
       "                   [--sides 1|2] [--views N] [--width W --height H] [--calibration "
       "charuco|truth]\n"
       "                   [--camera-distance-mm D] [--renderer sim|blender [--look "
       "SPEC|--look-index K]\n"
       "                   [--samples N] [--no-denoise] [--backgrounds]] [--render-only]\n"
       "                   [--json] [--keep DIR]\n"
       "      accuracy harness: simulated two-side captures (noise, distortion, JPEG, turntable\n"
       "      errors, flip) of N procedural rocks (default 20, seeds S..S+N-1) or of every mesh "
       "in\n"
       "      DIR scaled so its longest dimension is L mm (LO..HI spread over the files),\n"
       "      reconstructed by the worker; prints true vs reconstructed volume, area, a, b, c,\n"
       "      sphericity, volume MPE/MAPE and PASS/FAIL against the targets (--json: the same as\n"
       "      JSON); calibration from a simulated ChArUco capture unless --calibration truth;\n"
       "      --camera-distance-mm: the sim rig's tripod distance from the disc centre (default\n"
       "      650 mm frames rocks up to ~20 cm in every pose; ~800 mm for 20-25 cm rocks);\n"
       "      --renderer blender: every photo redrawn by Blender's Cycles path tracer (Debian's\n"
       "      blender, CPU) from the same poses, in a look per rock that cycles the disc/floor\n"
       "      (white, light-grey, wood, rubber-mat, gravel), the light (softbox, two-lights,\n"
       "      overcast, low-sun) and the stone (granite, dolomite, basalt, wet), or the one\n"
       "      --look surface=S,light=L,stone=T gives (--look-index K: start the cycle at look K);\n"
       "      object markers drawn like coloured pencil;\n"
       "      --samples: Cycles samples per pixel (default 16); render time per frame is "
       "reported;\n"
       "      the path tracer's noise is taken out (two half-sample renders, the light passes\n"
       "      smoothed in units of their own noise, the colours kept) and a camera's blur and\n"
       "      shot and read noise ([sim] noise_sigma levels at mid-grey) put in; --no-denoise:\n"
       "      Cycles' frames as they come;\n"
       "      --backgrounds: also side 1's views with the rock taken away, the look's\n"
       "      empty-turntable photos, as the sample's set (SAMPLE/empty/): the worker masks every\n"
       "      view against the one of its angle (and aggscan masks train --backgrounds takes "
       "them);\n"
       "      --render-only: capture and render into --keep DIR, reconstruct nothing (mask sets);\n"
       "      exit 0 all targets met, 1 a target missed or a rock failed, 2 usage\n";
}

int RunValidateCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err) {
  // Before the options are judged: a line that asks for help starts no harness.
  if (std::any_of(args.begin(), args.end(),
                  [](const std::string& a) { return a == "--help" || a == "-h"; })) {
    out << "usage:\n";
    PrintValidateUsage(out);
    return 0;
  }
  ValidateOptions o;
  bool json_out = false, count_given = false, seed_given = false, denoise_given = false;
  for (size_t i = 0; i < args.size(); ++i) {
    const std::string& a = args[i];
    const bool has_value = i + 1 < args.size();
    auto need = [&](const char* what) {
      err << "aggscan validate: " << a << " needs " << what << "\n";
      return 2;
    };
    long long n = 0;
    if (a == "--json") {
      json_out = true;
    } else if (a == "--count" || a == "--seed" || a == "--views" || a == "--width" ||
               a == "--height" || a == "--sides") {
      if (!has_value) return need("a number");
      if (!ParseCount(args[++i], &n) || (a != "--seed" && n == 0)) {
        err << "aggscan validate: " << a << " expects a "
            << (a == "--seed" ? "non-negative" : "positive") << " integer, got '" << args[i]
            << "'\n";
        return 2;
      }
      if (a == "--count") o.count = static_cast<int>(n), count_given = true;
      if (a == "--seed") o.seed = static_cast<uint64_t>(n), seed_given = true;
      if (a == "--views") o.views_per_side = static_cast<int>(n);
      if (a == "--width") o.width = static_cast<int>(n);
      if (a == "--height") o.height = static_cast<int>(n);
      if (a == "--sides") o.sides = static_cast<int>(n);
    } else if (a == "--mesh-dir") {
      if (!has_value) return need("a folder of PLY/OBJ/STL meshes");
      o.mesh_dir = args[++i];
    } else if (a == "--unit") {
      if (!has_value) return need("mm, cm or m");
      o.unit = args[++i];
    } else if (a == "--scale-to-mm") {
      if (!has_value) return need("a length L or a range LO:HI in mm");
      const std::string& v = args[++i];
      const size_t colon = v.find(':');
      double lo = 0, hi = 0;
      const bool ok = colon == std::string::npos ? ParseDouble(v, &lo) && (hi = lo, true)
                                                 : ParseDouble(v.substr(0, colon), &lo) &&
                                                       ParseDouble(v.substr(colon + 1), &hi);
      if (!ok || lo < kMinRockMm || hi > kMaxRockMm || hi < lo) {
        err << "aggscan validate: --scale-to-mm expects L or LO:HI in mm within " << kMinRockMm
            << ".." << kMaxRockMm << " (riprap on a 305 mm disc), got '" << v << "'\n";
        return 2;
      }
      o.scale_min_mm = lo;
      o.scale_max_mm = hi;
    } else if (a == "--camera-distance-mm") {
      if (!has_value) return need("a distance in mm");
      double d = 0;
      if (!ParseDouble(args[++i], &d) || d < 400 || d > 2000) {
        err << "aggscan validate: --camera-distance-mm expects the camera's distance from the disc "
               "centre "
               "in mm, 400..2000, got '"
            << args[i] << "'\n";
        return 2;
      }
      o.camera_distance_mm = d;
    } else if (a == "--calibration") {
      if (!has_value) return need("charuco or truth");
      o.calibration = args[++i];
    } else if (a == "--renderer") {
      if (!has_value) return need("sim or blender");
      o.renderer = args[++i];
    } else if (a == "--look") {
      if (!has_value) return need("a look, e.g. surface=wood,light=low-sun,stone=dolomite");
      o.look = args[++i];
      if (auto l = ParseBlenderLook(o.look); !l) {
        err << "aggscan validate: --look: " << l.error().message << "\n";
        return 2;
      }
    } else if (a == "--samples") {
      if (!has_value) return need("a number of samples per pixel");
      if (!ParseCount(args[++i], &n) || n < 1 || n > 4096) {
        err << "aggscan validate: --samples expects 1..4096 samples per pixel, got '" << args[i]
            << "'\n";
        return 2;
      }
      o.samples = static_cast<int>(n);
    } else if (a == "--look-index") {
      if (!has_value) return need("a look number");
      if (!ParseCount(args[++i], &n) || n > 1000) {
        err << "aggscan validate: --look-index expects 0..1000, got '" << args[i] << "'\n";
        return 2;
      }
      o.look_index = static_cast<int>(n);
    } else if (a == "--backgrounds") {
      o.backgrounds = true;
    } else if (a == "--no-denoise") {
      o.denoise = false;
      denoise_given = true;
    } else if (a == "--render-only") {
      o.render_only = true;
    } else if (a == "--keep") {
      if (!has_value) return need("a new folder");
      o.keep = args[++i];
    } else {
      err << "aggscan validate: unknown option '" << a << "'\n";
      return 2;
    }
  }
  if (o.renderer != "sim" && o.renderer != "blender") {
    err << "aggscan validate: --renderer must be sim or blender, got '" << o.renderer << "'\n";
    return 2;
  }
  if (o.renderer != "blender" && (!o.look.empty() || o.look_index > 0)) {
    err << "aggscan validate: --look and --look-index apply to --renderer blender only\n";
    return 2;
  }
  if (o.backgrounds && o.renderer != "blender") {
    err << "aggscan validate: --backgrounds (empty-turntable photos) needs --renderer blender\n";
    return 2;
  }
  if (denoise_given && o.renderer != "blender") {
    err << "aggscan validate: --no-denoise applies to --renderer blender only (the sim "
           "renderer's noise is already a camera's)\n";
    return 2;
  }
  if (o.render_only && o.keep.empty()) {
    err << "aggscan validate: --render-only keeps the samples and needs --keep DIR\n";
    return 2;
  }
  if (o.sides > 2) {
    err << "aggscan validate: --sides must be 1 or 2\n";
    return 2;
  }
  if (o.calibration != "charuco" && o.calibration != "truth") {
    err << "aggscan validate: --calibration must be charuco or truth, got '" << o.calibration
        << "'\n";
    return 2;
  }
  if ((o.width > 0) != (o.height > 0)) {
    err << "aggscan validate: give --width and --height together\n";
    return 2;
  }
  if (o.width > 0 && (o.width < 320 || o.height < 240)) {
    err << "aggscan validate: --width/--height below 320x240 are too small to reconstruct a rock\n";
    return 2;
  }
  if (!o.mesh_dir.empty()) {
    if (count_given || seed_given) {
      err << "aggscan validate: --count and --seed choose procedural rocks; drop them with "
             "--mesh-dir\n";
      return 2;
    }
    double f = 0;
    if (o.unit.empty() || !UnitToMm(o.unit, &f)) {
      err << "aggscan validate: --mesh-dir needs --unit mm|cm|m (the unit of the files' "
             "coordinates)\n";
      return 2;
    }
    std::error_code ec;
    if (!fs::is_directory(o.mesh_dir, ec)) {
      err << "aggscan validate: --mesh-dir " << o.mesh_dir
          << " is not a folder; give a folder of PLY/OBJ/STL rock meshes\n";
      return 2;
    }
    if (MeshFiles(o.mesh_dir).empty()) {
      err << "aggscan validate: --mesh-dir " << o.mesh_dir << " has no .ply, .obj or .stl file\n";
      return 2;
    }
  } else if (!o.unit.empty() || o.scale_min_mm > 0) {
    err << "aggscan validate: --unit and --scale-to-mm apply to --mesh-dir only\n";
    return 2;
  }
  if (!o.keep.empty()) {
    std::error_code ec;
    if (fs::exists(o.keep, ec)) {
      err << "aggscan validate: --keep " << o.keep << " already exists; give a new folder\n";
      return 2;
    }
  }
  auto rep = RunValidation(o, err);
  if (!rep) {
    err << "aggscan validate: " << rep.error().ToString() << "\n";
    return 1;
  }
  if (o.render_only) {
    int rendered = 0;
    for (const ValidateRock& r : rep->rocks) rendered += r.status == "rendered";
    out << rendered << " sample(s) captured" << (o.renderer == "blender" ? " and rendered" : "")
        << " into " << o.keep << ", " << rep->summary.rocks_failed << " failed\n";
    return rep->summary.rocks_failed == 0 && rendered > 0 ? 0 : 1;
  }
  if (json_out) {
    out << ValidateReportToJson(*rep).dump(2) << "\n";
  } else {
    PrintValidateReport(*rep, out);
  }
  return rep->summary.pass ? 0 : 1;
}

}  // namespace aggscan
