// Two-side captures rendered by the sim rig for the marker and stitch tests:
// JPEG round trip (quality 92, as the rig stores them), the sim's sensor noise
// and lens distortion, and turntable angle errors (the platter stops at the
// commanded angle + N(0, 0.05 deg); the measured angle the worker gets differs
// from where it really is by N(0, 0.02 deg)).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>
#include <string>
#include <vector>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/sim/render.h"
#include "drivers/sim/world.h"
#include "pipeline/core/geometry.h"
#include "pipeline/markers/markers.h"
#include "pipeline/stitch/stitch.h"

namespace aggscan::testing {

struct SimView {
  cv::Mat bgr;         // what the worker reads (after JPEG)
  cv::Mat truth_mask;  // renderer's rock mask
  double true_deg = 0;
  double measured_deg = 0;
};

inline std::vector<SimView> RenderSide(sim::Renderer& r, int side, int views, uint64_t seed,
                                       double step_deg = 30.0, double stop_sigma_deg = 0.05,
                                       double read_sigma_deg = 0.02) {
  std::mt19937_64 rng(seed * 7919 + side);
  std::normal_distribution<double> stop(0.0, stop_sigma_deg), read(0.0, read_sigma_deg);
  std::vector<SimView> out;
  for (int i = 0; i < views; ++i) {
    SimView v;
    v.true_deg = step_deg * i + (i == 0 ? 0.0 : stop(rng));  // homing defines 0
    v.measured_deg = v.true_deg + read(rng);
    sim::RenderOptions o;
    o.want_mask = true;
    o.noise_seed = seed * 1000 + side * 100 + i;
    sim::RenderedImage img = r.Render(side, v.true_deg, o);
    cv::Mat rgb(img.height, img.width, CV_8UC3, img.rgb.data()), bgr;
    cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
    std::vector<unsigned char> jpg;
    cv::imencode(".jpg", bgr, jpg, {cv::IMWRITE_JPEG_QUALITY, 92});
    v.bgr = cv::imdecode(jpg, cv::IMREAD_COLOR);
    v.truth_mask = cv::Mat(img.height, img.width, CV_8UC1, img.mask.data()).clone();
    out.push_back(std::move(v));
  }
  return out;
}

inline Eigen::Vector3d ToEigen(const sim::Vec3& p) { return {p.x, p.y, p.z}; }

inline geom::Rigid3 ToRigid3(const sim::Rigid& r) {
  return geom::Rigid3::FromRowMajor4(r.Matrix4());
}

/// One side rendered, its markers detected (with the renderer's masks) and
/// the views' poses from the calibration and the measured angles.
struct SideCapture {
  std::vector<SimView> views;
  std::vector<ViewMarkers> markers;
  std::vector<geom::Rigid3> poses;
  double detect_ms_per_view = 0;
};

inline const std::vector<std::string>& LabelColors() {
  static const std::vector<std::string> c{"red", "green", "blue", "yellow"};
  return c;
}
inline const std::vector<std::string>& ObjectColors() {
  static const std::vector<std::string> c{"purple", "red"};
  return c;
}

inline SideCapture CaptureSide(sim::Renderer& r, const RigCalibration& cal, int side, uint64_t seed,
                               int views = 30) {
  SideCapture c;
  c.views = RenderSide(r, side, views, seed);
  const TimeNs t0 = MonotonicNs();
  for (const SimView& v : c.views) {
    Result<ViewMarkers> m =
        DetectViewMarkers(v.bgr, v.truth_mask, LabelColors(), ObjectColors(), &cal.camera);
    c.markers.push_back(m.ok() ? m.value() : ViewMarkers{});
    c.poses.push_back(geom::CamFromTable(cal, v.measured_deg));
  }
  c.detect_ms_per_view = static_cast<double>(MonotonicNs() - t0) / 1e6 / views;
  return c;
}

/// Head or tail of an object marker in the side's table frame (truth).
inline Eigen::Vector3d TruthMarkerPoint(const sim::SimWorld& w, int side, const std::string& color,
                                        const std::string& segment) {
  for (const sim::ObjectMarker& m : w.object_markers()) {
    if (m.color == color) {
      return ToEigen(w.pose(side).rock_to_turntable.Apply(segment == "head" ? m.head : m.tail));
    }
  }
  return Eigen::Vector3d::Constant(1e9);
}

/// True motion side-2 table frame -> side-1 table frame.
inline geom::Rigid3 TruthStitch(const sim::SimWorld& w) {
  return ToRigid3(w.pose(1).rock_to_turntable) * ToRigid3(w.pose(2).rock_to_turntable).Inverse();
}

/// Error of a stitch over the rock: RMS and max displacement (mm) of the rock
/// mesh's vertices on side 2 between T and the truth, and the rotation error.
struct StitchError {
  double rms_mm = 0, max_mm = 0, rot_deg = 0;
};
inline StitchError MeasureStitch(const sim::SimWorld& w, const geom::Rigid3& T) {
  const geom::Rigid3 truth = TruthStitch(w);
  const sim::Rigid& p2 = w.pose(2).rock_to_turntable;
  StitchError e;
  double ss = 0;
  for (const auto& v : w.rock().vertices) {
    const Eigen::Vector3d p = ToEigen(p2.Apply(sim::ToVec3(v)));
    const double d = (T.Apply(p) - truth.Apply(p)).norm();
    ss += d * d, e.max_mm = std::max(e.max_mm, d);
  }
  e.rms_mm = std::sqrt(ss / static_cast<double>(w.rock().vertices.size()));
  e.rot_deg = geom::RotationAngleDeg(T.R * truth.R.transpose());
  return e;
}

}  // namespace aggscan::testing
