#include "pipeline/markers/view_evidence.h"

#include <chrono>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <utility>

namespace aggscan {

cv::Mat CropPadded(const cv::Mat& m, const cv::Rect& roi) {
  const cv::Rect in = roi & cv::Rect(0, 0, m.cols, m.rows);
  if (in == roi) return m(roi).clone();
  cv::Mat out = cv::Mat::zeros(roi.size(), m.type());
  if (in.area() > 0) m(in).copyTo(out(in - roi.tl()));
  return out;
}

cv::Rect RockWindow(const cv::Mat& full_mask, int margin) {
  const cv::Rect box = cv::boundingRect(full_mask);
  // Rounded up to even: an odd frame's window may end one pixel past it.
  const int fw = (full_mask.cols + 1) & ~1, fh = (full_mask.rows + 1) & ~1;
  if (box.area() == 0) return {0, 0, fw, fh};
  const int x0 = std::max(0, (box.x - margin) & ~1), y0 = std::max(0, (box.y - margin) & ~1);
  const int x1 = std::min(fw, (box.x + box.width + margin + 1) & ~1);
  const int y1 = std::min(fh, (box.y + box.height + margin + 1) & ~1);
  return {x0, y0, x1 - x0, y1 - y0};
}

std::string EvidenceOptions::Key() const {
  std::ostringstream k;
  k.precision(17);
  k << camera.width << ' ' << camera.height << ' ' << camera.fx << ' ' << camera.fy << ' '
    << camera.cx << ' ' << camera.cy << ' ' << camera.k1 << ' ' << camera.k2 << ' ' << camera.p1
    << ' ' << camera.p2 << ' ' << camera.k3 << " |";
  for (const std::string& c : label_colors) k << ' ' << c;
  k << " |";
  for (const std::string& c : object_colors) k << ' ' << c;
  const MarkerDetectOptions& m = markers;
  k << " |";
  for (const ColorClass& c : m.colors)
    k << ' ' << c.name << ' ' << c.hue_deg << ' ' << c.hue_tol_deg;
  k << " | " << m.min_saturation << ' ' << m.min_chroma << ' ' << m.label_min_side_frac << ' '
    << m.label_max_side_frac << ' ' << m.expected_label_side_px << ' ' << m.label_min_solidity
    << ' ' << m.label_min_fill << ' ' << m.rock_clearance_px << ' ' << m.segment_min_area_frac
    << ' ' << m.marker_mask_dilate_px << ' ' << m.head_tail_min_ratio << " | "
    << rig.aruco_dictionary << ' ' << rig.aruco_size_mm;
  for (const ArucoMarker& a : rig.aruco_markers)
    k << ' ' << a.id << ' ' << a.x_mm << ' ' << a.y_mm << ' ' << a.yaw_deg;
  k << " | " << window_margin;
  return k.str();
}

bool ViewEvidenceCache::Serves(EvidenceOptions wanted) const {
  wanted.window_margin = options_.window_margin;
  return wanted.Key() == options_.Key();
}

cv::Mat ViewEvidence::FullMask() const {
  cv::Mat full = cv::Mat::zeros(frame, CV_8U);
  if (mask.empty()) return full;
  // The window may reach one pixel past an odd frame (RockWindow).
  const cv::Rect in = window & cv::Rect(0, 0, frame.width, frame.height);
  if (in.area() > 0) mask(in - window.tl()).copyTo(full(in));
  return full;
}

namespace {

ViewEvidence GatherInWindow(const cv::Mat& bgr, const cv::Mat& mask, const cv::Rect& window,
                            const EvidenceOptions& o, bool keep_colour) {
  ViewEvidence e;
  e.frame = mask.size();
  e.window = window;
  e.mask = CropPadded(mask, e.window);
  if (keep_colour) e.bgr = CropPadded(bgr, e.window);
  const auto t0 = std::chrono::steady_clock::now();
  auto m = DetectViewMarkers(bgr, mask, o.label_colors, o.object_colors, &o.camera, o.markers);
  if (m) {
    e.markers_found = true;
    e.markers = std::move(*m);
  }
  const auto t1 = std::chrono::steady_clock::now();
  e.markers_s = std::chrono::duration<double>(t1 - t0).count();
  if (o.want_aruco()) {
    auto a = DetectArucoMarkers(bgr, mask, o.rig, &o.camera);
    if (a) {
      e.aruco_found = true;
      e.aruco = std::move(*a);
    }
    e.aruco_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
  }
  return e;
}

}  // namespace

ViewEvidence GatherViewEvidence(const cv::Mat& bgr, const cv::Mat& mask, const EvidenceOptions& o,
                                bool keep_colour) {
  return GatherInWindow(bgr, mask, RockWindow(mask, o.window_margin), o, keep_colour);
}

ViewEvidenceCache::ViewEvidenceCache(EvidenceOptions options, size_t colour_budget_bytes)
    : options_(std::move(options)), colour_budget_(colour_budget_bytes) {}

void ViewEvidenceCache::Add(const std::string& image, const cv::Mat& bgr, const cv::Mat& mask) {
  if (bgr.empty() || mask.empty() || bgr.size() != mask.size()) return;
  bool keep_colour = false;
  const cv::Rect window = RockWindow(mask, options_.window_margin);
  {
    std::lock_guard<std::mutex> l(mu_);
    if (by_image_.count(image)) return;
    const size_t colour = static_cast<size_t>(window.area()) * bgr.elemSize();
    keep_colour = colour_bytes_ + colour <= colour_budget_;
    if (keep_colour) colour_bytes_ += colour;  // reserved before the detection, outside the lock
  }
  auto e = std::make_shared<const ViewEvidence>(
      GatherInWindow(bgr, mask, window, options_, keep_colour));
  std::lock_guard<std::mutex> l(mu_);
  auto [it, inserted] = by_image_.emplace(image, e);
  if (!inserted) {
    // Two stages raced on the view: the first one's is kept.
    if (keep_colour) colour_bytes_ -= e->bgr.total() * e->bgr.elemSize();
    return;
  }
  bytes_ += e->bytes();
}

std::shared_ptr<const ViewEvidence> ViewEvidenceCache::Find(const std::string& image) const {
  std::lock_guard<std::mutex> l(mu_);
  auto it = by_image_.find(image);
  return it == by_image_.end() ? nullptr : it->second;
}

size_t ViewEvidenceCache::views() const {
  std::lock_guard<std::mutex> l(mu_);
  return by_image_.size();
}

size_t ViewEvidenceCache::bytes() const {
  std::lock_guard<std::mutex> l(mu_);
  return bytes_;
}

}  // namespace aggscan
