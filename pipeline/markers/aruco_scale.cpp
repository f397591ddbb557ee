#include "pipeline/markers/aruco_scale.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <filesystem>
#include <map>
#include <opencv2/aruco.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <span>

#include "common/fsutil.h"

namespace aggscan {

namespace {

using Eigen::Vector2d;
using Eigen::Vector3d;

// The marker's configured entry, or null.
const ArucoMarker* FindMarker(const RigConfig& rig, int id) {
  for (const ArucoMarker& m : rig.aruco_markers) {
    if (m.id == id) return &m;
  }
  return nullptr;
}

// True when the quadrilateral, grown by `clearance` pixels, covers a rock pixel.
bool TouchesRock(const std::vector<cv::Point2f>& quad, const cv::Mat& rock, int clearance) {
  if (rock.empty()) return false;
  cv::Rect box = cv::boundingRect(quad);
  box.x -= clearance + 1, box.y -= clearance + 1;
  box.width += 2 * clearance + 2, box.height += 2 * clearance + 2;
  box &= cv::Rect(0, 0, rock.cols, rock.rows);
  for (int y = box.y; y < box.y + box.height; ++y) {
    const uint8_t* row = rock.ptr<uint8_t>(y);
    for (int x = box.x; x < box.x + box.width; ++x) {
      if (row[x] == 0) continue;
      if (cv::pointPolygonTest(quad, cv::Point2f(static_cast<float>(x), static_cast<float>(y)),
                               true) >= -clearance) {
        return true;
      }
    }
  }
  return false;
}

// Least-squares scale s minimising sum (s * rec - conf)^2, and the residuals.
struct DictName {
  const char* name;
  cv::aruco::PREDEFINED_DICTIONARY_NAME id;
};
// The names config.cpp accepts (its BoardDictionaries()).
constexpr DictName kDictionaries[] = {
    {"DICT_4X4_50", cv::aruco::DICT_4X4_50},
    {"DICT_4X4_100", cv::aruco::DICT_4X4_100},
    {"DICT_4X4_250", cv::aruco::DICT_4X4_250},
    {"DICT_4X4_1000", cv::aruco::DICT_4X4_1000},
    {"DICT_5X5_50", cv::aruco::DICT_5X5_50},
    {"DICT_5X5_100", cv::aruco::DICT_5X5_100},
    {"DICT_5X5_250", cv::aruco::DICT_5X5_250},
    {"DICT_5X5_1000", cv::aruco::DICT_5X5_1000},
    {"DICT_6X6_50", cv::aruco::DICT_6X6_50},
    {"DICT_6X6_100", cv::aruco::DICT_6X6_100},
    {"DICT_6X6_250", cv::aruco::DICT_6X6_250},
    {"DICT_6X6_1000", cv::aruco::DICT_6X6_1000},
    {"DICT_7X7_50", cv::aruco::DICT_7X7_50},
    {"DICT_7X7_100", cv::aruco::DICT_7X7_100},
    {"DICT_7X7_250", cv::aruco::DICT_7X7_250},
    {"DICT_7X7_1000", cv::aruco::DICT_7X7_1000},
    {"DICT_ARUCO_ORIGINAL", cv::aruco::DICT_ARUCO_ORIGINAL},
};

// 8-bit sRGB value -> linear intensity.
const std::array<double, 256>& SrgbToLinear() {
  static const std::array<double, 256> k = [] {
    std::array<double, 256> t{};
    for (int i = 0; i < 256; ++i) {
      const double v = i / 255.0;
      t[static_cast<size_t>(i)] = v <= 0.04045 ? v / 12.92 : std::pow((v + 0.055) / 1.055, 2.4);
    }
    return t;
  }();
  return k;
}

// Bilinear sample of a linearised grey image; nullopt outside it.
std::optional<double> Sample(const cv::Mat& lin, double x, double y) {
  if (x < 0 || y < 0 || x > lin.cols - 1.001 || y > lin.rows - 1.001) return std::nullopt;
  const int i = static_cast<int>(x), j = static_cast<int>(y);
  const double fx = x - i, fy = y - j;
  const float* r0 = lin.ptr<float>(j);
  const float* r1 = lin.ptr<float>(j + 1);
  return (r0[i] * (1 - fx) + r0[i + 1] * fx) * (1 - fy) + (r1[i] * (1 - fx) + r1[i + 1] * fx) * fy;
}

// Line through points: (centroid, unit direction) by principal axis; nullopt
// for fewer than two points.
std::optional<std::pair<Vector2d, Vector2d>> FitLine(const std::vector<Vector2d>& pts) {
  if (pts.size() < 2) return std::nullopt;
  Vector2d c = Vector2d::Zero();
  for (const Vector2d& p : pts) c += p;
  c /= static_cast<double>(pts.size());
  Eigen::Matrix2d cov = Eigen::Matrix2d::Zero();
  for (const Vector2d& p : pts) cov += (p - c) * (p - c).transpose();
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> es(cov);
  return std::make_pair(c, Vector2d(es.eigenvectors().col(1)));
}

std::optional<Vector2d> Meet(const std::pair<Vector2d, Vector2d>& a,
                             const std::pair<Vector2d, Vector2d>& b) {
  const Vector2d& da = a.second;
  const Vector2d& db = b.second;
  const double den = da.x() * db.y() - da.y() * db.x();
  if (std::abs(den) < 1e-6) return std::nullopt;
  const Vector2d w = b.first - a.first;
  return a.first + (w.x() * db.y() - w.y() * db.x()) / den * da;
}

// The corners of a detected marker (distorted pixels, OpenCV order) from its
// four outer edges (see the header); false when a side has too few edge
// points, and the corners are left as they were.
bool RefineByEdges(const cv::Mat& lin, const CameraModel* cam, int cells,
                   const ArucoDetectOptions& opts, std::array<Vector2d, 4>* corners) {
  const std::array<Vector2d, 4>& q = *corners;
  Vector2d centre = Vector2d::Zero();
  for (const Vector2d& c : q) centre += c / 4.0;
  std::array<std::pair<Vector2d, Vector2d>, 4> lines;
  for (int k = 0; k < 4; ++k) {
    const Vector2d a = q[k], b = q[(k + 1) % 4];
    const double len = (b - a).norm();
    if (len < 8) return false;
    const Vector2d dir = (b - a) / len;
    Vector2d normal(-dir.y(), dir.x());  // outward: away from the centre
    if (normal.dot((a + b) / 2 - centre) < 0) normal = -normal;
    // Profile half length: within the black border cell inside and the paper
    // margin outside (the marker's apparent cell, less a safety margin).
    const double cell = len / cells;
    const double reach = std::clamp(0.45 * cell, 1.5, 6.0);
    const int steps = std::max(6, static_cast<int>(std::ceil(reach * 4)));
    std::vector<Vector2d> pts;
    const int n = std::clamp(static_cast<int>(len), 8, 80);
    for (int s = 0; s < n; ++s) {
      const double t = opts.edge_end_margin + (1 - 2 * opts.edge_end_margin) * (s + 0.5) / n;
      const Vector2d base = a + t * (b - a);
      std::vector<double> prof(static_cast<size_t>(2 * steps + 1));
      bool inside = true;
      for (int i = -steps; i <= steps && inside; ++i) {
        const Vector2d p = base + normal * (reach * i / steps);
        const std::optional<double> v = Sample(lin, p.x(), p.y());
        if (!v)
          inside = false;
        else
          prof[i + steps] = *v;
      }
      if (!inside) continue;
      // Dark and light levels from the profile's ends; the edge where it
      // crosses halfway, the crossing nearest the detected side.
      const int e = std::max(1, steps / 4);
      double dark = 0, light = 0;
      for (int i = 0; i < e; ++i)
        dark += prof[static_cast<size_t>(i)],
            light += prof[prof.size() - 1 - static_cast<size_t>(i)];
      dark /= e, light /= e;
      if (light - dark < 0.05 || light < 2 * dark) continue;  // no clear black-to-paper step
      const double mid = 0.5 * (dark + light);
      double best = 1e9;
      for (size_t i = 0; i + 1 < prof.size(); ++i) {
        if ((prof[i] - mid) * (prof[i + 1] - mid) > 0 || prof[i] == prof[i + 1]) continue;
        const double x =
            (static_cast<double>(i) + (mid - prof[i]) / (prof[i + 1] - prof[i]) - steps) * reach /
            steps;
        if (std::abs(x) < std::abs(best)) best = x;
      }
      if (std::abs(best) > reach) continue;
      const Vector2d edge = base + normal * best;
      pts.push_back(cam ? geom::UndistortPixel(*cam, edge) : edge);
    }
    if (static_cast<int>(pts.size()) < opts.min_edge_points) return false;
    std::optional<std::pair<Vector2d, Vector2d>> l = FitLine(pts);
    if (!l) return false;
    lines[static_cast<size_t>(k)] = *l;
  }
  // Side k runs from corner k to corner k+1: corner k is where sides k-1 and k meet.
  std::array<Vector2d, 4> out;
  for (int k = 0; k < 4; ++k) {
    std::optional<Vector2d> c =
        Meet(lines[static_cast<size_t>((k + 3) % 4)], lines[static_cast<size_t>(k)]);
    if (!c) return false;
    Vector2d d = *c;
    if (cam) {
      double u = 0, v = 0;
      if (!cam->Project({(c->x() - cam->cx) / cam->fx, (c->y() - cam->cy) / cam->fy, 1.0}, &u, &v))
        return false;
      d = Vector2d(u, v);
    }
    if ((d - q[static_cast<size_t>(k)]).norm() > 3.0)
      return false;  // not the same corner: keep OpenCV's
    out[static_cast<size_t>(k)] = d;
  }
  *corners = out;
  return true;
}

}  // namespace

Result<cv::Ptr<cv::aruco::Dictionary>> ArucoDictionary(const std::string& name) {
  for (const DictName& d : kDictionaries) {
    if (name == d.name) return cv::aruco::getPredefinedDictionary(d.id);
  }
  return MakeError(ErrorClass::kInvalidConfig,
                   "\"" + name +
                       "\" is not a known ArUco dictionary; use an OpenCV name such as "
                       "DICT_4X4_50 or DICT_5X5_100");
}

Result<cv::Mat> DrawArucoSheet(const RigConfig& rig, int px_per_marker) {
  if (rig.aruco_markers.empty()) {
    return MakeError(
        ErrorClass::kInvalidConfig,
        "no ArUco markers to draw: list them in [[rig.aruco_markers]] (id, x_mm, y_mm)");
  }
  Result<cv::Ptr<cv::aruco::Dictionary>> dict = ArucoDictionary(rig.aruco_dictionary);
  if (!dict) return dict.error();
  const int cells = (*dict)->markerSize + 2;  // data bits plus the one-bit black border
  const int side = px_per_marker / cells * cells;
  if (side < cells * 4) {
    return MakeError(ErrorClass::kInvalidArgument, "ArUco sheet: " + std::to_string(px_per_marker) +
                                                       " px a marker is too coarse; use at least " +
                                                       std::to_string(cells * 4));
  }
  const int n = static_cast<int>(rig.aruco_markers.size());
  cv::Mat sheet(side, side * n, CV_8UC1, cv::Scalar(255));
  for (int k = 0; k < n; ++k) {
    const int id = rig.aruco_markers[static_cast<size_t>(k)].id;
    if (id < 0 || id >= (*dict)->bytesList.rows) {
      return MakeError(ErrorClass::kInvalidConfig,
                       "rig.aruco_markers[" + std::to_string(k) + "].id " + std::to_string(id) +
                           " is not in " + rig.aruco_dictionary + " (ids 0.." +
                           std::to_string((*dict)->bytesList.rows - 1) + ")");
    }
    cv::Mat img;
    try {
      (*dict)->drawMarker(id, side, img, 1);
    } catch (const cv::Exception& e) {
      return MakeError(ErrorClass::kInternal, "cannot draw ArUco marker " + std::to_string(id),
                       e.what());
    }
    img.copyTo(sheet(cv::Rect(k * side, 0, side, side)));
  }
  return sheet;
}

Status WriteArucoSheet(const RigConfig& rig, const std::string& path, double px_per_mm) {
  if (!(px_per_mm > 0) || !(rig.aruco_size_mm > 0)) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "ArUco sheet: the resolution and rig.aruco_size_mm must be > 0");
  }
  const double px = rig.aruco_size_mm * px_per_mm;
  if (px * rig.aruco_markers.size() * px > 4e8) {
    return MakeError(ErrorClass::kInvalidArgument, "ArUco sheet: too many pixels; lower the dpi");
  }
  Result<cv::Mat> sheet = DrawArucoSheet(rig, static_cast<int>(std::lround(px)));
  if (!sheet) return sheet.error();
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(),
                 [](unsigned char c) { return std::tolower(c); });
  if (ext != ".png" && ext != ".pgm") {
    return MakeError(ErrorClass::kInvalidArgument,
                     "ArUco sheet: write a .png or a .pgm file, not " + path);
  }
  std::vector<unsigned char> bytes;
  try {
    if (!cv::imencode(ext, *sheet, bytes)) {
      return MakeError(ErrorClass::kInternal, "cannot encode the ArUco sheet as " + ext);
    }
  } catch (const cv::Exception& e) {
    return MakeError(ErrorClass::kInternal, "cannot encode the ArUco sheet as " + ext, e.what());
  }
  return WriteFileAtomic(path, std::span<const unsigned char>(bytes.data(), bytes.size()));
}

Vector3d ArucoCornerMm(const ArucoMarker& m, double size_mm, int k) {
  // Printed image: top-left, top-right, bottom-right, bottom-left; marker
  // frame x along the columns, y towards the top row.
  static constexpr double kX[4] = {-1, 1, 1, -1}, kY[4] = {1, 1, -1, -1};
  const double h = size_mm / 2, a = m.yaw_deg * M_PI / 180.0;
  const double x = kX[k] * h, y = kY[k] * h;
  return {m.x_mm + x * std::cos(a) - y * std::sin(a), m.y_mm + x * std::sin(a) + y * std::cos(a),
          0.0};
}

std::string ArucoDetectOptions::Check() const {
  if (rock_clearance_px < 0) return "rock_clearance_px must be >= 0";
  if (subpixel_window_px < 1) return "subpixel_window_px must be >= 1";
  if (!(edge_end_margin >= 0 && edge_end_margin < 0.5))
    return "edge_end_margin must be in [0, 0.5)";
  if (min_edge_points < 2) return "min_edge_points must be >= 2";
  return {};
}

Result<ArucoViewDetections> DetectArucoMarkers(const cv::Mat& image, const cv::Mat& rock_mask,
                                               const RigConfig& rig, const CameraModel* camera,
                                               const ArucoDetectOptions& opts) {
  if (std::string why = opts.Check(); !why.empty()) {
    return MakeError(ErrorClass::kInvalidArgument, "ArUco detection options: " + why);
  }
  if (image.empty() || image.depth() != CV_8U || (image.channels() != 3 && image.channels() != 1)) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "ArUco detection needs an 8-bit BGR or grey photo");
  }
  if (!rock_mask.empty() && (rock_mask.type() != CV_8UC1 || rock_mask.size() != image.size())) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "ArUco detection: the rock mask must be 8-bit, one channel, the photo's size");
  }
  Result<cv::Ptr<cv::aruco::Dictionary>> dict = ArucoDictionary(rig.aruco_dictionary);
  if (!dict) return dict.error();
  cv::Mat grey;
  if (image.channels() == 3) {
    cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  } else {
    grey = image;
  }
  cv::Ptr<cv::aruco::DetectorParameters> params = cv::aruco::DetectorParameters::create();
  if (opts.subpixel_corners) {
    params->cornerRefinementMethod = cv::aruco::CORNER_REFINE_SUBPIX;
    params->cornerRefinementWinSize = opts.subpixel_window_px;
    params->cornerRefinementMinAccuracy = 0.01;
    params->cornerRefinementMaxIterations = 50;
  }
  std::vector<std::vector<cv::Point2f>> corners, rejected;
  std::vector<int> ids;
  try {
    cv::aruco::detectMarkers(grey, *dict, corners, ids, params, rejected);
  } catch (const cv::Exception& e) {
    return MakeError(ErrorClass::kInternal, "ArUco detection failed", e.what());
  }
  cv::Mat lin;
  if (opts.edge_refine && !ids.empty()) {
    const std::array<double, 256>& lut = SrgbToLinear();
    lin.create(grey.size(), CV_32F);
    for (int y = 0; y < grey.rows; ++y) {
      const uint8_t* src = grey.ptr<uint8_t>(y);
      float* dst = lin.ptr<float>(y);
      for (int x = 0; x < grey.cols; ++x) {
        dst[x] = static_cast<float>(opts.srgb_photo ? lut[src[x]] : src[x] / 255.0);
      }
    }
  }
  const int cells = (*dict)->markerSize + 2;
  ArucoViewDetections out;
  std::map<int, int> count;
  for (int id : ids) ++count[id];
  for (size_t i = 0; i < ids.size(); ++i) {
    if (!FindMarker(rig, ids[i])) {
      ++out.unknown_ids;
      continue;
    }
    if (count[ids[i]] > 1) {
      ++out.duplicate_ids;
      continue;
    }
    if (TouchesRock(corners[i], rock_mask, opts.rock_clearance_px)) {
      ++out.near_rock;
      continue;
    }
    ArucoSighting s;
    s.id = ids[i];
    for (int k = 0; k < 4; ++k) s.corners_px[k] = Vector2d(corners[i][k].x, corners[i][k].y);
    if (opts.edge_refine && RefineByEdges(lin, camera, cells, opts, &s.corners_px))
      ++out.edge_refined;
    out.markers.push_back(s);
  }
  return out;
}

Result<ArucoScale> LocateArucoMarkers(const std::vector<ArucoViewDetections>& views,
                                      const std::vector<geom::Rigid3>& cam_from_frame,
                                      const CameraModel& camera, const RigConfig& rig,
                                      const ArucoLocateOptions& opts) {
  if (views.size() != cam_from_frame.size()) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "ArUco markers: " + std::to_string(views.size()) + " views but " +
                         std::to_string(cam_from_frame.size()) + " poses");
  }
  if (std::string why = opts.triangulation.Check(); !why.empty()) {
    return MakeError(ErrorClass::kInvalidArgument, "ArUco markers: triangulation options: " + why);
  }
  ArucoScale out;
  out.views = static_cast<int>(views.size());
  for (const ArucoViewDetections& v : views) out.views_with_markers += v.markers.empty() ? 0 : 1;
  for (const ArucoMarker& m : rig.aruco_markers) {
    ArucoMarkerPoint mp;
    mp.id = m.id;
    for (int k = 0; k < 4; ++k) mp.configured[k] = ArucoCornerMm(m, rig.aruco_size_mm, k);
    std::array<std::vector<geom::Sighting>, 4> s;
    for (size_t v = 0; v < views.size(); ++v) {
      for (const ArucoSighting& a : views[v].markers) {
        if (a.id != m.id) continue;
        for (int k = 0; k < 4; ++k) {
          s[k].push_back(
              geom::MakeSighting(camera, cam_from_frame[v], a.corners_px[k], static_cast<int>(v)));
        }
      }
    }
    mp.views_seen = static_cast<int>(s[0].size());
    mp.views_used = mp.views_seen;
    double ss = 0;
    int n = 0;
    static constexpr const char* kCorner[4] = {"top-left", "top-right", "bottom-right",
                                               "bottom-left"};
    for (int k = 0; k < 4 && mp.problem.empty(); ++k) {
      Result<geom::TriangulatedPoint> tp = geom::TriangulatePoint(s[k], opts.triangulation);
      if (!tp) {
        mp.problem = std::string(kCorner[k]) + " corner: " + tp.error().message;
        break;
      }
      mp.corners[k] = tp->X;
      for (int i : tp->inliers)
        ss += tp->residual_px[static_cast<size_t>(i)] * tp->residual_px[static_cast<size_t>(i)],
            ++n;
      mp.max_px = std::max(mp.max_px, tp->max_px);
      mp.views_used = std::min(mp.views_used, static_cast<int>(tp->inliers.size()));
    }
    if (mp.problem.empty()) {
      mp.located = true;
      mp.rms_px = std::sqrt(ss / std::max(n, 1));
      mp.center = (mp.corners[0] + mp.corners[1] + mp.corners[2] + mp.corners[3]) / 4.0;
    } else {
      mp.views_used = 0;
      mp.max_px = 0;
    }
    out.markers.push_back(mp);
  }

  // Lengths: per marker its sides and diagonals; between markers the centres.
  std::vector<std::pair<double, double>> edges, centres;
  std::vector<Vector3d> rec, conf;
  std::string missing;
  std::vector<const ArucoMarkerPoint*> located;
  for (const ArucoMarkerPoint& mp : out.markers) {
    if (!mp.located) {
      missing += (missing.empty() ? "" : "; ") + std::string("id ") + std::to_string(mp.id) +
                 " (detected in " + std::to_string(mp.views_seen) + " of " +
                 std::to_string(views.size()) + " views" +
                 (mp.views_seen > 0 ? ": " + mp.problem : std::string()) + ")";
      continue;
    }
    located.push_back(&mp);
    for (int a = 0; a < 4; ++a) {
      rec.push_back(mp.corners[a]), conf.push_back(mp.configured[a]);
      for (int b = a + 1; b < 4; ++b) {
        edges.emplace_back((mp.corners[a] - mp.corners[b]).norm(),
                           (mp.configured[a] - mp.configured[b]).norm());
      }
    }
  }
  for (size_t i = 0; i < located.size(); ++i) {
    for (size_t j = i + 1; j < located.size(); ++j) {
      const Vector3d ci = (located[i]->configured[0] + located[i]->configured[2]) / 2;
      const Vector3d cj = (located[j]->configured[0] + located[j]->configured[2]) / 2;
      centres.emplace_back((located[i]->center - located[j]->center).norm(), (ci - cj).norm());
    }
  }
  out.markers_used = static_cast<int>(located.size());
  if (out.markers_used < opts.min_markers) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "ArUco markers: only " + std::to_string(out.markers_used) + " of " +
                         std::to_string(rig.aruco_markers.size()) + " located, need " +
                         std::to_string(opts.min_markers) + " for the scale. Missing: " + missing +
                         ". Check that the markers lie flat on the disc, uncovered by the rock, "
                         "lit without glare, and that rig.aruco_dictionary, aruco_size_mm and "
                         "aruco_markers match the print");
  }
  std::vector<geom::LengthPair> all = edges;
  all.insert(all.end(), centres.begin(), centres.end());
  out.lengths = static_cast<int>(all.size());
  const geom::LengthScaleFit fa = geom::FitLengthScale(all);
  out.scale = fa.scale;
  const geom::LengthScaleFit fe = geom::LengthResiduals(out.scale, edges),
                             fc = geom::LengthResiduals(out.scale, centres);
  out.rms_mm = fa.rms_mm, out.max_mm = fa.max_mm;
  out.edge_rms_mm = fe.rms_mm, out.edge_max_mm = fe.max_mm;
  out.centre_rms_mm = fc.rms_mm, out.centre_max_mm = fc.max_mm;
  out.centre_pairs = static_cast<int>(centres.size());
  if (const std::optional<geom::Similarity3> T = geom::AlignPoints(rec, conf, true)) {
    out.frame_to_table = *T;
    geom::AlignmentResidual(*T, rec, conf, &out.align_rms_mm, &out.align_max_mm);
  }
  return out;
}

}  // namespace aggscan
