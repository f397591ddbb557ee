// Poses of a table turned by hand (turntable.backend = "manual", the study's
// own protocol): nothing measures the angle, so each view's turntable angle
// is measured from what is fixed on the disc and known in the table frame:
// the background labels' centres (rig.markers) and the ArUco markers'
// corners (rig.aruco_markers), seen with the rig calibration. One unknown per
// view, the angle theta in p_cam = cam_from_table0 * Rz(theta) * p; the fit
// minimises the reprojection error in distorted pixels.
//
// A view shot while the table was still turning is smeared along the turn;
// its sharpness inside the rock, against the side's median, names it.
#pragma once

#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "common/rig_calibration.h"
#include "config/config.h"
#include "pipeline/markers/aruco_scale.h"
#include "pipeline/markers/markers.h"

namespace aggscan {

struct TableAngleOptions {
  int min_references = 2;   // labels + ArUco markers; one alone has no check
  double max_rms_px = 2.0;  // a fit worse than this is refused
  double grid_step_deg = 0.5;
};

struct TableAngleFit {
  bool ok = false;
  double angle_deg = 0;  // in [0, 360)
  double rms_px = 0, max_px = 0;
  int labels = 0, aruco_markers = 0;  // references used
  std::vector<std::string> dropped;   // a reference left out as inconsistent with the others
  std::string problem;                // why not ok, with what to do
};

/// The turntable angle of one view from the labels and ArUco markers found in
/// it (aruco may be null), with the rig calibration and the rig's layout.
TableAngleFit FitTableAngle(const ViewMarkers& markers, const ArucoViewDetections* aruco,
                            const RigCalibration& cal, const RigConfig& rig,
                            const TableAngleOptions& opts = {});

/// angle_deg + 360 k closest to near_deg.
double UnwrapNear(double angle_deg, double near_deg);

/// Fine-detail energy of the photo inside the rock (the mask eroded by a few
/// pixels, so the silhouette's own edge does not count): the mean squared
/// derivative of the grey image, after a Gaussian of 0.7 px that takes most
/// of the sensor noise out and leaves the stone's grain, along `along` (any
/// length; zero: the whole gradient). A turning table smears the photo along
/// the image of its turn, across the image of its axis (TurnDirection), and
/// a smeared view has a fraction of its side's median there. 0 for an
/// empty mask.
double RockSharpness(const cv::Mat& bgr, const cv::Mat& mask, cv::Point2d along = {});

/// The image direction in which the turning table moves the rock (unit):
/// across the image of the turntable axis, seen with the rig calibration.
cv::Point2d TurnDirection(const RigCalibration& cal);

}  // namespace aggscan
