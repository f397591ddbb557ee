#include "pipeline/poses/hand_turned.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <opencv2/imgproc.hpp>

#include "pipeline/core/geometry.h"

namespace aggscan {
namespace {

struct Reference {
  std::string name;
  bool aruco = false;
  std::vector<Eigen::Vector3d> table;   // points in the table frame (mm)
  std::vector<Eigen::Vector2d> pixels;  // their sightings, distorted pixels
};

// Squared reprojection errors of the references at angle theta; a point
// behind the camera costs as much as a pixel at the far corner.
double Cost(const std::vector<Reference>& refs, const RigCalibration& cal, double theta,
            std::vector<double>* per_point = nullptr) {
  const geom::Rigid3 cam = geom::Rigid3::FromRowMajor4(cal.CamFromTable(theta));
  const double far = static_cast<double>(cal.camera.width) * cal.camera.width +
                     static_cast<double>(cal.camera.height) * cal.camera.height;
  double sum = 0;
  if (per_point) per_point->clear();
  for (const Reference& r : refs) {
    for (size_t i = 0; i < r.table.size(); ++i) {
      const std::optional<Eigen::Vector2d> p = geom::ProjectPoint(cal.camera, cam, r.table[i]);
      const double e = p ? (*p - r.pixels[i]).squaredNorm() : far;
      sum += e;
      if (per_point) per_point->push_back(e);
    }
  }
  return sum;
}

// The best angle: a grid over the whole turn, then a golden-section search
// around the grid's best (the cost is smooth and single-welled there).
double Solve(const std::vector<Reference>& refs, const RigCalibration& cal, double step) {
  double best = 0, best_cost = std::numeric_limits<double>::infinity();
  for (double t = 0; t < 360.0; t += step) {
    const double c = Cost(refs, cal, t);
    if (c < best_cost) best_cost = c, best = t;
  }
  double lo = best - step, hi = best + step;
  const double g = (std::sqrt(5.0) - 1.0) / 2.0;
  double x1 = hi - g * (hi - lo), x2 = lo + g * (hi - lo);
  double f1 = Cost(refs, cal, x1), f2 = Cost(refs, cal, x2);
  while (hi - lo > 1e-6) {
    if (f1 < f2) {
      hi = x2, x2 = x1, f2 = f1;
      x1 = hi - g * (hi - lo);
      f1 = Cost(refs, cal, x1);
    } else {
      lo = x1, x1 = x2, f1 = f2;
      x2 = lo + g * (hi - lo);
      f2 = Cost(refs, cal, x2);
    }
  }
  const double t = 0.5 * (lo + hi);
  return t - 360.0 * std::floor(t / 360.0);
}

// RMS and largest error per reference (px) at theta.
void Residuals(const std::vector<Reference>& refs, const RigCalibration& cal, double theta,
               double* rms, double* max, std::vector<double>* per_ref) {
  std::vector<double> e;
  Cost(refs, cal, theta, &e);
  double sum = 0, mx = 0;
  size_t k = 0;
  per_ref->assign(refs.size(), 0.0);
  for (size_t r = 0; r < refs.size(); ++r) {
    double s = 0;
    for (size_t i = 0; i < refs[r].table.size(); ++i, ++k) {
      s += e[k];
      mx = std::max(mx, std::sqrt(e[k]));
    }
    sum += s;
    (*per_ref)[r] = std::sqrt(s / static_cast<double>(refs[r].table.size()));
  }
  *rms = k ? std::sqrt(sum / static_cast<double>(k)) : 0;
  *max = mx;
}

}  // namespace

double UnwrapNear(double angle_deg, double near_deg) {
  return angle_deg + 360.0 * std::round((near_deg - angle_deg) / 360.0);
}

TableAngleFit FitTableAngle(const ViewMarkers& markers, const ArucoViewDetections* aruco,
                            const RigCalibration& cal, const RigConfig& rig,
                            const TableAngleOptions& opts) {
  std::vector<Reference> refs;
  for (const LabelSighting& s : markers.labels) {
    for (const RigMarker& m : rig.markers) {
      if (m.color != s.color) continue;
      refs.push_back(
          {s.color + " label", false, {Eigen::Vector3d(m.x_mm, m.y_mm, 0.0)}, {s.center_px}});
    }
  }
  if (aruco) {
    for (const ArucoSighting& s : aruco->markers) {
      for (const ArucoMarker& m : rig.aruco_markers) {
        if (m.id != s.id) continue;
        Reference r{"ArUco marker " + std::to_string(m.id), true, {}, {}};
        for (int k = 0; k < 4; ++k) {
          r.table.push_back(ArucoCornerMm(m, rig.aruco_size_mm, k));
          r.pixels.push_back(s.corners_px[k]);
        }
        refs.push_back(std::move(r));
      }
    }
  }
  TableAngleFit fit;
  auto count = [&] {
    fit.labels = fit.aruco_markers = 0;
    for (const Reference& r : refs) ++(r.aruco ? fit.aruco_markers : fit.labels);
  };
  count();
  if (static_cast<int>(refs.size()) < opts.min_references) {
    fit.problem = "only " + std::to_string(refs.size()) + " of the disc's labels and markers (" +
                  std::to_string(opts.min_references) +
                  " needed) are in view: keep them uncovered and inside the frame, away from the "
                  "rock";
    return fit;
  }
  std::vector<double> per_ref;
  fit.angle_deg = Solve(refs, cal, opts.grid_step_deg);
  Residuals(refs, cal, fit.angle_deg, &fit.rms_px, &fit.max_px, &per_ref);
  // One reference at odds with the others (a label half hidden, a paint
  // smear of the label's colour) is dropped while enough remain.
  if (fit.rms_px > opts.max_rms_px && static_cast<int>(refs.size()) > opts.min_references) {
    const auto worst = std::max_element(per_ref.begin(), per_ref.end()) - per_ref.begin();
    fit.dropped.push_back(refs[static_cast<size_t>(worst)].name);
    refs.erase(refs.begin() + worst);
    count();
    fit.angle_deg = Solve(refs, cal, opts.grid_step_deg);
    Residuals(refs, cal, fit.angle_deg, &fit.rms_px, &fit.max_px, &per_ref);
  }
  if (fit.rms_px > opts.max_rms_px) {
    char buf[64];
    std::snprintf(buf, sizeof buf, "%.2f px", fit.rms_px);
    fit.problem = std::string("the disc's labels and markers disagree on the angle (RMS ") + buf +
                  "): check the rig calibration and that the labels lie where [rig] says";
    return fit;
  }
  fit.ok = true;
  return fit;
}

double RockSharpness(const cv::Mat& bgr, const cv::Mat& mask, cv::Point2d along) {
  if (bgr.empty() || mask.empty()) return 0;
  cv::Mat inner;
  cv::erode(mask, inner, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(9, 9)));
  const cv::Rect box = cv::boundingRect(inner);
  if (box.area() == 0) return 0;
  cv::Mat grey, smooth, gx, gy;
  cv::cvtColor(bgr(box), grey, cv::COLOR_BGR2GRAY);
  grey.convertTo(grey, CV_32F);
  cv::GaussianBlur(grey, smooth, cv::Size(0, 0), 0.7);
  cv::Sobel(smooth, gx, CV_32F, 1, 0);
  cv::Sobel(smooth, gy, CV_32F, 0, 1);
  cv::Mat energy;
  const double n = std::hypot(along.x, along.y);
  if (n > 0) {
    const cv::Mat d = gx * (along.x / n) + gy * (along.y / n);
    energy = d.mul(d);
  } else {
    energy = gx.mul(gx) + gy.mul(gy);
  }
  return cv::mean(energy, inner(box))[0];
}

cv::Point2d TurnDirection(const RigCalibration& cal) {
  const geom::Rigid3 cam = geom::Rigid3::FromRowMajor4(cal.CamFromTable(0.0));
  const auto p0 = geom::ProjectPoint(cal.camera, cam, Eigen::Vector3d(0, 0, 0));
  const auto p1 = geom::ProjectPoint(cal.camera, cam, Eigen::Vector3d(0, 0, 100));
  if (!p0 || !p1 || (*p1 - *p0).norm() < 1e-9) return {1, 0};
  const Eigen::Vector2d axis = (*p1 - *p0).normalized();
  return {-axis.y(), axis.x()};
}

}  // namespace aggscan
