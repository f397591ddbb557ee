#include "pipeline/markers/markers.h"

#include <Eigen/Eigenvalues>
#include <algorithm>
#include <cmath>
#include <map>
#include <numeric>
#include <opencv2/imgproc.hpp>

namespace aggscan {

namespace {

using Eigen::Vector2d;
using Eigen::Vector3d;

const ColorClass* FindClass(const MarkerDetectOptions& opts, const std::string& name, int* index) {
  for (size_t i = 0; i < opts.colors.size(); ++i) {
    if (opts.colors[i].name == name) {
      *index = static_cast<int>(i) + 1;
      return &opts.colors[i];
    }
  }
  return nullptr;
}

// Undistorted -> distorted pixel through the camera's lens model.
Vector2d DistortPixel(const CameraModel& cam, const Vector2d& undistorted) {
  double u = 0, v = 0;
  cam.Project({(undistorted.x() - cam.cx) / cam.fx, (undistorted.y() - cam.cy) / cam.fy, 1.0}, &u,
              &v);
  return {u, v};
}

// Intersection of two lines given as (direction, point); nullopt if parallel.
std::optional<Vector2d> Intersect(const cv::Vec4f& a, const cv::Vec4f& b) {
  const Vector2d da(a[0], a[1]), pa(a[2], a[3]), db(b[0], b[1]), pb(b[2], b[3]);
  const double den = da.x() * db.y() - da.y() * db.x();
  if (std::abs(den) < 1e-9) return std::nullopt;
  const Vector2d w = pb - pa;
  const double s = (w.x() * db.y() - w.y() * db.x()) / den;
  return pa + s * da;
}

std::optional<Vector2d> IntersectSegments(const Vector2d& p0, const Vector2d& p1,
                                          const Vector2d& q0, const Vector2d& q1) {
  const Vector2d d1 = p1 - p0, d2 = q1 - q0;
  return Intersect(cv::Vec4f(d1.x(), d1.y(), p0.x(), p0.y()),
                   cv::Vec4f(d2.x(), d2.y(), q0.x(), q0.y()));
}

// Label centre with sub-pixel accuracy: the blob's outline (undistorted) is
// split among the four sides of its rough quadrilateral, a line is fitted to
// each side's points away from the corners, adjacent lines meet in the
// refined corners, and the diagonals meet in the image of the square's centre.
std::optional<LabelSighting> FitLabel(const std::vector<cv::Point>& contour,
                                      const std::vector<cv::Point>& quad, const CameraModel* cam,
                                      cv::Point offset) {
  auto undist = [&](double x, double y) {
    const Vector2d p(x + offset.x, y + offset.y);
    return cam ? geom::UndistortPixel(*cam, p) : p;
  };
  std::array<Vector2d, 4> q;
  for (int k = 0; k < 4; ++k) q[k] = undist(quad[k].x, quad[k].y);
  std::array<std::vector<cv::Point2f>, 4> side_pts;
  for (const cv::Point& c : contour) {
    const Vector2d p = undist(c.x, c.y);
    // The nearest side takes the point, unless it lies near that side's ends
    // (corner rounding) or off the side (a notch).
    int best = -1;
    double best_d = 1e300, best_t = 0;
    for (int k = 0; k < 4; ++k) {
      const Vector2d a = q[k], b = q[(k + 1) % 4];
      const double len = (b - a).norm();
      if (len < 1e-9) continue;
      const double t = std::clamp((p - a).dot(b - a) / (len * len), 0.0, 1.0);
      const double d = (a + t * (b - a) - p).norm();
      if (d < best_d) best_d = d, best = k, best_t = t;
    }
    if (best_t < 0.15 || best_t > 0.85 || best_d > 3.0) best = -1;
    if (best >= 0)
      side_pts[best].emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()));
  }
  std::array<cv::Vec4f, 4> lines;
  for (int k = 0; k < 4; ++k) {
    if (side_pts[k].size() < 3) return std::nullopt;
    cv::fitLine(side_pts[k], lines[k], cv::DIST_L2, 0, 0.01, 0.01);
  }
  LabelSighting out;
  std::array<Vector2d, 4> corners;
  for (int k = 0; k < 4; ++k) {
    const std::optional<Vector2d> c = Intersect(lines[(k + 3) % 4], lines[k]);
    if (!c) return std::nullopt;
    corners[k] = *c;
  }
  const std::optional<Vector2d> centre =
      IntersectSegments(corners[0], corners[2], corners[1], corners[3]);
  if (!centre) return std::nullopt;
  double ss = 0;
  int n = 0;
  for (int k = 0; k < 4; ++k) {
    const Vector2d d(lines[k][0], lines[k][1]), p0(lines[k][2], lines[k][3]);
    for (const cv::Point2f& p : side_pts[k]) {
      const Vector2d w = Vector2d(p.x, p.y) - p0;
      const double e = d.x() * w.y() - d.y() * w.x();
      ss += e * e, ++n;
    }
  }
  out.edge_rms_px = std::sqrt(ss / std::max(n, 1));
  out.center_px = cam ? DistortPixel(*cam, *centre) : *centre;
  for (int k = 0; k < 4; ++k) out.corners_px[k] = cam ? DistortPixel(*cam, corners[k]) : corners[k];
  return out;
}

// Quadrilateral of a convex outline: approxPolyDP with a growing tolerance
// until four vertices remain (empty if it never gives exactly four).
std::vector<cv::Point> QuadOf(const std::vector<cv::Point>& hull) {
  const double perim = cv::arcLength(hull, true);
  std::vector<cv::Point> poly;
  for (double eps = 0.02; eps <= 0.12; eps += 0.01) {
    cv::approxPolyDP(hull, poly, eps * perim, true);
    if (poly.size() == 4) return poly;
    if (poly.size() < 4) break;
  }
  return {};
}

// Pixel statistics of one connected segment (labels image == id inside rect;
// `labels` and `inner_mask` are a window whose top-left is `origin` in the
// photo, and the statistics are in the photo's pixels).
SegmentBlob BlobOf(const cv::Mat& labels, int id, const cv::Rect& rect, const cv::Mat& inner_mask,
                   cv::Point origin) {
  double sx = 0, sy = 0, sxx = 0, syy = 0, sxy = 0;
  int n = 0, edge = 0;
  for (int wy = rect.y; wy < rect.y + rect.height; ++wy) {
    const int* row = labels.ptr<int>(wy);
    const uint8_t* inner = inner_mask.ptr<uint8_t>(wy);
    const double y = wy + origin.y;
    for (int wx = rect.x; wx < rect.x + rect.width; ++wx) {
      if (row[wx] != id) continue;
      const double x = wx + origin.x;
      sx += x, sy += y, sxx += x * x, syy += y * y, sxy += x * y;
      ++n;
      edge += inner[wx] == 0;
    }
  }
  SegmentBlob b;
  b.area_px = n;
  const double mx = sx / n, my = sy / n;
  b.center_px = {mx, my};
  Eigen::Matrix2d C;
  C << sxx / n - mx * mx, sxy / n - mx * my, sxy / n - mx * my, syy / n - my * my;
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> es(C);
  // A uniform bar of length L has variance L^2 / 12 along it.
  b.length_px = std::sqrt(12.0 * std::max(es.eigenvalues()(1), 0.0));
  b.width_px = std::sqrt(12.0 * std::max(es.eigenvalues()(0), 0.0));
  b.axis = es.eigenvectors().col(1);
  b.truncated = edge > 0;
  return b;
}

}  // namespace

std::vector<ColorClass> DefaultColorClasses() {
  return {{"red", 0.0, 22.0},
          {"yellow", 54.0, 18.0},
          {"green", 132.0, 25.0},
          {"blue", 223.0, 25.0},
          {"purple", 288.0, 25.0}};
}

std::string MarkerDetectOptions::Check() const {
  if (colors.empty() || colors.size() > 250) return "colors: 1..250 classes";
  for (const ColorClass& c : colors) {
    if (!(c.hue_deg >= 0 && c.hue_deg < 360)) return "colors." + c.name + ": hue_deg in [0, 360)";
    if (!(c.hue_tol_deg > 0 && c.hue_tol_deg <= 90))
      return "colors." + c.name + ": hue_tol_deg in (0, 90]";
  }
  if (!(min_saturation > 0 && min_saturation < 1)) return "min_saturation in (0, 1)";
  if (!(min_chroma >= 0 && min_chroma < 1)) return "min_chroma in [0, 1)";
  if (!(label_min_side_frac > 0 && label_min_side_frac < label_max_side_frac))
    return "label_min_side_frac must be > 0 and < label_max_side_frac";
  if (!(label_min_solidity > 0 && label_min_solidity <= 1)) return "label_min_solidity in (0, 1]";
  if (!(label_min_fill > 0 && label_min_fill <= 1)) return "label_min_fill in (0, 1]";
  if (rock_clearance_px < 0 || marker_mask_dilate_px < 0) return "pixel distances must be >= 0";
  if (!(segment_min_area_frac > 0)) return "segment_min_area_frac must be > 0";
  if (!(head_tail_min_ratio >= 1)) return "head_tail_min_ratio must be >= 1";
  return {};
}

namespace {

// The colour class rule below as two tables, made by the very OpenCV
// operations that define it (so a lookup gives what they give, to the bit):
// per hue the class (a later class wins where two overlap), per
// (saturation, value) whether the pixel is paint at all.
struct ClassTables {
  std::array<uint8_t, 256> hue_class{};
  cv::Mat paint;  // 256 x 256 CV_8U, row = saturation, column = value; 0/255
};

ClassTables MakeClassTables(const MarkerDetectOptions& opts) {
  ClassTables t;
  cv::Mat sat(256, 256, CV_8UC1), val(256, 256, CV_8UC1);
  for (int y = 0; y < 256; ++y) {
    for (int x = 0; x < 256; ++x) {
      sat.at<uint8_t>(y, x) = static_cast<uint8_t>(y);
      val.at<uint8_t>(y, x) = static_cast<uint8_t>(x);
    }
  }
  // Chroma (max - min) = S * V / 255: low on noisy dark pixels whatever S says.
  cv::Mat chroma;
  cv::multiply(sat, val, chroma, 1.0 / 255.0, CV_8U);
  t.paint = (sat >= opts.min_saturation * 255.0) & (chroma >= opts.min_chroma * 255.0);
  cv::Mat hue(1, 256, CV_8UC1), cls(1, 256, CV_8UC1, cv::Scalar(0));
  for (int h = 0; h < 256; ++h) hue.at<uint8_t>(0, h) = static_cast<uint8_t>(h);
  for (size_t i = 0; i < opts.colors.size(); ++i) {
    const ColorClass& c = opts.colors[i];
    const double lo = (c.hue_deg - c.hue_tol_deg) * 256.0 / 360.0;
    const double hi = (c.hue_deg + c.hue_tol_deg) * 256.0 / 360.0;
    cv::Mat in;
    if (lo < 0) {
      in = (hue >= lo + 256.0) | (hue <= hi);
    } else if (hi >= 256.0) {
      in = (hue >= lo) | (hue <= hi - 256.0);
    } else {
      in = (hue >= lo) & (hue <= hi);
    }
    cls.setTo(cv::Scalar(static_cast<double>(i + 1)), in);
  }
  for (int h = 0; h < 256; ++h) t.hue_class[static_cast<size_t>(h)] = cls.at<uint8_t>(0, h);
  return t;
}

// ClassifyColors, and the box of each class's pixels (index = class value;
// empty where a class has none): the steps after it look only there.
cv::Mat ClassifyColorsBoxed(const cv::Mat& bgr, const MarkerDetectOptions& opts,
                            std::vector<cv::Rect>* boxes) {
  // 8-bit HSV with the full hue range: H in 0..255 for 0..360 deg.
  cv::Mat hsv;
  cv::cvtColor(bgr, hsv, cv::COLOR_BGR2HSV_FULL);
  const ClassTables t = MakeClassTables(opts);
  const size_t n = opts.colors.size() + 1;
  std::vector<int> x0(n, bgr.cols), y0(n, bgr.rows), x1(n, -1), y1(n, -1);
  cv::Mat cls(bgr.size(), CV_8UC1);
  for (int y = 0; y < hsv.rows; ++y) {
    const uint8_t* p = hsv.ptr<uint8_t>(y);
    uint8_t* c = cls.ptr<uint8_t>(y);
    for (int x = 0; x < hsv.cols; ++x, p += 3) {
      const uint8_t k = t.paint.at<uint8_t>(p[1], p[2]) ? t.hue_class[p[0]] : 0;
      c[x] = k;
      if (k) {
        x0[k] = std::min(x0[k], x), x1[k] = std::max(x1[k], x);
        y0[k] = std::min(y0[k], y), y1[k] = std::max(y1[k], y);
      }
    }
  }
  if (boxes) {
    boxes->assign(n, cv::Rect());
    for (size_t k = 1; k < n; ++k)
      if (x1[k] >= 0) (*boxes)[k] = cv::Rect(x0[k], y0[k], x1[k] - x0[k] + 1, y1[k] - y0[k] + 1);
  }
  return cls;
}

// `r` grown by `margin` on every side, within `frame`.
cv::Rect Grown(const cv::Rect& r, int margin, const cv::Size& frame) {
  return cv::Rect(r.x - margin, r.y - margin, r.width + 2 * margin, r.height + 2 * margin) &
         cv::Rect(0, 0, frame.width, frame.height);
}

}  // namespace

cv::Mat ClassifyColors(const cv::Mat& bgr, const MarkerDetectOptions& opts) {
  return ClassifyColorsBoxed(bgr, opts, nullptr);
}

double PxPerMmAtDisc(const RigCalibration& cal) {
  const std::array<double, 3> c = cal.CameraCentreTable0();
  const double dist = std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
  return dist > 0 ? 0.5 * (cal.camera.fx + cal.camera.fy) / dist : 0;
}

double ExpectedLabelSidePx(const RigCalibration& cal, const RigConfig& rig) {
  return PxPerMmAtDisc(cal) * rig.marker_size_mm;
}

Result<ViewMarkers> DetectViewMarkers(const cv::Mat& bgr, const cv::Mat& rock_mask,
                                      const std::vector<std::string>& label_colors,
                                      const std::vector<std::string>& object_colors,
                                      const CameraModel* camera, const MarkerDetectOptions& opts) {
  if (std::string bad = opts.Check(); !bad.empty()) {
    return MakeError(ErrorClass::kInvalidArgument, "marker detection options: " + bad);
  }
  if (bgr.empty() || bgr.type() != CV_8UC3) {
    return MakeError(ErrorClass::kInvalidArgument, "markers: the photo must be 8-bit BGR");
  }
  if (rock_mask.size() != bgr.size() || rock_mask.type() != CV_8UC1) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "markers: the rock mask must be 8-bit, one channel, the photo's size");
  }
  for (const auto* list : {&label_colors, &object_colors}) {
    for (const std::string& name : *list) {
      int idx = 0;
      if (!FindClass(opts, name, &idx)) {
        return MakeError(ErrorClass::kInvalidArgument,
                         "markers: no colour class '" + name +
                             "' (known: red, green, blue, "
                             "yellow, purple, or MarkerDetectOptions::colors)");
      }
    }
  }
  // Every step below works on the box of the pixels it can concern (a
  // class's paint, the rock and its surroundings): the rock and its labels
  // cover a few per cent of the frame.
  std::vector<cv::Rect> class_box;
  const cv::Mat cls = ClassifyColorsBoxed(bgr, opts, &class_box);
  const int W = bgr.cols, H = bgr.rows;
  cv::Mat rock;
  cv::compare(rock_mask, 0, rock, cv::CMP_GT);
  const cv::Rect rock_box = cv::boundingRect(rock);
  ViewMarkers out;

  // --- background labels ---
  cv::Mat near_rock = cv::Mat::zeros(rock.size(), CV_8UC1);
  if (rock_box.area() > 0) {
    const cv::Rect r = Grown(rock_box, opts.rock_clearance_px + 1, rock.size());
    cv::Mat grown;
    cv::dilate(
        rock(r), grown,
        cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * opts.rock_clearance_px + 1,
                                                              2 * opts.rock_clearance_px + 1)));
    grown.copyTo(near_rock(r));
  }
  const double min_side = opts.label_min_side_frac * W, max_side = opts.label_max_side_frac * W;
  const cv::Mat k3 = cv::getStructuringElement(cv::MORPH_RECT, cv::Size(3, 3));
  for (const std::string& color : label_colors) {
    int idx = 0;
    FindClass(opts, color, &idx);
    if (class_box[static_cast<size_t>(idx)].empty()) continue;  // no pixel of this colour
    const cv::Rect box = Grown(class_box[static_cast<size_t>(idx)], 2, cls.size());
    cv::Mat bin = cls(box) == idx;
    cv::morphologyEx(bin, bin, cv::MORPH_OPEN, k3);
    cv::Mat lab, stats, cents;
    const int n = cv::connectedComponentsWithStats(bin, lab, stats, cents, 8, CV_32S);
    std::optional<LabelSighting> best;
    double best_score = 0;
    for (int i = 1; i < n; ++i) {
      const int area = stats.at<int>(i, cv::CC_STAT_AREA);
      const double side = std::sqrt(static_cast<double>(area));
      if (side < min_side || side > max_side) continue;
      if (opts.expected_label_side_px > 0 &&
          (side < 0.4 * opts.expected_label_side_px || side > 2.5 * opts.expected_label_side_px)) {
        continue;
      }
      const cv::Rect in_box(stats.at<int>(i, cv::CC_STAT_LEFT), stats.at<int>(i, cv::CC_STAT_TOP),
                            stats.at<int>(i, cv::CC_STAT_WIDTH),
                            stats.at<int>(i, cv::CC_STAT_HEIGHT));
      const cv::Rect r = in_box + box.tl();
      if (r.x <= 1 || r.y <= 1 || r.x + r.width >= W - 1 || r.y + r.height >= H - 1) continue;
      const cv::Mat blob = lab(in_box) == i;
      if (cv::countNonZero(blob & near_rock(r)) > 0) continue;  // partly hidden by the rock
      std::vector<std::vector<cv::Point>> contours;
      cv::findContours(blob.clone(), contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE);
      if (contours.empty()) continue;
      const auto& contour =
          *std::max_element(contours.begin(), contours.end(),
                            [](const auto& a, const auto& b) { return a.size() < b.size(); });
      std::vector<cv::Point> hull;
      cv::convexHull(contour, hull);
      const double hull_area = cv::contourArea(hull);
      if (!(hull_area > 0) || area / hull_area < opts.label_min_solidity) continue;
      const std::vector<cv::Point> quad = QuadOf(hull);
      if (quad.size() != 4) continue;
      const double quad_area = cv::contourArea(quad);
      if (!(quad_area > 0) || std::min(area / quad_area, quad_area / area) < opts.label_min_fill) {
        continue;
      }
      std::optional<LabelSighting> fit = FitLabel(contour, quad, camera, r.tl());
      if (!fit) continue;
      fit->color = color;
      fit->area_px = area;
      const double score = area * std::min(area / quad_area, quad_area / area);
      if (score > best_score) best = fit, best_score = score;
    }
    if (best) out.labels.push_back(*best);
  }

  // --- object markers ---
  // On the rock's box grown by the dilation: nothing of these reaches past it.
  const int d = opts.marker_mask_dilate_px;
  const cv::Rect near_box = rock_box.area() > 0 ? Grown(rock_box, d + 3, rock.size()) : cv::Rect();
  cv::Mat near_mask, inner;
  if (near_box.area() > 0) {
    cv::dilate(rock(near_box), near_mask,
               cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * d + 1, 2 * d + 1)));
    // Pixels of the rock at least 2 px from the background: a segment
    // reaching outside this touches the silhouette.
    cv::erode(rock(near_box), inner, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(5, 5)));
  }
  const double min_area = opts.segment_min_area_frac * W * W;
  for (const std::string& color : object_colors) {
    int idx = 0;
    FindClass(opts, color, &idx);
    ObjectMarkerSighting sight;
    sight.color = color;
    if (near_box.area() == 0) {
      out.objects.push_back(std::move(sight));
      continue;
    }
    const cv::Mat bin = (cls(near_box) == idx) & near_mask;
    cv::Mat lab, stats, cents;
    const int n = cv::connectedComponentsWithStats(bin, lab, stats, cents, 8, CV_32S);
    std::vector<SegmentBlob> blobs;
    for (int i = 1; i < n; ++i) {
      const int area = stats.at<int>(i, cv::CC_STAT_AREA);
      if (area < min_area) continue;
      const cv::Rect r(stats.at<int>(i, cv::CC_STAT_LEFT), stats.at<int>(i, cv::CC_STAT_TOP),
                       stats.at<int>(i, cv::CC_STAT_WIDTH), stats.at<int>(i, cv::CC_STAT_HEIGHT));
      // Mostly outside the mask: paint of the background (a label), not the rock.
      if (cv::countNonZero((lab(r) == i) & rock(r + near_box.tl())) * 2 < area) continue;
      blobs.push_back(BlobOf(lab, i, r, inner, near_box.tl()));
    }
    std::sort(blobs.begin(), blobs.end(),
              [](const SegmentBlob& a, const SegmentBlob& b) { return a.area_px > b.area_px; });
    if (blobs.size() >= 2) {
      // Head and tail: the largest segment and a smaller one on its axis,
      // beyond its end but not farther than a pattern length.
      const SegmentBlob& a = blobs[0];
      int partner = -1;
      for (size_t j = 1; j < blobs.size() && partner < 0; ++j) {
        const SegmentBlob& b = blobs[j];
        const Vector2d w = b.center_px - a.center_px;
        const double along = std::abs(w.dot(a.axis));
        const double across = std::abs(a.axis.x() * w.y() - a.axis.y() * w.x());
        const bool on_axis = across <= std::max(1.5 * a.width_px, 3.0);
        const bool beyond = along >= 0.4 * a.length_px && along <= 1.5 * a.length_px + b.length_px;
        if (on_axis && beyond && a.area_px >= opts.head_tail_min_ratio * b.area_px) {
          partner = static_cast<int>(j);
        }
      }
      if (partner > 0) {
        sight.tail = blobs[0];
        sight.head = blobs[partner];
        blobs.erase(blobs.begin() + partner);
        blobs.erase(blobs.begin());
      }
    }
    sight.unassigned = std::move(blobs);
    out.objects.push_back(std::move(sight));
  }
  return out;
}

// --- background labels: 3D and scale ---

Result<LabelScale> LocateLabels(const std::vector<ViewMarkers>& views,
                                const std::vector<geom::Rigid3>& cam_from_frame,
                                const CameraModel& camera, const RigConfig& rig,
                                const LabelLocateOptions& opts) {
  if (views.size() != cam_from_frame.size()) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "labels: " + std::to_string(views.size()) + " views but " +
                         std::to_string(cam_from_frame.size()) + " poses");
  }
  LabelScale out;
  for (const RigMarker& m : rig.markers) {
    LabelPoint lp;
    lp.color = m.color;
    lp.configured = Vector3d(m.x_mm, m.y_mm, 0.0);
    std::vector<geom::Sighting> s;
    for (size_t v = 0; v < views.size(); ++v) {
      for (const LabelSighting& l : views[v].labels) {
        if (l.color == m.color) {
          s.push_back(
              geom::MakeSighting(camera, cam_from_frame[v], l.center_px, static_cast<int>(v)));
        }
      }
    }
    lp.views_seen = static_cast<int>(s.size());
    Result<geom::TriangulatedPoint> tp = geom::TriangulatePoint(s, opts.triangulation);
    if (tp.ok()) {
      lp.located = true;
      lp.position = tp->X;
      lp.rms_px = tp->rms_px;
      lp.max_px = tp->max_px;
      lp.views_used = static_cast<int>(tp->inliers.size());
    } else {
      lp.problem = tp.error().message;
    }
    out.labels.push_back(lp);
  }
  std::vector<Vector3d> rec, conf;
  std::string missing;
  for (const LabelPoint& lp : out.labels) {
    if (lp.located) {
      rec.push_back(lp.position), conf.push_back(lp.configured);
    } else {
      missing += (missing.empty() ? "" : "; ") + lp.color + " (detected in " +
                 std::to_string(lp.views_seen) + " of " + std::to_string(views.size()) +
                 " views: " + lp.problem + ")";
    }
  }
  out.labels_used = static_cast<int>(rec.size());
  if (out.labels_used < opts.min_labels) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "background labels: only " + std::to_string(out.labels_used) + " of " +
                         std::to_string(rig.markers.size()) + " located, need " +
                         std::to_string(opts.min_labels) + " for the scale. Missing: " + missing +
                         ". Check that the labels are on the disc, uncovered by the rock or "
                         "anything else, lit, and that rig.markers lists their colours and "
                         "positions");
  }
  std::vector<geom::LengthPair> pairs;
  for (size_t i = 0; i < rec.size(); ++i) {
    for (size_t j = i + 1; j < rec.size(); ++j) {
      pairs.emplace_back((rec[i] - rec[j]).norm(), (conf[i] - conf[j]).norm());
    }
  }
  const geom::LengthScaleFit fit = geom::FitLengthScale(pairs);
  out.scale = fit.scale;
  out.pair_rms_mm = fit.rms_mm;
  out.pair_max_mm = fit.max_mm;
  const std::optional<geom::Similarity3> T = geom::AlignPoints(rec, conf, true);
  if (!T) {
    return MakeError(ErrorClass::kInvalidArgument,
                     "background labels: the located labels are collinear; no similarity");
  }
  out.frame_to_table = *T;
  geom::AlignmentResidual(*T, rec, conf, &out.align_rms_mm, &out.align_max_mm);
  return out;
}

// --- object markers ---

int SideMarkers::located() const {
  return static_cast<int>(
      std::count_if(points.begin(), points.end(), [](const MarkerPoint& p) { return p.located; }));
}

const MarkerPoint* SideMarkers::Find(const std::string& color, const std::string& segment) const {
  for (const MarkerPoint& p : points) {
    if (p.color == color && p.segment == segment) return &p;
  }
  return nullptr;
}

namespace {

// One segment seen in one view; hint: the per-view head/tail split (0 none,
// 1 head, 2 tail).
struct Obs {
  int view;
  SegmentBlob blob;
  int hint = 0;
};

// Triangulates one segment from its observations, clean ones first. Inliers
// are indices into `obs`.
Result<geom::TriangulatedPoint> TriangulateSegment(const std::vector<Obs>& obs,
                                                   const std::vector<geom::Rigid3>& poses,
                                                   const CameraModel& cam,
                                                   const MarkerLocateOptions& opts) {
  // Clean: not cut by the silhouette, and seen nearly as large as in the best
  // view (a foreshortened segment on a curved surface shows a lopsided part).
  double max_area = 0;
  for (const Obs& o : obs) {
    if (!o.blob.truncated) max_area = std::max(max_area, o.blob.area_px);
  }
  std::vector<geom::Sighting> clean, all;
  std::vector<int> clean_idx;
  for (size_t i = 0; i < obs.size(); ++i) {
    const Obs& o = obs[i];
    geom::Sighting s = geom::MakeSighting(cam, poses[o.view], o.blob.center_px, o.view);
    if (!o.blob.truncated && o.blob.area_px >= opts.min_area_frac * max_area) {
      clean.push_back(s);
      clean_idx.push_back(static_cast<int>(i));
    }
    all.push_back(s);
  }
  if (static_cast<int>(clean.size()) >= opts.min_clean_views) {
    Result<geom::TriangulatedPoint> r = geom::TriangulatePoint(clean, opts.triangulation);
    if (r.ok()) {
      for (int& i : r->inliers) i = clean_idx[i];
      return r;
    }
  }
  return geom::TriangulatePoint(all, opts.triangulation);
}

// The observations a 3D point explains: per view, the nearest segment within
// the inlier distance (truncated ones count half in the score).
std::vector<int> Support(const Eigen::Vector3d& X, const std::vector<Obs>& obs,
                         const std::vector<bool>& taken, const std::vector<geom::Rigid3>& poses,
                         const CameraModel& cam, double tol_px, double* score) {
  std::map<int, std::pair<int, double>> per_view;  // view -> (obs, distance)
  for (size_t i = 0; i < obs.size(); ++i) {
    if (taken[i]) continue;
    const std::optional<Vector2d> p = geom::ProjectPoint(cam, poses[obs[i].view], X);
    if (!p) continue;
    const double d = (*p - obs[i].blob.center_px).norm();
    if (d > tol_px) continue;
    auto it = per_view.find(obs[i].view);
    if (it == per_view.end() || d < it->second.second)
      per_view[obs[i].view] = {static_cast<int>(i), d};
  }
  std::vector<int> out;
  *score = 0;
  for (const auto& [v, od] : per_view) {
    out.push_back(od.first);
    *score += obs[od.first].blob.truncated ? 0.5 : 1.0;
  }
  return out;
}

// The best-supported 3D point among the two-view triangulations of untaken
// observations (optionally within [min_d, max_d] of `other`).
std::optional<Eigen::Vector3d> BestSeed(const std::vector<Obs>& obs, const std::vector<bool>& taken,
                                        const std::vector<geom::Rigid3>& poses,
                                        const CameraModel& cam, const MarkerLocateOptions& opts,
                                        const Eigen::Vector3d* other) {
  std::vector<geom::Sighting> s;
  s.reserve(obs.size());
  for (const Obs& o : obs)
    s.push_back(geom::MakeSighting(cam, poses[o.view], o.blob.center_px, o.view));
  geom::TriangulationOptions two = opts.triangulation;
  two.robust = false;
  two.refine_iterations = 3;
  double best_score = 0;
  std::optional<Eigen::Vector3d> best;
  for (size_t i = 0; i < obs.size(); ++i) {
    for (size_t j = i + 1; j < obs.size(); ++j) {
      if (taken[i] || taken[j] || obs[i].view == obs[j].view) continue;
      Result<geom::TriangulatedPoint> t = geom::TriangulatePoint({s[i], s[j]}, two);
      if (!t.ok() || t->max_px > opts.triangulation.inlier_px) continue;
      if (other) {
        const double d = (t->X - *other).norm();
        if (d < opts.min_head_tail_mm || d > opts.max_head_tail_mm) continue;
      }
      double score = 0;
      Support(t->X, obs, taken, poses, cam, opts.triangulation.inlier_px, &score);
      if (score > best_score) best_score = score, best = t->X;
    }
  }
  return best;
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

}  // namespace

SideMarkers LocateObjectMarkers(const std::vector<ViewMarkers>& views,
                                const std::vector<geom::Rigid3>& cam_from_frame,
                                const CameraModel& camera, const std::vector<std::string>& colors,
                                const MarkerLocateOptions& opts) {
  SideMarkers out;
  out.views = static_cast<int>(views.size());
  const size_t nv = std::min(views.size(), cam_from_frame.size());
  for (const std::string& color : colors) {
    // Every segment seen, whatever the per-view split said: head and tail are
    // two fixed points of the side, so they are found as the two 3D points
    // that explain most segments; the split only breaks ties of naming.
    std::vector<Obs> obs;
    int with_marker = 0;
    for (size_t v = 0; v < nv; ++v) {
      for (const ObjectMarkerSighting& s : views[v].objects) {
        if (s.color != color) continue;
        with_marker += s.seen();
        const int vi = static_cast<int>(v);
        if (s.head) obs.push_back({vi, *s.head, 1});
        if (s.tail) obs.push_back({vi, *s.tail, 2});
        for (const SegmentBlob& b : s.unassigned) obs.push_back({vi, b, 0});
      }
    }
    out.views_with_marker.push_back(with_marker);
    std::vector<bool> taken(obs.size(), false);
    // Up to two points: the best supported, then the best at a head-tail
    // distance from it.
    std::array<std::optional<geom::TriangulatedPoint>, 2> found;
    std::array<std::vector<Obs>, 2> found_obs;
    std::string why;
    for (int k = 0; k < 2; ++k) {
      const Eigen::Vector3d* other = k == 1 && found[0] ? &found[0]->X : nullptr;
      if (k == 1 && !other) break;
      const std::optional<Eigen::Vector3d> seed =
          BestSeed(obs, taken, cam_from_frame, camera, opts, other);
      if (!seed) {
        why = "no two views of its segments agree within " +
              std::to_string(opts.triangulation.inlier_px) + " px";
        break;
      }
      double score = 0;
      const std::vector<int> sup =
          Support(*seed, obs, taken, cam_from_frame, camera, opts.triangulation.inlier_px, &score);
      std::vector<Obs> so;
      so.reserve(sup.size());
      for (int i : sup) so.push_back(obs[i]);
      Result<geom::TriangulatedPoint> tp = TriangulateSegment(so, cam_from_frame, camera, opts);
      if (!tp.ok()) {
        why = tp.error().message;
        break;
      }
      if (other) {
        const double d = (tp->X - *other).norm();
        if (d < opts.min_head_tail_mm || d > opts.max_head_tail_mm) {
          why = "the second segment refines to " + std::to_string(d) + " mm from the first";
          break;
        }
      }
      for (int i : sup) taken[i] = true;
      found[k] = tp.value();
      found_obs[k] = so;
    }
    // Which is the tail: its segments are the larger (3x the head's length)
    // in the views that show both; failing that, the per-view split's votes.
    int tail_index = -1;  // 0 or 1: which found point is the tail
    if (found[0] && found[1]) {
      std::vector<double> ratio;
      for (const Obs& a : found_obs[0]) {
        for (const Obs& b : found_obs[1]) {
          if (a.view == b.view && !a.blob.truncated && !b.blob.truncated) {
            ratio.push_back(a.blob.area_px / std::max(b.blob.area_px, 1.0));
          }
        }
      }
      if (!ratio.empty() && std::abs(std::log(Median(ratio))) > std::log(1.2)) {
        tail_index = Median(ratio) > 1 ? 0 : 1;
      }
    }
    if (tail_index < 0) {
      // Votes of the per-view split: +1 for "tail" hints, -1 for "head".
      std::array<int, 2> votes{0, 0};
      for (int k = 0; k < 2; ++k) {
        for (const Obs& o : found_obs[k]) votes[k] += o.hint == 2 ? 1 : o.hint == 1 ? -1 : 0;
      }
      if (found[0] && found[1] && votes[0] != votes[1]) {
        tail_index = votes[0] > votes[1] ? 0 : 1;
      } else if (found[0] && !found[1] && votes[0] != 0) {
        tail_index = votes[0] > 0 ? 0 : 1;  // 1: the lone point is the head
      }
    }
    std::array<MarkerPoint, 2> pts;  // head, tail
    for (int seg = 0; seg < 2; ++seg) {
      MarkerPoint& p = pts[seg];
      p.color = color;
      p.segment = seg == 0 ? "head" : "tail";
      // found index holding this segment
      int k = -1;
      if (tail_index >= 0) {
        if (found[0] && found[1])
          k = seg == 1 ? tail_index : 1 - tail_index;
        else if (found[0])
          k = (seg == 1) == (tail_index == 0) ? 0 : -1;
      }
      if (k >= 0 && found[k]) {
        const geom::TriangulatedPoint& tp = *found[k];
        p.located = true;
        p.position = tp.X;
        p.rms_px = tp.rms_px;
        p.max_px = tp.max_px;
        p.views_seen = static_cast<int>(found_obs[k].size());
        p.views_used = static_cast<int>(tp.inliers.size());
      } else if (with_marker == 0) {
        p.problem =
            "the " + color + " marker was not seen in any of the " + std::to_string(nv) + " views";
      } else if (found[0] && tail_index < 0) {
        p.problem = "the " + color + " marker (seen in " + std::to_string(with_marker) +
                    " views) gave " + (found[1] ? "two points" : "one point") +
                    " that cannot be told apart as head and tail";
      } else {
        p.problem = "the " + color + " marker was seen in " + std::to_string(with_marker) +
                    " views, but only in pieces or at the rock's outline: " +
                    (why.empty() ? "one segment located" : why);
      }
    }
    out.points.push_back(pts[0]);
    out.points.push_back(pts[1]);
  }
  return out;
}

}  // namespace aggscan
