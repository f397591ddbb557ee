#include "pipeline/morph/morph2d.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <opencv2/imgproc.hpp>

namespace aggscan {
namespace {

// Gaussian applied to the 0/1 silhouette before tracing the 0.5 iso-line.
// 1.0 px removes the staircase of slanted edges (its 2-3 px periods are damped
// by > 90 %) while rounding corners by well under a pixel.
constexpr double kContourSigmaPx = 1.0;

struct SubpixelContour {
  std::vector<cv::Point2f> points;  // segment end points (unordered), image coordinates
  double length = 0;
};

cv::Point2f Lerp(float x0, float y0, float x1, float y1, float v0, float v1) {
  const float t = (0.5f - v0) / (v1 - v0);
  return {x0 + t * (x1 - x0), y0 + t * (y1 - y0)};
}

// Marching squares on `field` (CV_32F, values in [0,1]) at level 0.5. Cell
// corners are pixel centres; `offset` maps field coordinates to the image.
SubpixelContour TraceIsoLine(const cv::Mat& field, cv::Point offset) {
  SubpixelContour out;
  const float ox = static_cast<float>(offset.x), oy = static_cast<float>(offset.y);
  for (int y = 0; y + 1 < field.rows; ++y) {
    const float* r0 = field.ptr<float>(y);
    const float* r1 = field.ptr<float>(y + 1);
    for (int x = 0; x + 1 < field.cols; ++x) {
      const float v0 = r0[x], v1 = r0[x + 1], v2 = r1[x + 1], v3 = r1[x];  // TL, TR, BR, BL
      const int code =
          (v0 >= 0.5f) | ((v1 >= 0.5f) << 1) | ((v2 >= 0.5f) << 2) | ((v3 >= 0.5f) << 3);
      if (code == 0 || code == 15) continue;
      const float fx = static_cast<float>(x) + ox, fy = static_cast<float>(y) + oy;
      // Crossing points on the four cell edges: top, right, bottom, left.
      cv::Point2f e[4];
      bool has[4] = {false, false, false, false};
      if ((v0 >= 0.5f) != (v1 >= 0.5f)) {
        e[0] = Lerp(fx, fy, fx + 1, fy, v0, v1);
        has[0] = true;
      }
      if ((v1 >= 0.5f) != (v2 >= 0.5f)) {
        e[1] = Lerp(fx + 1, fy, fx + 1, fy + 1, v1, v2);
        has[1] = true;
      }
      if ((v3 >= 0.5f) != (v2 >= 0.5f)) {
        e[2] = Lerp(fx, fy + 1, fx + 1, fy + 1, v3, v2);
        has[2] = true;
      }
      if ((v0 >= 0.5f) != (v3 >= 0.5f)) {
        e[3] = Lerp(fx, fy, fx, fy + 1, v0, v3);
        has[3] = true;
      }
      auto add = [&](int a, int b) {
        out.points.push_back(e[a]);
        out.points.push_back(e[b]);
        out.length += std::hypot(e[a].x - e[b].x, e[a].y - e[b].y);
      };
      if (code == 5 || code == 10) {
        // Saddle: the cell centre value decides which diagonal is connected.
        const bool centre_in = (v0 + v1 + v2 + v3) * 0.25f >= 0.5f;
        const bool tl_br_in = code == 5;
        if (centre_in == tl_br_in) {
          add(0, 1);  // cut off the TR corner
          add(2, 3);  // and the BL corner
        } else {
          add(0, 3);  // cut off the TL corner
          add(1, 2);  // and the BR corner
        }
        continue;
      }
      int idx[2], n = 0;
      for (int k = 0; k < 4 && n < 2; ++k)
        if (has[k]) idx[n++] = k;
      if (n == 2) add(idx[0], idx[1]);
    }
  }
  return out;
}

}  // namespace

cv::Mat LargestComponentFilled(const cv::Mat& mask) {
  CV_Assert(mask.type() == CV_8UC1);
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(mask, labels, stats, centroids, 8, CV_32S);
  cv::Mat out = cv::Mat::zeros(mask.size(), CV_8UC1);
  if (n <= 1) return out;
  int best = 1;
  for (int i = 2; i < n; ++i)
    if (stats.at<int>(i, cv::CC_STAT_AREA) > stats.at<int>(best, cv::CC_STAT_AREA)) best = i;
  out = (labels == best);
  // Fill holes: background reachable from outside the bounding box stays background.
  const cv::Rect box(stats.at<int>(best, cv::CC_STAT_LEFT), stats.at<int>(best, cv::CC_STAT_TOP),
                     stats.at<int>(best, cv::CC_STAT_WIDTH),
                     stats.at<int>(best, cv::CC_STAT_HEIGHT));
  cv::Mat padded;
  cv::copyMakeBorder(out(box), padded, 1, 1, 1, 1, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::floodFill(padded, cv::Point(0, 0), cv::Scalar(128), nullptr, cv::Scalar(0), cv::Scalar(0), 4);
  cv::Mat filled = (padded != 128);
  filled(cv::Rect(1, 1, box.width, box.height)).copyTo(out(box));
  return out;
}

Result<Morph2D> ComputeMorph2D(const cv::Mat& binary_mask) {
  if (binary_mask.empty() || binary_mask.type() != CV_8UC1)
    return MakeError(ErrorClass::kInvalidArgument,
                     "morph2d: mask must be a non-empty 8-bit single-channel image");
  const cv::Mat sil = LargestComponentFilled(binary_mask != 0);
  const cv::Rect box = cv::boundingRect(sil);
  if (box.area() == 0)
    return MakeError(ErrorClass::kInvalidArgument,
                     "morph2d: the mask has no foreground pixel (no silhouette)");

  Morph2D m;
  m.area_px = cv::countNonZero(sil(box));

  // Sub-pixel outer contour of the blurred silhouette, on a padded crop.
  const int pad = static_cast<int>(std::ceil(4 * kContourSigmaPx)) + 2;
  cv::Mat crop;
  cv::copyMakeBorder(sil(box), crop, pad, pad, pad, pad, cv::BORDER_CONSTANT, cv::Scalar(0));
  cv::Mat field;
  crop.convertTo(field, CV_32F, 1.0 / 255.0);
  cv::GaussianBlur(field, field, cv::Size(0, 0), kContourSigmaPx, kContourSigmaPx,
                   cv::BORDER_CONSTANT);
  SubpixelContour contour = TraceIsoLine(field, cv::Point(box.x - pad, box.y - pad));

  std::vector<cv::Point2f> hull_src;
  if (contour.points.size() >= 6) {
    m.perimeter_px = contour.length;
    hull_src = std::move(contour.points);
  } else {
    // Objects thinner than the blur vanish at level 0.5: fall back to the pixel
    // boundary (crack length) and the pixel corners.
    std::vector<std::vector<cv::Point>> cs;
    cv::findContours(sil(box).clone(), cs, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_NONE, box.tl());
    for (const auto& c : cs) m.perimeter_px += cv::arcLength(c, true);
    for (int y = box.y; y < box.y + box.height; ++y)
      for (int x = box.x; x < box.x + box.width; ++x)
        if (sil.at<uchar>(y, x))
          for (float dy : {-0.5f, 0.5f})
            for (float dx : {-0.5f, 0.5f})
              hull_src.emplace_back(static_cast<float>(x) + dx, static_cast<float>(y) + dy);
    if (m.perimeter_px <= 0) m.perimeter_px = 4;  // a single pixel
  }

  std::vector<cv::Point2f> hull;
  cv::convexHull(hull_src, hull);
  // Longest Feret diameter: the farthest pair of hull vertices (O(h^2); h is a
  // few hundred for a rock silhouette).
  double best = -1;
  size_t bi = 0, bj = 0;
  for (size_t i = 0; i < hull.size(); ++i)
    for (size_t j = i + 1; j < hull.size(); ++j) {
      const double dx = hull[i].x - hull[j].x, dy = hull[i].y - hull[j].y;
      const double d2 = dx * dx + dy * dy;
      if (d2 > best) {
        best = d2;
        bi = i;
        bj = j;
      }
    }
  m.l_max_px = std::sqrt(std::max(best, 0.0));
  m.l_max_p1 = hull[bi];
  m.l_max_p2 = hull[bj];
  if (m.l_max_px > 0) {
    const double ux = (m.l_max_p2.x - m.l_max_p1.x) / m.l_max_px;
    const double uy = (m.l_max_p2.y - m.l_max_p1.y) / m.l_max_px;
    double lo = 1e300, hi = -1e300;
    for (const auto& p : hull) {
      const double s = -uy * p.x + ux * p.y;  // projection on the perpendicular
      lo = std::min(lo, s);
      hi = std::max(hi, s);
    }
    m.l_min_px = hi - lo;
    double ang = std::atan2(uy, ux) * 180.0 / std::numbers::pi;
    if (ang < 0) ang += 180.0;
    if (ang >= 180.0) ang -= 180.0;
    m.l_max_angle_deg = ang;
  }
  m.fer_2d = m.l_min_px > 0 ? m.l_max_px / m.l_min_px : 0.0;
  m.circularity = m.perimeter_px > 0
                      ? 4.0 * std::numbers::pi * m.area_px / (m.perimeter_px * m.perimeter_px)
                      : 0.0;
  return m;
}

}  // namespace aggscan
