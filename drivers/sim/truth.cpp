#include "drivers/sim/truth.h"

#include <cstdio>

#include "common/fsutil.h"
#include "common/log.h"
#include "common/mesh_props.h"
#include "drivers/sim/jpeg.h"
#include "drivers/sim/sim_camera.h"
#include "drivers/sim/world.h"

namespace aggscan::sim {

using nlohmann::json;

namespace {
json Vec(const Vec3& v) { return json::array({v.x, v.y, v.z}); }
json Mat(const std::array<double, 16>& m) { return json(std::vector<double>(m.begin(), m.end())); }
}  // namespace

void TruthRecorder::Attach(RigDevices& rig,
                           std::function<std::string(const std::string&)> truth_dir_for) {
  auto* cam = dynamic_cast<SimCamera*>(rig.camera.get());
  if (!cam) return;
  cam->SetTruthSink([this, truth_dir_for = std::move(truth_dir_for)](const StillRequest& req,
                                                                     const TruthView& tv) {
    const std::string dir = truth_dir_for(req.sample_id) + "/side" + std::to_string(tv.side);
    char name[64];
    std::snprintf(name, sizeof name, "view_%03d_mask.pgm", tv.view);
    Status s = MakeDirsDurable(dir);
    if (s) s = WritePgm(tv.mask, tv.width, tv.height, dir + "/" + name);
    if (!s)
      LogLine(LogLevel::kWarning, "sim", req.sample_id,
              "cannot write truth mask: " + s.error().ToString());
    json v = {{"side", tv.side},
              {"view", tv.view},
              {"platter_deg", tv.platter_deg},
              {"mask", "truth/side" + std::to_string(tv.side) + "/" + name},
              {"rock_to_camera_4x4", Mat(tv.rock_to_camera_4x4)}};
    std::lock_guard<std::mutex> l(mu_);
    views_.push_back(std::move(v));
  });
}

json TruthRecorder::SampleTruth(const Config& config) const {
  const MeshProps p = ComputeMeshProps(world_->rock());
  const Intrinsics in = world_->IntrinsicsFor(config.camera.width, config.camera.height);
  json poses = json::array();
  for (int side = 1; side <= config.capture.sides; ++side) {
    poses.push_back(
        {{"side", side},
         {"rock_to_turntable_4x4", Mat(world_->pose(side).rock_to_turntable.Matrix4())}});
  }
  json markers = json::array();
  for (const auto& m : world_->object_markers()) {
    markers.push_back({{"color", m.color}, {"head_mm", Vec(m.head)}, {"tail_mm", Vec(m.tail)}});
  }
  json labels = json::array();
  for (const auto& m : config.rig.markers)
    labels.push_back({{"color", m.color}, {"x_mm", m.x_mm}, {"y_mm", m.y_mm}});
  json truth = {{"units", "mm, degrees; matrices row-major 4x4"},
                {"seed", config.sim.seed},
                {"rock_mesh", config.sim.rock_mesh},
                {"rock_faces", world_->rock().faces.size()},
                {"poses", poses},
                {"object_markers", markers},
                {"background_markers", labels},
                {"camera",
                 {{"width", in.width},
                  {"height", in.height},
                  {"fx", in.fx},
                  {"fy", in.fy},
                  {"cx", in.cx},
                  {"cy", in.cy},
                  {"k1", in.k1},
                  {"k2", in.k2},
                  {"world_to_camera_4x4", Mat(world_->world_to_camera().Matrix4())}}}};
  truth.update(MeshPropsJson(p));  // the rock's morphology, in the fields morphology.json uses
  return truth;
}

Status TruthRecorder::WriteTruthJson(const std::string& path, const Config& config) const {
  json t = SampleTruth(config);
  if (const SimBoard* b = world_->board()) {
    // Scene "charuco": the calibration board's pose on the disc (board.h frames).
    t["scene"] = "charuco";
    t["board"] = {{"x_mm", b->x_mm},
                  {"y_mm", b->y_mm},
                  {"yaw_deg", b->yaw_deg},
                  {"width_mm", b->width_mm},
                  {"height_mm", b->height_mm}};
    t["calibration"] =
        CalibrationToJson(world_->TruthCalibration(config.camera.width, config.camera.height));
  }
  {
    std::lock_guard<std::mutex> l(mu_);
    t["views"] = views_;
  }
  return WriteFileAtomic(path, t.dump(1) + "\n");
}

}  // namespace aggscan::sim
