#include "cli/blender_render.h"

#include <limits.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "common/clock.h"
#include "common/fsutil.h"
#include "common/json_io.h"
#include "config/config.h"
#include "drivers/sim/board.h"
#include "drivers/sim/jpeg.h"
#include "drivers/sim/world.h"
#include "pipeline/core/subprocess.h"
#include "pipeline/worker/side_job.h"
#include "store/empty_turntable.h"
#include "store/layout.h"
#include "store/sample_files.h"

#ifndef AGGSCAN_SOURCE_DIR
#define AGGSCAN_SOURCE_DIR ""
#endif

namespace aggscan {

namespace {

namespace fs = std::filesystem;
using nlohmann::json;

constexpr const char* kScriptName = "render_capture.py";

json Vec(const sim::Vec3& v) { return json::array({v.x, v.y, v.z}); }

json Mat(const std::array<double, 16>& m) { return json(std::vector<double>(m.begin(), m.end())); }

// A row-major 4x4 rigid transform from truth.json; false when malformed.
bool RigidFrom(const json& j, sim::Rigid* out) {
  if (!j.is_array() || j.size() != 16) return false;
  for (const json& x : j)
    if (!x.is_number()) return false;
  for (size_t r = 0; r < 3; ++r) {
    for (size_t c = 0; c < 3; ++c) out->R[3 * r + c] = j[4 * r + c].get<double>();
  }
  out->t = {j[3].get<double>(), j[7].get<double>(), j[11].get<double>()};
  return true;
}

bool OneOf(const std::string& v, const std::vector<std::string>& known) {
  return std::find(known.begin(), known.end(), v) != known.end();
}

std::string Joined(const std::vector<std::string>& v) {
  std::string s;
  for (const std::string& x : v) s += (s.empty() ? "" : ", ") + x;
  return s;
}

double Iou(const cv::Mat& a, const cv::Mat& b) {
  const int inter = cv::countNonZero(a & b), uni = cv::countNonZero(a | b);
  return uni > 0 ? static_cast<double>(inter) / uni : 1.0;
}

// The scene file the render script reads (its docstring has the format).
Result<json> SceneJson(const std::string& sample_dir, const std::string& scene_dir,
                       const Config& config, const sim::SimWorld& world, const json& truth,
                       const BlenderLook& look, const BlenderOptions& o) {
  const sim::Intrinsics in = world.IntrinsicsFor(config.camera.width, config.camera.height);
  json scene = {{"format", "aggscan-blender-scene-1"},
                {"camera",
                 {{"width", in.width},
                  {"height", in.height},
                  {"fx", in.fx},
                  {"fy", in.fy},
                  {"cx", in.cx},
                  {"cy", in.cy},
                  {"world_to_camera_4x4", Mat(world.world_to_camera().Matrix4())}}},
                {"disc",
                 {{"radius_mm", config.rig.turntable_diameter_mm / 2},
                  {"thickness_mm", sim::kDiscThicknessMm}}},
                {"look", look.ToJson()},
                {"render",
                 {{"samples", o.samples},
                  {"threads", o.threads},
                  {"denoise", o.denoise},
                  {"camera_noise_levels", config.sim.noise_sigma}}}};
  json labels = json::array();
  for (const RigMarker& m : config.rig.markers) {
    std::array<float, 3> a{};
    if (!sim::ColorAlbedo(m.color, &a)) continue;
    labels.push_back({{"color", m.color},
                      {"x_mm", m.x_mm},
                      {"y_mm", m.y_mm},
                      {"size_mm", config.rig.marker_size_mm},
                      {"albedo", {a[0], a[1], a[2]}}});
  }
  scene["labels"] = labels;
  if (const sim::SimBoard* b = world.board()) {
    cv::Mat img(b->image.height, b->image.width, CV_8UC1,
                const_cast<uint8_t*>(b->image.pixels.data()));
    if (!cv::imwrite(scene_dir + "/board.png", img)) {
      return MakeError(ErrorClass::kIo, "cannot write " + scene_dir + "/board.png");
    }
    scene["board"] = {{"image", "board.png"},
                      {"x_mm", b->x_mm},
                      {"y_mm", b->y_mm},
                      {"yaw_deg", b->yaw_deg},
                      {"width_mm", b->width_mm},
                      {"height_mm", b->height_mm},
                      {"paper_margin_mm", sim::kBoardPaperMarginMm},
                      {"paper_albedo", sim::kPaperAlbedo},
                      {"ink_albedo", 0.04}};
  } else {
    json verts = json::array(), faces = json::array();
    for (const auto& v : world.rock().vertices)
      for (double x : v) verts.push_back(x);
    for (const auto& f : world.rock().faces)
      for (int i : f) faces.push_back(i);
    if (Status s = WriteFileAtomic(scene_dir + "/rock.json",
                                   json{{"vertices", verts}, {"faces", faces}}.dump());
        !s) {
      return s.error();
    }
    json markers = json::array();
    for (const sim::ObjectMarker& m : world.object_markers()) {
      markers.push_back({{"color", m.color},
                         {"origin", Vec(m.origin)},
                         {"axis", Vec(m.axis)},
                         {"normal", Vec(m.normal)},
                         {"head_mm", m.head_mm},
                         {"gap_mm", m.gap_mm},
                         {"tail_mm", m.tail_mm},
                         {"width_mm", m.width_mm},
                         {"albedo", {m.albedo[0], m.albedo[1], m.albedo[2]}}});
    }
    scene["rock"] = {{"mesh", "rock.json"}, {"markers", markers}};
  }
  const sim::Rigid camera_to_world = world.world_to_camera().Inverse();
  json views = json::array();
  for (const json& v : truth.value("views", json::array())) {
    sim::Rigid r2c;
    if (!v.is_object() || !v.contains("side") || !v.contains("view") ||
        !v.contains("platter_deg") || !RigidFrom(v.value("rock_to_camera_4x4", json()), &r2c)) {
      return MakeError(
          ErrorClass::kInvalidArgument,
          sample_dir + "/truth.json: a view without side, view, platter_deg or rock_to_camera_4x4");
    }
    const int side = v["side"].get<int>(), view = v["view"].get<int>();
    char stem[64];
    std::snprintf(stem, sizeof stem, "side%d/view_%03d", side, view);
    views.push_back({{"side", side},
                     {"view", view},
                     {"platter_deg", v["platter_deg"]},
                     {"rock_to_world_4x4", Mat((camera_to_world * r2c).Matrix4())},
                     {"image", std::string(stem) + ".png"},
                     {"mask", std::string(stem) + "_mask.png"}});
    // The empty turntable once, at side 1's angles: the rig's set serves
    // every side (matched by angle).
    if (o.empty_plates && world.rock().vertices.size() > 0 && side == 1)
      views.back()["empty_image"] = "empty/" + std::string(stem) + ".png";
  }
  if (views.empty())
    return MakeError(ErrorClass::kInvalidArgument, sample_dir + "/truth.json lists no views");
  scene["views"] = views;
  return scene;
}

// The photo and truth mask of one view replaced by the renderer's; returns
// the silhouette IoU against the sim's mask (-1 for a scene without a rock).
// One of Blender's PNG frames stored as the rig stores its photos (JPEG at
// the camera's quality) at `jpeg_path`; returns the frame's size.
Result<cv::Size> StoreFrameAsJpeg(const std::string& png, const std::string& what, int jpeg_quality,
                                  const std::string& jpeg_path) {
  cv::Mat bgr = cv::imread(png, cv::IMREAD_COLOR);
  if (bgr.empty())
    return MakeError(ErrorClass::kIo, "Blender wrote no readable " + what + " " + png);
  cv::Mat rgb;
  cv::cvtColor(bgr, rgb, cv::COLOR_BGR2RGB);
  Result<std::vector<unsigned char>> jpeg =
      sim::EncodeJpeg(rgb.data, rgb.cols, rgb.rows, jpeg_quality);
  if (!jpeg) return jpeg.error();
  if (Status s = WriteFileAtomic(jpeg_path, *jpeg); !s) return s.error();
  return bgr.size();
}

Result<double> IngestView(const std::string& sample_dir, const std::string& scene_dir,
                          const json& view, int jpeg_quality, bool has_rock) {
  const int side = view["side"].get<int>(), v = view["view"].get<int>();
  Result<cv::Size> size = StoreFrameAsJpeg(
      scene_dir + "/" + view["image"].get<std::string>(), "frame", jpeg_quality,
      sample_dir + "/" + layout::SideDirName(side) + "/" + layout::ViewImageName(v));
  if (!size) return size.error();
  if (!has_rock) return -1.0;
  const std::string mask_png = scene_dir + "/" + view["mask"].get<std::string>();
  cv::Mat mask = cv::imread(mask_png, cv::IMREAD_GRAYSCALE);
  if (mask.empty() || mask.size() != *size) {
    return MakeError(ErrorClass::kIo,
                     "Blender wrote no readable mask " + mask_png + " of the frame's size");
  }
  mask = mask > 127;
  char name[64];
  std::snprintf(name, sizeof name, "/side%d/view_%03d_mask.pgm", side, v);
  const std::string truth_mask = sample_dir + "/" + layout::kTruthDir + name;
  double iou = 0;
  if (Result<sim::GrayImage> old = sim::ReadPgm(truth_mask);
      old && old->width == mask.cols && old->height == mask.rows) {
    cv::Mat sim_mask(old->height, old->width, CV_8UC1, old->pixels.data());
    iou = Iou(mask, sim_mask > 127);
  }
  std::vector<uint8_t> px(mask.datastart, mask.dataend);
  if (Status s = sim::WritePgm(px, mask.cols, mask.rows, truth_mask); !s) return s.error();
  return iou;
}

// A side manifest's byte counts brought in line with the replaced photos.
Status UpdateManifest(const std::string& side_dir) {
  Result<SideManifest> m = ReadSideManifest(side_dir);
  if (!m) return m.error();
  for (SideManifest::Entry& v : m->views) {
    std::error_code ec;
    const auto size = fs::file_size(side_dir + "/" + v.image, ec);
    if (ec) return MakeError(ErrorClass::kIo, "cannot stat " + side_dir + "/" + v.image);
    v.bytes = static_cast<int64_t>(size);
  }
  return jsonio::WriteFile(side_dir + "/" + layout::kManifest, m->ToJson());
}

// The empty-turntable frames (side 1's views) as the sample's own set of
// empty-turntable photos (SAMPLE/empty/, store/empty_turntable.h), encoded as
// the rig encodes its photos, each at the angle the turntable measured for
// that view; sample.json records the set as arming records the rig's.
Status IngestEmptyTurntable(const std::string& sample_dir, const std::string& scene_dir,
                            const std::vector<json>& views, int jpeg_quality,
                            const BlenderLook& look) {
  const std::string staging = scene_dir + "/empty-jpeg";
  if (Status s = MakeDirsDurable(staging); !s) return s;
  EmptyTurntableSet set;
  set.id = "blender-" + look.Name();
  std::replace(set.id.begin(), set.id.end(), '/', '-');
  set.source = "Blender render of " + look.Name() + " without the rock";
  set.captured_utc = NowUtcString();
  std::vector<std::string> photos;
  for (const json& view : views) {
    const int side = view["side"].get<int>(), v = view["view"].get<int>();
    const std::string name = layout::ViewImageName(v);
    Result<cv::Size> size =
        StoreFrameAsJpeg(scene_dir + "/" + view["empty_image"].get<std::string>(),
                         "empty-turntable frame", jpeg_quality, staging + "/" + name);
    if (!size) return size.error();
    set.width = size->width;
    set.height = size->height;
    const std::string side_dir = sample_dir + "/" + layout::SideDirName(side);
    const Result<ViewSidecar> car = ReadViewSidecar(side_dir, v);
    const double angle = car && car->measured_angle_deg ? *car->measured_angle_deg : std::nan("");
    if (!std::isfinite(angle))
      return MakeError(ErrorClass::kCorrupt,
                       side_dir + "/" + layout::ViewSidecarName(v) +
                           " has no measured angle for the empty-turntable photo",
                       car ? std::string() : car.error().ToString());
    set.views.push_back({name, angle});
    photos.push_back(staging + "/" + name);
  }
  if (set.views.empty()) return {};
  if (Status s = WriteEmptyTurntableSet(sample_dir + "/" + layout::kEmptyDir, set, photos); !s)
    return s;
  auto rec_text = ReadFile(sample_dir + "/" + layout::kSampleRecord);
  json rec = rec_text ? json::parse(*rec_text, nullptr, false) : json();
  if (!rec.is_object())
    return MakeError(ErrorClass::kCorrupt, sample_dir + "/sample.json is unreadable");
  rec["empty_turntable"] = {
      {"set", set.id}, {"captured_utc", set.captured_utc}, {"views", set.views.size()}};
  return WriteFileAtomic(sample_dir + "/" + layout::kSampleRecord, rec.dump(2) + "\n");
}

}  // namespace

json BlenderLook::ToJson() const {
  return {
      {"surface", surface}, {"light", light}, {"stone", stone}, {"seed", seed}, {"name", Name()}};
}

const std::vector<std::string>& BlenderSurfaces() {
  static const std::vector<std::string> k = {"white", "light-grey", "wood", "rubber-mat", "gravel"};
  return k;
}
const std::vector<std::string>& BlenderLights() {
  static const std::vector<std::string> k = {"softbox", "two-lights", "overcast", "low-sun"};
  return k;
}
const std::vector<std::string>& BlenderStones() {
  static const std::vector<std::string> k = {"granite", "dolomite", "basalt", "wet"};
  return k;
}

Result<BlenderLook> ParseBlenderLook(const std::string& spec) {
  BlenderLook look;
  std::stringstream ss(spec);
  std::string item;
  while (std::getline(ss, item, ',')) {
    if (item.empty()) continue;
    const size_t eq = item.find('=');
    const std::string key = item.substr(0, eq),
                      value = eq == std::string::npos ? "" : item.substr(eq + 1);
    const std::vector<std::string>* known = nullptr;
    std::string* field = nullptr;
    if (key == "surface") known = &BlenderSurfaces(), field = &look.surface;
    if (key == "light") known = &BlenderLights(), field = &look.light;
    if (key == "stone") known = &BlenderStones(), field = &look.stone;
    if (key == "seed") {
      char* end = nullptr;
      look.seed = std::strtoull(value.c_str(), &end, 10);
      if (value.empty() || *end != '\0') {
        return MakeError(ErrorClass::kInvalidArgument,
                         "look: seed expects a non-negative integer, got '" + value + "'");
      }
      continue;
    }
    if (!known) {
      return MakeError(ErrorClass::kInvalidArgument, "look: unknown key '" + key + "' in '" + item +
                                                         "' (known: surface, light, stone, seed)");
    }
    if (!OneOf(value, *known)) {
      return MakeError(ErrorClass::kInvalidArgument,
                       "look: " + key + " '" + value + "' is not one of " + Joined(*known));
    }
    *field = value;
  }
  return look;
}

BlenderLook BatchLook(int i, uint64_t seed) {
  // Surfaces and lights cycle (5 and 4 values: 20 rocks see every pairing);
  // the stones are laid out so that the first ten rocks have every stone,
  // a dark basalt on the dark rubber mat and a yellowish dolomite on wood
  // among them, and every stone meets four surfaces over twenty rocks.
  static const char* const kStones[20] = {
      "granite", "dolomite", "dolomite", "basalt", "wet",    "basalt",  "wet",
      "granite", "wet",      "dolomite", "wet",    "basalt", "granite", "dolomite",
      "granite", "dolomite", "granite",  "basalt", "basalt", "wet"};
  const auto& s = BlenderSurfaces();
  const auto& l = BlenderLights();
  BlenderLook look;
  const size_t k = static_cast<size_t>(i);
  look.surface = s[k % s.size()];
  look.light = l[k % l.size()];
  look.stone = kStones[k % 20];
  look.seed = seed + k;
  return look;
}

std::string BlenderScriptPath() {
  if (const char* e = std::getenv("AGGSCAN_BLENDER_SCRIPT"); e && *e) return e;
  std::string installed = ExecutableDir() + "/../share/aggscan/blender/" + kScriptName;
  if (PathExists(installed)) return installed;
  return std::string(AGGSCAN_SOURCE_DIR) + "/scripts/blender/" + kScriptName;
}

bool BlenderAvailable(const BlenderOptions& o) {
  SubprocessOptions so;
  so.timeout_s = 60;
  auto r = RunSubprocess({o.blender, "-b", "--factory-startup", "-noaudio", "--version"}, so);
  return r && r->Succeeded();
}

json BlenderRenderReport::ToJson() const {
  json j = {{"renderer", renderer},
            {"frames", frames},
            {"mean_frame_seconds", mean_frame_s},
            {"max_frame_seconds", max_frame_s},
            {"wall_seconds", wall_s}};
  if (silhouette_iou_mean > 0) {
    j["silhouette_iou_vs_sim_min"] = silhouette_iou_min;
    j["silhouette_iou_vs_sim_mean"] = silhouette_iou_mean;
  }
  return j;
}

Result<BlenderRenderReport> RerenderWithBlender(const std::string& sample_dir,
                                                const BlenderLook& look, const BlenderOptions& opts,
                                                std::ostream& log) {
  auto truth_text = ReadFile(sample_dir + "/truth.json");
  if (!truth_text) {
    return MakeError(
        ErrorClass::kInvalidArgument,
        sample_dir + " has no truth.json; capture it with `aggscan sim capture` (truth on)");
  }
  json truth = json::parse(*truth_text, nullptr, false);
  if (!truth.is_object())
    return MakeError(ErrorClass::kInvalidArgument, sample_dir + "/truth.json is not JSON");
  std::vector<ConfigProblem> problems;
  Result<Config> cfg = LoadConfigFile(sample_dir + "/" + layout::kConfigCopy, &problems);
  if (!cfg || !problems.empty()) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "cannot read the sample's " + std::string(layout::kConfigCopy) + ": " +
                         (problems.empty() ? cfg.error().ToString() : problems.front().ToString()));
  }
  Config config = *cfg;
  if (config.sim.k1 != 0 || config.sim.k2 != 0) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "the sample was captured with lens distortion (sim.k1/k2); Blender draws a "
                     "pinhole camera, so "
                     "capture it with [sim] k1 = 0 and k2 = 0");
  }
  if (!config.rig.aruco_markers.empty()) {
    return MakeError(
        ErrorClass::kInvalidArgument,
        "the Blender renderer does not draw rig.aruco_markers; validate it with the colour labels");
  }
  const bool charuco = config.sim.scene == "charuco";
  if (charuco) config.sim.board_image = sample_dir + "/board.pgm";
  Result<std::shared_ptr<sim::SimWorld>> world = sim::SimWorld::Create(config);
  if (!world) return world.error();

  const std::string scene_dir = sample_dir + "/blender";
  if (Status s = MakeDirsDurable(scene_dir); !s) return s.error();
  Result<json> scene = SceneJson(sample_dir, scene_dir, config, **world, truth, look, opts);
  if (!scene) return scene.error();
  if (Status s = WriteFileAtomic(scene_dir + "/scene.json", scene->dump(1)); !s) return s.error();

  const std::string script = opts.script.empty() ? BlenderScriptPath() : opts.script;
  if (!PathExists(script)) {
    return MakeError(ErrorClass::kNotFound,
                     "the Blender render script " + script +
                         " is missing; set AGGSCAN_BLENDER_SCRIPT to scripts/blender/" +
                         kScriptName + " of the source tree");
  }
  const size_t frames = (*scene)["views"].size();
  SubprocessOptions so;
  so.log_path = scene_dir + "/blender.log";
  so.timeout_s = 120 + opts.frame_timeout_s * static_cast<double>(frames);
  log << "blender: rendering " << frames << " frames of " << sample_dir << " (" << look.Name()
      << ", " << opts.samples << " samples/px" << (opts.denoise ? ", denoised" : "") << ")\n"
      << std::flush;
  auto run = RunSubprocess({opts.blender, "-b", "--factory-startup", "-noaudio",
                            "--python-exit-code", "3", "--python", script, "--", scene_dir},
                           so);
  if (!run) {
    if (run.error().cls == ErrorClass::kNotFound) {
      return MakeError(ErrorClass::kNotFound, "cannot run '" + opts.blender +
                                                  "': " + run.error().message +
                                                  "; install Debian's blender");
    }
    return run.error();
  }
  if (!run->Succeeded()) {
    return MakeError(ErrorClass::kInternal, "blender " + run->Describe() + "; the end of " +
                                                so.log_path + ":\n" + TailOfFile(so.log_path, 12));
  }
  auto rep_text = ReadFile(scene_dir + "/render_report.json");
  json rj = rep_text ? json::parse(*rep_text, nullptr, false) : json();
  if (!rj.is_object())
    return MakeError(ErrorClass::kInternal, "blender wrote no render_report.json in " + scene_dir);

  BlenderRenderReport rep;
  rep.renderer = rj.value("renderer", "blender");
  rep.wall_s = run->wall_s;
  for (const json& t : rj.value("frame_seconds", json::array())) {
    const double s = t.is_number() ? t.get<double>() : 0.0;
    rep.mean_frame_s += s;
    rep.max_frame_s = std::max(rep.max_frame_s, s);
    ++rep.frames;
  }
  if (rep.frames > 0) rep.mean_frame_s /= rep.frames;
  double iou_sum = 0;
  int iou_n = 0;
  rep.silhouette_iou_min = 1;
  std::vector<int> sides;
  std::vector<json> empty_views;
  for (const json& v : (*scene)["views"]) {
    Result<double> iou = IngestView(sample_dir, scene_dir, v, config.camera.jpeg_quality, !charuco);
    if (!iou) return iou.error();
    if (*iou >= 0) {
      iou_sum += *iou;
      ++iou_n;
      rep.silhouette_iou_min = std::min(rep.silhouette_iou_min, *iou);
    }
    const int side = v["side"].get<int>();
    if (std::find(sides.begin(), sides.end(), side) == sides.end()) sides.push_back(side);
    if (v.contains("empty_image")) empty_views.push_back(v);
  }
  if (Status s = IngestEmptyTurntable(sample_dir, scene_dir, empty_views,
                                      config.camera.jpeg_quality, look);
      !s)
    return s.error();
  rep.silhouette_iou_mean = iou_n > 0 ? iou_sum / iou_n : 0;
  if (iou_n == 0) rep.silhouette_iou_min = 0;
  for (int side : sides) {
    if (Status s = UpdateManifest(sample_dir + "/" + layout::SideDirName(side)); !s)
      return s.error();
  }
  truth["renderer"] = rep.ToJson();
  truth["renderer"]["look"] = look.ToJson();
  truth["renderer"]["samples_per_pixel"] = opts.samples;
  truth["renderer"]["denoise"] = opts.denoise;
  truth["renderer"]["exposure_ev"] = rj.value("exposure_ev", 0.0);
  if (Status s = WriteFileAtomic(sample_dir + "/truth.json", truth.dump(1) + "\n"); !s)
    return s.error();
  return rep;
}

}  // namespace aggscan
