#include "pipeline/calib/calibrate.h"

#include <ceres/ceres.h>
#include <ceres/rotation.h>
#include <unistd.h>

#include <Eigen/Dense>
#include <Eigen/Geometry>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <opencv2/aruco/charuco.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "common/clock.h"
#include "common/fsutil.h"
#include "config/config.h"
#include "pipeline/core/image_io.h"
#include "pipeline/markers/aruco_scale.h"
#include "store/layout.h"
#include "store/sample_files.h"

namespace aggscan {

namespace {

using nlohmann::json;
constexpr double kDeg = M_PI / 180.0;

Result<cv::Ptr<cv::aruco::CharucoBoard>> MakeBoard(const CalibrationConfig& b) {
  Result<cv::Ptr<cv::aruco::Dictionary>> dict = ArucoDictionary(b.dictionary);
  if (!dict) {
    return MakeError(ErrorClass::kInvalidConfig, "calibration.dictionary: " + dict.error().message);
  }
  try {
    return cv::aruco::CharucoBoard::create(b.squares_x, b.squares_y,
                                           static_cast<float>(b.square_mm),
                                           static_cast<float>(b.marker_mm), *dict);
  } catch (const cv::Exception& e) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "cannot build the ChArUco board from [calibration]", e.what());
  }
}

std::string Fixed(double v, int digits) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", digits, v);
  return buf;
}

// Reprojection of one corner: table0 point Rz(theta) (p + b), camera pose as
// angle-axis + translation, lens fx = fy, cx, cy fixed, k1, k2.
struct CornerResidual {
  double u, v, px, py, c, s, cx, cy;

  template <typename T>
  bool operator()(const T* cam, const T* board, const T* intr, T* r) const {
    const T x = T(px) + board[0], y = T(py) + board[1];
    const T pt[3] = {T(c) * x - T(s) * y, T(s) * x + T(c) * y, T(0)};
    T pc[3];
    ceres::AngleAxisRotatePoint(cam, pt, pc);
    pc[0] += cam[3], pc[1] += cam[4], pc[2] += cam[5];
    const T xn = pc[0] / pc[2], yn = pc[1] / pc[2];
    const T r2 = xn * xn + yn * yn;
    const T radial = T(1) + r2 * (intr[1] + r2 * intr[2]);
    r[0] = intr[0] * xn * radial + T(cx) - T(u);
    r[1] = intr[0] * yn * radial + T(cy) - T(v);
    return true;
  }
};

// Turntable rotation the angles cover: 360 minus the largest gap between
// neighbouring angles on the circle.
double AngleSpanDeg(std::vector<double> a) {
  for (double& x : a) x = std::fmod(std::fmod(x, 360.0) + 360.0, 360.0);
  std::sort(a.begin(), a.end());
  if (a.size() < 2) return 0;
  double gap = a.front() + 360.0 - a.back();
  for (size_t i = 1; i < a.size(); ++i) gap = std::max(gap, a[i] - a[i - 1]);
  return 360.0 - gap;
}

double NormalizeDeg(double d) {
  d = std::fmod(d, 360.0);
  if (d > 180) d -= 360;
  if (d <= -180) d += 360;
  return d;
}

// Detections on one image: markers, then the interpolated ChArUco corners as
// OpenCV returns them.
void DetectCharuco(const cv::Mat& img, const cv::Ptr<cv::aruco::CharucoBoard>& board,
                   BoardView* view) {
  std::vector<std::vector<cv::Point2f>> marker_corners, rejected;
  std::vector<int> marker_ids;
  cv::Ptr<cv::aruco::DetectorParameters> params = cv::aruco::DetectorParameters::create();
  cv::aruco::detectMarkers(img, board->dictionary, marker_corners, marker_ids, params, rejected);
  view->markers = static_cast<int>(marker_ids.size());
  if (marker_ids.size() < 2) return;
  std::vector<cv::Point2f> corners;
  std::vector<int> ids;
  cv::aruco::interpolateCornersCharuco(marker_corners, marker_ids, img, board, corners, ids);
  for (size_t k = 0; k < ids.size(); ++k) {
    view->ids.push_back(ids[k]);
    view->corners.push_back({corners[k].x, corners[k].y});
  }
}

// OpenCV's aruco module from 4.5.4 (opencv_contrib#3024) until opencv#28380
// returns ChArUco corners 0.5 px right of and below the pixel-centre
// convention that cornerSubPix, calibrateCamera and rig_calibration.h use
// (opencv/opencv#25539): uncorrected, the whole rig model shifts by half a
// pixel. Measured once on a drawn board (corners known exactly), rounded to
// 0.5 px, so an OpenCV with the fix needs no change here.
double CharucoCornerOffsetPx() {
  static const double offset = [] {
    CalibrationConfig b;
    auto board = MakeBoard(b);
    if (!board) return 0.0;
    constexpr int kSquarePx = 40, kMarginPx = 40;
    cv::Mat squares, page(b.squares_y * kSquarePx + 2 * kMarginPx,
                          b.squares_x * kSquarePx + 2 * kMarginPx, CV_8UC1, cv::Scalar(255));
    try {
      (*board)->draw(cv::Size(b.squares_x * kSquarePx, b.squares_y * kSquarePx), squares, 0, 1);
      squares.copyTo(page(cv::Rect(kMarginPx, kMarginPx, squares.cols, squares.rows)));
      cv::GaussianBlur(page, page, cv::Size(0, 0), 1.0);
      BoardView v;
      DetectCharuco(page, *board, &v);
      if (v.ids.size() < 4) return 0.0;
      double sum = 0;
      for (size_t k = 0; k < v.ids.size(); ++k) {
        const int i = v.ids[k] % (b.squares_x - 1), j = v.ids[k] / (b.squares_x - 1);
        // Square edges lie between pixels: at n * kSquarePx - 0.5 in pixel-centre coordinates.
        sum += v.corners[k][0] - ((i + 1) * kSquarePx + kMarginPx - 0.5);
        sum += v.corners[k][1] - ((j + 1) * kSquarePx + kMarginPx - 0.5);
      }
      return std::round(sum / (2.0 * v.ids.size()) * 2) / 2;
    } catch (const cv::Exception&) {
      return 0.0;
    }
  }();
  return offset;
}

}  // namespace

std::array<double, 2> BoardCornerMm(const CalibrationConfig& b, int id) {
  // OpenCV numbers the inner corners row by row from the image's top-left,
  // at ((i + 1) * square, (j + 1) * square) with y down the image.
  const int i = id % (b.squares_x - 1), j = id / (b.squares_x - 1);
  const double X = (i + 1) * b.square_mm, Y = (j + 1) * b.square_mm;
  return {X - b.squares_x * b.square_mm / 2, b.squares_y * b.square_mm / 2 - Y};
}

Status WriteBoardImage(const CalibrationConfig& b, const std::string& path, double px_per_mm,
                       double margin_mm) {
  if (!(px_per_mm > 0) || !(margin_mm >= 0)) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "board image: resolution must be > 0 and margin >= 0");
  }
  auto board = MakeBoard(b);
  if (!board) return board.error();
  const int w = static_cast<int>(std::lround(b.squares_x * b.square_mm * px_per_mm));
  const int h = static_cast<int>(std::lround(b.squares_y * b.square_mm * px_per_mm));
  const int m = static_cast<int>(std::lround(margin_mm * px_per_mm));
  if (w < 10 * b.squares_x || h < 10 * b.squares_y) {
    return MakeError(ErrorClass::kInvalidArgument, "board image: " + Fixed(px_per_mm, 2) +
                                                       " px/mm is too coarse to draw the markers");
  }
  if (static_cast<double>(w + 2 * m) * (h + 2 * m) > 4e8) {
    return MakeError(ErrorClass::kInvalidArgument, "board image: too many pixels; lower the dpi");
  }
  cv::Mat squares, page(h + 2 * m, w + 2 * m, CV_8UC1, cv::Scalar(255));
  try {
    (*board)->draw(cv::Size(w, h), squares, 0, 1);
    squares.copyTo(page(cv::Rect(m, m, w, h)));
    if (m >= 24) {
      // What the sheet is, in the bottom margin: an operator checks the print with it.
      const std::string label = "aggscan ChArUco " + std::to_string(b.squares_x) + "x" +
                                std::to_string(b.squares_y) + ", squares " + Fixed(b.square_mm, 1) +
                                " mm, markers " + Fixed(b.marker_mm, 1) + " mm, " + b.dictionary +
                                "; print at true size, measure, lay flat on the turntable";
      const double scale = std::min(0.4 * m / 22.0, 0.9 * w / (label.size() * 20.0));
      cv::putText(page, label, cv::Point(m, h + m + static_cast<int>(m * 0.65)),
                  cv::FONT_HERSHEY_SIMPLEX, scale, cv::Scalar(0),
                  std::max(1, static_cast<int>(scale * 1.5)), cv::LINE_AA);
    }
  } catch (const cv::Exception& e) {
    return MakeError(ErrorClass::kInternal, "cannot draw the ChArUco board", e.what());
  }
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return std::tolower(c); });
  if (ext != ".png" && ext != ".pgm") {
    return MakeError(ErrorClass::kInvalidArgument,
                     "board image: write a .png or a .pgm file, not " + path);
  }
  std::vector<unsigned char> bytes;
  try {
    if (!cv::imencode(ext, page, bytes)) {
      return MakeError(ErrorClass::kInternal, "cannot encode the board image as " + ext);
    }
  } catch (const cv::Exception& e) {
    return MakeError(ErrorClass::kInternal, "cannot encode the board image as " + ext, e.what());
  }
  return WriteFileAtomic(path, std::span<const unsigned char>(bytes.data(), bytes.size()));
}

Result<BoardView> DetectBoardInImage(const std::string& image_path, const CalibrationConfig& b,
                                     int* width, int* height) {
  auto board = MakeBoard(b);
  if (!board) return board.error();
  auto loaded = LoadImage(image_path, ImageMode::kGray);
  if (!loaded) {
    return MakeError(loaded.error().cls,
                     "cannot read image " + image_path + ": " + loaded.error().message,
                     loaded.error().detail);
  }
  cv::Mat img = std::move(*loaded);
  if (width) *width = img.cols;
  if (height) *height = img.rows;
  BoardView view;
  view.name = image_path;
  try {
    DetectCharuco(img, *board, &view);
    const double offset = CharucoCornerOffsetPx();
    for (auto& c : view.corners) c[0] -= offset, c[1] -= offset;
  } catch (const cv::Exception& e) {
    return MakeError(ErrorClass::kInternal, "board detection failed on " + image_path, e.what());
  }
  return view;
}

Result<CalibrationResult> SolveRigCalibration(const std::vector<BoardView>& all_views,
                                              const CalibrationConfig& b, int width, int height,
                                              const CalibrateOptions& opt) {
  const auto t0 = std::chrono::steady_clock::now();
  CalibrationResult res;
  res.views_total = static_cast<int>(all_views.size());
  const int max_id = (b.squares_x - 1) * (b.squares_y - 1);

  std::vector<const BoardView*> views;
  for (const BoardView& v : all_views) {
    int valid = 0;
    for (int id : v.ids) valid += id >= 0 && id < max_id;
    if (valid >= opt.min_corners_per_view && v.ids.size() == v.corners.size()) {
      views.push_back(&v);
    } else {
      res.skipped.push_back(v.name + ": " + std::to_string(v.markers) + " markers, " +
                            std::to_string(v.ids.size()) + " corners (needs " +
                            std::to_string(opt.min_corners_per_view) + ")");
    }
  }
  int total_corners = 0;
  for (const BoardView* v : views) total_corners += static_cast<int>(v->ids.size());
  if (static_cast<int>(views.size()) < opt.min_views) {
    return MakeError(
        ErrorClass::kInvalidArgument,
        "the board was found in " + std::to_string(views.size()) + " of " +
            std::to_string(all_views.size()) + " views (" + std::to_string(total_corners) +
            " corners); the calibration needs at least " + std::to_string(opt.min_views) +
            " views with " + std::to_string(opt.min_corners_per_view) +
            " corners each. Check that the whole board lies flat in view on the disc, that it is "
            "evenly lit without glare, that the image is in focus, and that [calibration] matches "
            "the printed board (" +
            b.dictionary + ", " + std::to_string(b.squares_x) + "x" + std::to_string(b.squares_y) +
            " squares); then capture the side again");
  }
  std::vector<double> angles;
  angles.reserve(views.size());
  for (const BoardView* v : views) angles.push_back(v->angle_deg);
  const double span = AngleSpanDeg(angles);
  if (span < opt.min_rotation_deg) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "the usable views cover only " + Fixed(span, 1) +
                         " deg of turntable rotation; the axis needs at least " +
                         Fixed(opt.min_rotation_deg, 0) +
                         " deg: capture a side with the turntable turning through a full turn");
  }

  // ---- 1. OpenCV: lens and a free pose per view (the initial guess) ----
  std::vector<std::vector<cv::Point3f>> obj(views.size());
  std::vector<std::vector<cv::Point2f>> img(views.size());
  for (size_t i = 0; i < views.size(); ++i) {
    for (size_t k = 0; k < views[i]->ids.size(); ++k) {
      const int id = views[i]->ids[k];
      if (id < 0 || id >= max_id) continue;
      const auto p = BoardCornerMm(b, id);
      obj[i].emplace_back(static_cast<float>(p[0]), static_cast<float>(p[1]), 0.0f);
      img[i].emplace_back(static_cast<float>(views[i]->corners[k][0]),
                          static_cast<float>(views[i]->corners[k][1]));
    }
  }
  const double cx = (width - 1) / 2.0, cy = (height - 1) / 2.0;
  cv::Mat K = (cv::Mat_<double>(3, 3) << 1, 0, cx, 0, 1, cy, 0, 0, 1);
  cv::Mat dist = cv::Mat::zeros(5, 1, CV_64F);
  std::vector<cv::Mat> rvecs, tvecs;
  // One plane seen in every view: see calibrate.h for why these are fixed.
  const int flags = cv::CALIB_FIX_ASPECT_RATIO | cv::CALIB_ZERO_TANGENT_DIST | cv::CALIB_FIX_K3 |
                    cv::CALIB_FIX_PRINCIPAL_POINT;
  try {
    res.init_rms_px =
        cv::calibrateCamera(obj, img, cv::Size(width, height), K, dist, rvecs, tvecs, flags);
  } catch (const cv::Exception& e) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "OpenCV could not calibrate from the detected corners; capture the side again "
                     "with the board flat and fully in view",
                     e.what());
  }
  if (!(K.at<double>(0, 0) > 0) || !std::isfinite(res.init_rms_px)) {
    return MakeError(ErrorClass::kInvalidArgument, "OpenCV calibration gave no usable lens (rms " +
                                                       Fixed(res.init_rms_px, 3) + " px)");
  }

  // ---- 2. the turntable axis and the camera, from the per-view poses ----
  // The axis pierces the board at one board point a (z = 0) that every view
  // sees at the same camera point m: R_i a + t_i = m, linear in (a, m).
  std::vector<Eigen::Matrix3d> Rv(views.size());
  std::vector<Eigen::Vector3d> tv(views.size());
  Eigen::MatrixXd A(3 * views.size(), 5);
  Eigen::VectorXd rhs(3 * views.size());
  for (size_t i = 0; i < views.size(); ++i) {
    cv::Mat R;
    cv::Rodrigues(rvecs[i], R);
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) Rv[i](r, c) = R.at<double>(r, c);
      tv[i](r) = tvecs[i].at<double>(r);
    }
    A.block<3, 2>(3 * i, 0) = Rv[i].leftCols<2>();
    A.block<3, 3>(3 * i, 2) = -Eigen::Matrix3d::Identity();
    rhs.segment<3>(3 * i) = -tv[i];
  }
  const Eigen::VectorXd sol = A.colPivHouseholderQr().solve(rhs);
  // Board pose on the table with the gauge psi = 0: p_table = p_board + b.
  double board_b[2] = {-sol(0), -sol(1)};
  // cam_from_table0 aligns the table0 positions of every corner with the
  // camera positions the per-view poses give (Umeyama, no scale).
  Eigen::Matrix3Xd src(3, total_corners), dst(3, total_corners);
  int n = 0;
  for (size_t i = 0; i < views.size(); ++i) {
    const double c = std::cos(views[i]->angle_deg * kDeg), s = std::sin(views[i]->angle_deg * kDeg);
    for (const cv::Point3f& p : obj[i]) {
      const double x = p.x + board_b[0], y = p.y + board_b[1];
      src.col(n) = Eigen::Vector3d(c * x - s * y, s * x + c * y, 0);
      dst.col(n) = Rv[i] * Eigen::Vector3d(p.x, p.y, 0) + tv[i];
      ++n;
    }
  }
  src.conservativeResize(3, n);
  dst.conservativeResize(3, n);
  const Eigen::Matrix4d T = Eigen::umeyama(src, dst, false);
  double cam[6];
  {
    Eigen::Matrix<double, 3, 3, Eigen::RowMajor> R = T.topLeftCorner<3, 3>();
    ceres::RotationMatrixToAngleAxis(ceres::RowMajorAdapter3x3<const double>(R.data()), cam);
    cam[3] = T(0, 3), cam[4] = T(1, 3), cam[5] = T(2, 3);
  }
  double intr[3] = {K.at<double>(0, 0), dist.at<double>(0), dist.at<double>(1)};

  // ---- 3. joint refinement over every corner of every view ----
  ceres::Problem problem;
  std::vector<CornerResidual> obs;
  for (size_t i = 0; i < views.size(); ++i) {
    const double c = std::cos(views[i]->angle_deg * kDeg), s = std::sin(views[i]->angle_deg * kDeg);
    for (size_t k = 0; k < obj[i].size(); ++k) {
      obs.push_back({img[i][k].x, img[i][k].y, obj[i][k].x, obj[i][k].y, c, s, cx, cy});
    }
  }
  // Corners are sub-pixel accurate; a mis-interpolated one should not pull
  // the rig: Huber beyond 1 px.
  for (const CornerResidual& o : obs) {
    problem.AddResidualBlock(
        new ceres::AutoDiffCostFunction<CornerResidual, 2, 6, 2, 3>(new CornerResidual(o)),
        new ceres::HuberLoss(1.0), cam, board_b, intr);
  }
  ceres::Solver::Options so;
  so.linear_solver_type = ceres::DENSE_QR;
  so.max_num_iterations = 200;
  so.function_tolerance = 1e-14;
  so.gradient_tolerance = 1e-14;
  so.parameter_tolerance = 1e-12;
  so.num_threads = 1;
  // Standard deviations of fx, k1, k2 from the fit: Ceres' covariance of the
  // lens block scaled by the corner noise the residuals show.
  auto lens_sigmas = [&](double out[3]) {
    out[0] = out[1] = out[2] = -1;
    double sum = 0;
    for (const CornerResidual& o : obs) {
      double r[2];
      o(cam, board_b, intr, r);
      sum += r[0] * r[0] + r[1] * r[1];
    }
    const double dof = 2.0 * obs.size() - 11;
    const double var = dof > 0 ? sum / dof : 0;
    ceres::Covariance::Options co;
    co.algorithm_type = ceres::DENSE_SVD;
    co.null_space_rank = -1;
    ceres::Covariance cov(co);
    const std::vector<std::pair<const double*, const double*>> blocks = {{intr, intr}};
    double C[9];
    if (!cov.Compute(blocks, &problem) || !cov.GetCovarianceBlock(intr, intr, C)) return;
    for (size_t i = 0; i < 3; ++i) out[i] = std::sqrt(std::max(0.0, C[i * 4]) * var);
  };
  ceres::Solver::Summary summary;
  if (opt.k2 == CalibrateOptions::K2::kZero) {
    intr[2] = 0;
    problem.SetManifold(intr, new ceres::SubsetManifold(3, {2}));
  }
  ceres::Solve(so, &problem, &summary);
  double sigma[3];
  lens_sigmas(sigma);
  res.k2_estimated = opt.k2 != CalibrateOptions::K2::kZero;
  if (opt.k2 == CalibrateOptions::K2::kAuto && !(sigma[2] >= 0 && sigma[2] <= opt.max_k2_sigma)) {
    // The corners do not reach far enough out in the image to separate k2
    // from k1: a free k2 would only fit noise and extrapolate badly beyond
    // the board (see calibrate.h). Solve again with k2 = 0.
    res.k2_free_value = intr[2];
    res.k2_free_sigma = sigma[2];
    intr[2] = 0;
    problem.SetManifold(intr, new ceres::SubsetManifold(3, {2}));
    ceres::Solve(so, &problem, &summary);
    lens_sigmas(sigma);
    res.k2_estimated = false;
  }
  if (summary.termination_type == ceres::FAILURE || !(intr[0] > 0)) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "the rig refinement did not converge; capture the side again",
                     summary.BriefReport());
  }
  res.sigma_fx_px = sigma[0];
  res.sigma_k1 = sigma[1];
  res.sigma_k2 = res.k2_estimated ? sigma[2] : 0;

  // ---- 4. residuals ----
  double sum2 = 0;
  std::vector<double> view_sum2(views.size(), 0.0);
  size_t k = 0;
  for (size_t i = 0; i < views.size(); ++i) {
    for (size_t j = 0; j < obj[i].size(); ++j, ++k) {
      double r[2];
      obs[k](cam, board_b, intr, r);
      const double e2 = r[0] * r[0] + r[1] * r[1];
      sum2 += e2;
      view_sum2[i] += e2;
      res.outlier_corners += e2 > 4.0;
    }
    res.max_view_rms_px = std::max(res.max_view_rms_px, std::sqrt(view_sum2[i] / obj[i].size()));
  }
  const double rms = std::sqrt(sum2 / static_cast<double>(obs.size()));

  // ---- 5. gauge: the camera at table0 x = 0, y < 0 (see calibrate.h) ----
  double Rc[9];
  ceres::AngleAxisToRotationMatrix(cam, ceres::RowMajorAdapter3x3(Rc));
  const double C[3] = {-(Rc[0] * cam[3] + Rc[3] * cam[4] + Rc[6] * cam[5]),
                       -(Rc[1] * cam[3] + Rc[4] * cam[4] + Rc[7] * cam[5])};
  const double beta = std::atan2(C[1], C[0]) + M_PI / 2;
  const double cb = std::cos(beta), sb = std::sin(beta);
  RigCalibration& cal = res.cal;
  for (int r = 0; r < 3; ++r) {
    // R' = R Rz(beta)
    cal.R_cam_table0[r * 3 + 0] = Rc[r * 3 + 0] * cb + Rc[r * 3 + 1] * sb;
    cal.R_cam_table0[r * 3 + 1] = -Rc[r * 3 + 0] * sb + Rc[r * 3 + 1] * cb;
    cal.R_cam_table0[r * 3 + 2] = Rc[r * 3 + 2];
  }
  cal.t_cam_table0 = {cam[3], cam[4], cam[5]};
  res.board_x_mm = cb * board_b[0] + sb * board_b[1];
  res.board_y_mm = -sb * board_b[0] + cb * board_b[1];
  res.board_yaw_deg = NormalizeDeg(-beta / kDeg);

  cal.camera.width = width;
  cal.camera.height = height;
  cal.camera.fx = cal.camera.fy = intr[0];
  cal.camera.cx = cx;
  cal.camera.cy = cy;
  cal.camera.k1 = intr[1];
  cal.camera.k2 = intr[2];
  cal.reprojection_rms_px = rms;
  cal.views_used = static_cast<int>(views.size());
  cal.corners_used = static_cast<int>(obs.size());
  cal.method = "charuco";
  cal.created_utc = NowUtcString();
  cal.board = {
      {"type", "charuco"},
      {"dictionary", b.dictionary},
      {"squares_x", b.squares_x},
      {"squares_y", b.squares_y},
      {"square_mm", b.square_mm},
      {"marker_mm", b.marker_mm},
      {"pose_on_table",
       {{"x_mm", res.board_x_mm}, {"y_mm", res.board_y_mm}, {"yaw_deg", res.board_yaw_deg}}},
      {"fixed",
       std::string("cx, cy at the image centre, fy = fx, p1 = p2 = k3 = 0: a board lying on "
                   "the turntable shows one plane") +
           (res.k2_estimated ? ""
                             : "; k2 = 0: the corners do not reach far enough out in "
                               "the image to measure it")},
      {"sigma", {{"fx_px", res.sigma_fx_px}, {"k1", res.sigma_k1}, {"k2", res.sigma_k2}}},
      {"max_view_rms_px", res.max_view_rms_px},
      {"rotation_span_deg", span}};
  res.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

Result<CalibrationResult> CalibrateSampleSide(const std::string& sample_dir, int side,
                                              const CalibrationConfig& b,
                                              const CalibrateOptions& opt) {
  const auto t0 = std::chrono::steady_clock::now();
  const std::string side_name = layout::SideDirName(side);
  const std::string side_dir = sample_dir + "/" + side_name;
  const std::string manifest_path = side_dir + "/" + layout::kManifest;
  // Image and sidecar names are checked there to be files in the side directory.
  Result<SideManifest> manifest = ReadSideManifest(side_dir);
  if (!manifest) {
    if (manifest.error().cls == ErrorClass::kNotFound) {
      return MakeError(ErrorClass::kNotFound,
                       side_name + " of " + sample_dir +
                           " has no manifest.json: it was not captured or the "
                           "capture did not finish; capture the board again");
    }
    if (manifest.error().cls == ErrorClass::kCorrupt) {
      return MakeError(ErrorClass::kCorrupt, manifest.error().message + "; capture the board again",
                       manifest.error().detail);
    }
    return manifest.error();
  }
  std::vector<BoardView> views;
  std::string camera_id;
  int width = 0, height = 0;
  for (const SideManifest::Entry& v : manifest->views) {
    if (!v.sidecar) {
      return MakeError(ErrorClass::kCorrupt, manifest_path + " lists view " +
                                                 std::to_string(v.view) +
                                                 " without its sidecar; capture the board again");
    }
    const std::string& image = v.image;
    const std::string& sidecar = *v.sidecar;
    Result<ViewSidecar> sc = ReadViewSidecarFile(side_dir + "/" + sidecar);
    if (!sc || !sc->measured_angle_deg || !std::isfinite(*sc->measured_angle_deg)) {
      return MakeError(
          ErrorClass::kCorrupt,
          side_name + "/" + sidecar +
              " is missing, damaged or has no measured_angle_deg: the turntable angle of " + image +
              " is unknown, so the view cannot be placed; capture the board again",
          sc ? std::string() : sc.error().ToString());
    }
    if (sc->view != v.view) {
      return MakeError(ErrorClass::kCorrupt,
                       side_name + "/" + sidecar + " is of view " + std::to_string(sc->view) +
                           ", the manifest lists it for view " + std::to_string(v.view) +
                           "; capture the board again");
    }
    if (camera_id.empty()) camera_id = sc->camera_id.value_or("");
    int w = 0, h = 0;
    Result<BoardView> det = DetectBoardInImage(side_dir + "/" + image, b, &w, &h);
    if (!det) return det.error();
    if (width == 0) width = w, height = h;
    if (w != width || h != height) {
      return MakeError(ErrorClass::kCorrupt,
                       side_name + "/" + image + " is " + std::to_string(w) + "x" +
                           std::to_string(h) + ", the other views " + std::to_string(width) + "x" +
                           std::to_string(height) + "; one capture must keep one resolution");
    }
    det->name = side_name + "/" + image;
    det->angle_deg = *sc->measured_angle_deg;
    views.push_back(std::move(det).value());
  }
  if (views.empty()) {
    return MakeError(ErrorClass::kInvalidArgument,
                     side_name + " of " + sample_dir + " has no views");
  }
  Result<CalibrationResult> res = SolveRigCalibration(views, b, width, height, opt);
  if (!res) return res;
  res->cal.camera_id = camera_id;
  res->cal.source = sample_dir + " " + side_name;
  res->seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

Result<std::string> InstallRigCalibration(const std::string& path, const RigCalibration& cal) {
  std::string prev;
  if (PathExists(path)) {
    prev = FreeTimedName("", path + ".prev-");
    if (::link(path.c_str(), prev.c_str()) != 0) {
      // A filesystem without hard links: a durable copy instead.
      Result<std::string> old = ReadFile(path);
      if (!old) return old.error();
      if (Status s = WriteFileAtomic(prev, *old, true); !s) return s.error();
    } else {
      const std::string dir = std::filesystem::path(path).parent_path().string();
      if (Status s = FsyncDir(dir.empty() ? "." : dir); !s) return s.error();
    }
  }
  if (Status s = SaveCalibration(path, cal); !s) {
    return MakeError(s.error().cls,
                     "cannot write " + path + ": " + s.error().ToString() +
                         (prev.empty() ? "" : " (the previous one is kept as " + prev + ")"));
  }
  return prev;
}

Status RunCalibrationCapture(const std::string& capture_dir, int side,
                             const std::string& state_dir) {
  // The board the capture was shot with: its own config copy.
  std::vector<ConfigProblem> problems;
  Result<Config> config = LoadConfigFile(capture_dir + "/" + layout::kConfigCopy, &problems);
  if (!config) {
    std::string why = config.error().ToString();
    for (const auto& p : problems) why += "; " + p.ToString();
    return MakeError(ErrorClass::kCorrupt, "the calibration capture's " +
                                               std::string(layout::kConfigCopy) + " is unusable (" +
                                               why + "): capture the board again");
  }
  Result<CalibrationResult> r = CalibrateSampleSide(capture_dir, side, config->calibration);
  if (!r) return r.error();
  const std::string target = CalibrationPath(state_dir);
  Result<std::string> prev = InstallRigCalibration(target, r->cal);
  if (!prev) return prev.error();
  const RigCalibration& cal = r->cal;
  const auto C = cal.CameraCentreTable0();
  nlohmann::json summary = {
      {"calibration", target},
      {"previous", prev->empty() ? nlohmann::json(nullptr) : nlohmann::json(*prev)},
      {"reprojection_rms_px", cal.reprojection_rms_px},
      {"max_view_rms_px", r->max_view_rms_px},
      {"views_used", cal.views_used},
      {"views_total", r->views_total},
      {"corners_used", cal.corners_used},
      {"skipped", r->skipped},
      {"outlier_corners", r->outlier_corners},
      {"fx_px", cal.camera.fx},
      {"k1", cal.camera.k1},
      {"camera_distance_mm", std::sqrt(C[0] * C[0] + C[1] * C[1] + C[2] * C[2])},
      {"seconds", r->seconds},
      {"created_utc", cal.created_utc}};
  const std::string results = capture_dir + "/" + layout::kResultsDir;
  if (Status s = MakeDirsDurable(results); !s) return s;
  return WriteFileAtomic(results + "/calibration_result.json", summary.dump(2) + "\n", false);
}

}  // namespace aggscan
