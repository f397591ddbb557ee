#include "pipeline/masks/mask.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "pipeline/masks/mask_graphcut.h"
#include "pipeline/morph/morph2d.h"

namespace aggscan {
namespace {

cv::Mat Disk(int r) {
  return cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 1, 2 * r + 1));
}

// Seeds OpenCV's per-thread RNG for one scope and restores it afterwards:
// cv::kmeans and cv::grabCut draw their initial centres from it, and a mask
// must not depend on what ran on the thread before.
class ScopedRngSeed {
 public:
  explicit ScopedRngSeed(uint64_t seed) : saved_(cv::theRNG().state) { cv::theRNG().state = seed; }
  ~ScopedRngSeed() { cv::theRNG().state = saved_; }
  ScopedRngSeed(const ScopedRngSeed&) = delete;
  ScopedRngSeed& operator=(const ScopedRngSeed&) = delete;

 private:
  uint64_t saved_;
};

// BGR 8-bit -> Lab float (L 0..100, a/b about -100..100), lightly smoothed so
// that sensor noise and JPEG blocks do not read as texture or colour.
cv::Mat ToLab(const cv::Mat& bgr, double smooth_sigma) {
  cv::Mat f;
  bgr.convertTo(f, CV_32FC3, 1.0 / 255.0);
  if (smooth_sigma > 0) cv::GaussianBlur(f, f, cv::Size(0, 0), smooth_sigma);
  cv::Mat lab;
  cv::cvtColor(f, lab, cv::COLOR_BGR2Lab);
  return lab;
}

// Value at quantile q (0..1) of the CV_32F pixels of `m` selected by `sel`.
float Quantile(const cv::Mat& m, const cv::Mat& sel, double q) {
  std::vector<float> v;
  v.reserve(static_cast<size_t>(cv::countNonZero(sel)));
  for (int y = 0; y < m.rows; ++y) {
    const float* p = m.ptr<float>(y);
    const uchar* s = sel.ptr<uchar>(y);
    for (int x = 0; x < m.cols; ++x)
      if (s[x]) v.push_back(p[x]);
  }
  if (v.empty()) return 0.0f;
  const auto k = static_cast<size_t>(q * static_cast<double>(v.size() - 1));
  std::nth_element(v.begin(), v.begin() + static_cast<long>(k), v.end());
  return v[k];
}

// One colour of the background: a k-means centre of the border pixels and how
// far its members stray from its hue.
struct Cluster {
  cv::Vec3f mean;    // BGR, 8-bit levels (after light smoothing)
  float norm = 0;    // |mean|
  float spread = 0;  // 90th percentile of the members' chromatic distortion / brightness
};

// Horprasert-style decomposition of pixel c against background colour mu:
// brightness factor a = c.mu/|mu|^2 (shading, shadow) and chromatic distortion
// |c - a mu|. Outside [shade_min, shade_max] the factor is clamped, so a pixel
// much darker or brighter than any background colour is far from it too.
// Returned in units of the cluster's own spread plus sensor noise.
inline float ClusterDistance(const cv::Vec3f& c, const Cluster& k, float lo, float hi,
                             float noise) {
  const float a = std::clamp(c.dot(k.mean) / (k.norm * k.norm), lo, hi);
  const cv::Vec3f d = c - a * k.mean;
  return std::sqrt(d.dot(d)) / (a * k.norm * k.spread + noise);
}

std::vector<Cluster> FitBackground(const cv::Mat& img32, const cv::Mat& sample,
                                   const MaskOptions& o) {
  constexpr int kMaxSamples = 6000;
  const int n = cv::countNonZero(sample);
  const int step = std::max(1, n / kMaxSamples);
  std::vector<cv::Vec3f> pts;
  pts.reserve(static_cast<size_t>(n / step) + 1);
  int i = 0;
  for (int y = 0; y < img32.rows; ++y) {
    const cv::Vec3f* p = img32.ptr<cv::Vec3f>(y);
    const uchar* s = sample.ptr<uchar>(y);
    for (int x = 0; x < img32.cols; ++x)
      if (s[x] && i++ % step == 0) pts.push_back(p[x]);
  }
  const int k = std::min<int>(std::max(1, o.background_clusters), static_cast<int>(pts.size()));
  std::vector<Cluster> out;
  if (k == 0) return out;
  const cv::Mat data(static_cast<int>(pts.size()), 3, CV_32F, pts.data());
  cv::Mat labels, centers;
  {
    ScopedRngSeed seed(0x6167677363616eULL);
    cv::kmeans(data, k, labels,
               cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 20, 0.5), 2,
               cv::KMEANS_PP_CENTERS, centers);
  }
  std::vector<std::vector<float>> nd(static_cast<size_t>(k));
  for (int j = 0; j < k; ++j) {
    Cluster c;
    c.mean = centers.at<cv::Vec3f>(j);
    c.norm = std::max(1.0f, static_cast<float>(cv::norm(c.mean)));
    out.push_back(c);
  }
  for (size_t j = 0; j < pts.size(); ++j) {
    const Cluster& c = out[static_cast<size_t>(labels.at<int>(static_cast<int>(j)))];
    const float a = std::max(1e-3f, pts[j].dot(c.mean) / (c.norm * c.norm));
    const cv::Vec3f d = pts[j] - a * c.mean;
    nd[static_cast<size_t>(labels.at<int>(static_cast<int>(j)))].push_back(std::sqrt(d.dot(d)) /
                                                                           (a * c.norm));
  }
  for (int j = 0; j < k; ++j) {
    auto& v = nd[static_cast<size_t>(j)];
    float p90 = 0;
    if (!v.empty()) {
      const auto q = static_cast<size_t>(0.9 * static_cast<double>(v.size() - 1));
      std::nth_element(v.begin(), v.begin() + static_cast<long>(q), v.end());
      p90 = v[q];
    }
    out[static_cast<size_t>(j)].spread = std::max(p90, 0.01f);  // ~0.6 deg of hue at least
  }
  return out;
}

cv::Mat ColorDistanceMap(const cv::Mat& img32, const std::vector<Cluster>& bg,
                         const MaskOptions& o) {
  cv::Mat out(img32.size(), CV_32F, cv::Scalar(1e6f));
  const auto lo = static_cast<float>(o.shade_min), hi = static_cast<float>(o.shade_max);
  const auto noise = static_cast<float>(o.noise_levels);
  for (int y = 0; y < img32.rows; ++y) {
    const cv::Vec3f* p = img32.ptr<cv::Vec3f>(y);
    float* d = out.ptr<float>(y);
    for (int x = 0; x < img32.cols; ++x) {
      float best = d[x];
      for (const Cluster& k : bg) best = std::min(best, ClusterDistance(p[x], k, lo, hi, noise));
      d[x] = best;
    }
  }
  return out;
}

// The empty turntable's photo brought to the lighting of `img32` (both
// CV_32FC3, smoothed alike): a gain per channel, the median ratio over the
// border strip, where the rock never is. Outdoors the sun and clouds change
// the light between the empty photos and the rock's; a camera with locked
// exposure sees that as a scale per channel.
cv::Mat MatchLighting(const cv::Mat& img32, const cv::Mat& empty32, const cv::Mat& strip) {
  std::vector<float> r[3];
  for (int y = 0; y < img32.rows; ++y) {
    const cv::Vec3f* p = img32.ptr<cv::Vec3f>(y);
    const cv::Vec3f* e = empty32.ptr<cv::Vec3f>(y);
    const uchar* s = strip.ptr<uchar>(y);
    for (int x = 0; x < img32.cols; ++x)
      if (s[x])
        for (int c = 0; c < 3; ++c) r[c].push_back((p[x][c] + 1.0f) / (e[x][c] + 1.0f));
  }
  cv::Scalar gain(1, 1, 1);
  for (int c = 0; c < 3; ++c) {
    if (r[c].empty()) continue;
    auto mid = r[c].begin() + static_cast<long>(r[c].size() / 2);
    std::nth_element(r[c].begin(), mid, r[c].end());
    gain[c] = std::clamp(static_cast<double>(*mid), 0.25, 4.0);
  }
  cv::Mat out;
  cv::multiply(empty32, gain, out);
  return out;
}

// ClusterDistance against the empty turntable pixel by pixel: each pixel is
// explained by the colour the same pixel had with no rock, scaled by a
// brightness factor (the rock's shadow darkens it; light it reflects
// brightens the disc a little). `spread` is the chromatic noise of the pair,
// measured on the border strip.
cv::Mat ReferenceDistanceMap(const cv::Mat& img32, const cv::Mat& empty32, const cv::Mat& strip,
                             const MaskOptions& o) {
  const auto lo = static_cast<float>(o.shade_min), hi = static_cast<float>(o.reference_shade_max);
  const auto noise = static_cast<float>(o.noise_levels);
  cv::Mat rel(img32.size(), CV_32F), out(img32.size(), CV_32F);
  for (int y = 0; y < img32.rows; ++y) {
    const cv::Vec3f* p = img32.ptr<cv::Vec3f>(y);
    const cv::Vec3f* e = empty32.ptr<cv::Vec3f>(y);
    float* r = rel.ptr<float>(y);
    for (int x = 0; x < img32.cols; ++x) {
      const float n2 = std::max(1.0f, e[x].dot(e[x]));
      const float a = std::max(1e-3f, p[x].dot(e[x]) / n2);
      const cv::Vec3f d = p[x] - a * e[x];
      r[x] = std::sqrt(d.dot(d)) / (a * std::sqrt(n2));
    }
  }
  const float spread = std::max(0.01f, Quantile(rel, strip, 0.9));
  for (int y = 0; y < img32.rows; ++y) {
    const cv::Vec3f* p = img32.ptr<cv::Vec3f>(y);
    const cv::Vec3f* e = empty32.ptr<cv::Vec3f>(y);
    float* d = out.ptr<float>(y);
    for (int x = 0; x < img32.cols; ++x) {
      const float n = std::max(1.0f, std::sqrt(e[x].dot(e[x])));
      const float a = std::clamp(p[x].dot(e[x]) / (n * n), lo, hi);
      const cv::Vec3f r = p[x] - a * e[x];
      d[x] = std::sqrt(r.dot(r)) / (a * n * spread + noise);
    }
  }
  return out;
}

cv::Mat ToFloatSmoothed(const cv::Mat& bgr) {
  cv::Mat f;
  bgr.convertTo(f, CV_32FC3);
  cv::GaussianBlur(f, f, cv::Size(0, 0), 0.8);
  return f;
}

// Everything the steps share, at the working resolution.
struct Scene {
  double scale = 1.0;               // working / full resolution
  cv::Mat small;                    // BGR at the working resolution
  cv::Mat ab;                       // CV_32FC2, Lab a,b of `small` (lightly smoothed)
  std::vector<Cluster> background;  // border colour model
  cv::Mat color_distance;           // CV_32F, ColorDistanceMap of `small`
  cv::Vec2f rock_ab{0, 0};          // median Lab a,b of the rock's first estimate
  cv::Mat paint;    // 0/255: unexplained and far from the rock's colour (labels, markers)
  cv::Mat texture;  // CV_32F, TextureMap of `small` (against `empty` when there is one)
  cv::Mat empty;    // CV_32FC3, the empty turntable at this view, lighting matched (or empty)
};

// Hysteresis (0/255): the 8-connected regions of `strong | weak` that hold a
// `strong` pixel.
cv::Mat Hysteresis(const cv::Mat& strong, const cv::Mat& weak) {
  cv::Mat labels;
  const int n = cv::connectedComponents(strong | weak, labels, 8, CV_32S);
  std::vector<uchar> keep(static_cast<size_t>(n), 0);
  for (int y = 0; y < labels.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    const uchar* st = strong.ptr<uchar>(y);
    for (int x = 0; x < labels.cols; ++x)
      if (st[x]) keep[static_cast<size_t>(l[x])] = 255;
  }
  keep[0] = 0;
  cv::Mat out(strong.size(), CV_8UC1);
  for (int y = 0; y < labels.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    uchar* po = out.ptr<uchar>(y);
    for (int x = 0; x < labels.cols; ++x) po[x] = keep[static_cast<size_t>(l[x])];
  }
  return out;
}

// The border strip's width (px) at this size.
int BorderWidth(cv::Size size, const MaskOptions& o) {
  return std::max(
      2, static_cast<int>(std::lround(o.border_fraction * std::min(size.width, size.height))));
}

// The strip's four sides, apart: top and bottom whole, left and right
// between them. Empty when the strip would fill the frame.
std::vector<cv::Rect> BorderSides(cv::Size size, const MaskOptions& o) {
  const int b = BorderWidth(size, o), w = size.width, h = size.height;
  if (2 * b >= std::min(w, h)) return {};
  return {cv::Rect(0, 0, w, b), cv::Rect(0, h - b, w, b), cv::Rect(0, b, b, h - 2 * b),
          cv::Rect(w - b, b, b, h - 2 * b)};
}

cv::Mat BorderStrip(cv::Size size, const MaskOptions& o) {
  const int b = BorderWidth(size, o);
  cv::Mat strip(size, CV_8UC1, cv::Scalar(255));
  strip(cv::Rect(b, b, std::max(0, size.width - 2 * b), std::max(0, size.height - 2 * b))).setTo(0);
  return strip;
}

// A quantile of `m` on the border strip, side by side: the median of the four
// sides' values. A busy background raises all four; the disc's rim or a label
// crossing one side of the frame (a camera walked round the rock, closer or
// higher than the tripod) raises that side's alone, and must not lift the bar
// above the rock.
float StripQuantile(const cv::Mat& m, const MaskOptions& o, double q) {
  const std::vector<cv::Rect> sides = BorderSides(m.size(), o);
  if (sides.empty()) return Quantile(m, BorderStrip(m.size(), o), q);
  std::array<float, 4> v{};
  for (size_t i = 0; i < sides.size(); ++i) {
    cv::Mat sel = cv::Mat::zeros(m.size(), CV_8UC1);
    sel(sides[i]).setTo(255);
    v[i] = Quantile(m, sel, q);
  }
  std::sort(v.begin(), v.end());
  return 0.5f * (v[1] + v[2]);
}

cv::Mat AbOf(const cv::Mat& bgr, double smooth_sigma) {
  const cv::Mat lab = ToLab(bgr, smooth_sigma);
  cv::Mat ab;
  const int from_to[] = {1, 0, 2, 1};
  ab.create(lab.size(), CV_32FC2);
  cv::mixChannels(&lab, 1, &ab, 1, from_to, 2);
  return ab;
}

// Pixels whose a,b lie farther than saturated_chroma from the rock's median
// colour and that the background does not explain: label and marker paint.
// With hysteresis: a connected region farther than half that, holding such a
// pixel, is paint too, so the blurred fringe of a label (a mixture of paint and
// disc) goes with the label instead of bridging it to the rock.
cv::Mat PaintMap(const cv::Mat& ab, const cv::Mat& color_distance, cv::Vec2f rock_ab,
                 const MaskOptions& o) {
  cv::Mat d = ab - cv::Scalar(rock_ab[0], rock_ab[1]);
  cv::Mat ch[2];
  cv::split(d, ch);
  cv::Mat mag;
  cv::magnitude(ch[0], ch[1], mag);
  const cv::Mat unexplained = color_distance > o.color_threshold;
  const cv::Mat strong = (mag > o.saturated_chroma) & unexplained;
  const cv::Mat weak = (mag > 0.5 * o.saturated_chroma) & unexplained;
  return Hysteresis(strong, weak);
}

// The border strip without the places where an object crosses one side of
// the frame (a figure's head at the top edge, a rock framed tightly by a
// walked camera): pixels of a side that the colours of the other three sides
// do not explain, where they are a minority of that side. A background that
// changes along one side (the table far, the disc near) is seen across by
// the sides that meet it, and stays. Without these pixels the object's
// colours do not join the background model.
cv::Mat StripWithoutCrossings(const cv::Mat& f, const cv::Mat& strip, const MaskOptions& o) {
  constexpr double kMaxCrossing = 0.35;  // of a side's pixels: more is that side's background
  cv::Mat out = strip.clone();
  for (const cv::Rect& side : BorderSides(f.size(), o)) {
    cv::Mat others = strip.clone();
    others(side).setTo(0);
    const std::vector<Cluster> bg = FitBackground(f, others, o);
    const cv::Mat foreign = ColorDistanceMap(f(side), bg, o) > o.color_threshold;
    const int n = cv::countNonZero(foreign);
    if (n > 0 && n <= kMaxCrossing * side.area()) out(side).setTo(0, foreign);
  }
  return out;
}

Scene PrepareScene(const cv::Mat& bgr, const cv::Mat& empty, const MaskOptions& o) {
  Scene s;
  const int long_side = std::max(bgr.cols, bgr.rows);
  s.scale = (o.work_long_side > 0 && long_side > o.work_long_side)
                ? static_cast<double>(o.work_long_side) / long_side
                : 1.0;
  s.small = bgr;
  if (s.scale < 1.0) cv::resize(bgr, s.small, cv::Size(), s.scale, s.scale, cv::INTER_AREA);
  const cv::Mat f = ToFloatSmoothed(s.small);
  const cv::Mat strip = BorderStrip(f.size(), o);
  s.background = FitBackground(f, empty.empty() ? StripWithoutCrossings(f, strip, o) : strip, o);
  s.ab = AbOf(s.small, 0.8);
  if (!empty.empty()) {
    cv::Mat small_empty = empty;
    if (s.scale < 1.0) cv::resize(empty, small_empty, s.small.size(), 0, 0, cv::INTER_AREA);
    s.empty = MatchLighting(f, ToFloatSmoothed(small_empty), strip);
    s.color_distance = ReferenceDistanceMap(f, s.empty, strip, o);
    s.texture = TextureMap(s.small, o, s.empty);
  } else {
    s.color_distance = ColorDistanceMap(f, s.background, o);
    s.texture = TextureMap(s.small, o);
  }
  return s;
}

// The rock's typical colour from a first estimate of it (0/255, working
// resolution), and the paint map that follows from it.
void SetRockColor(Scene& s, const cv::Mat& rock, const MaskOptions& o) {
  cv::Mat core;
  cv::erode(rock, core, Disk(2));
  if (cv::countNonZero(core) == 0) core = rock;
  cv::Mat ch[2];
  cv::split(s.ab, ch);
  s.rock_ab = cv::countNonZero(core) > 0
                  ? cv::Vec2f(Quantile(ch[0], core, 0.5), Quantile(ch[1], core, 0.5))
                  : cv::Vec2f(0, 0);
  s.paint = PaintMap(s.ab, s.color_distance, s.rock_ab, o);
}

// The component of `evidence` that is the rock, holes filled. A rock's
// silhouette is compact (area over convex-hull area, the solidity, 0.8-1);
// the other things that can survive the evidence steps are not: the shaded
// side of the disc is a long thin arc (solidity ~0.1-0.2) and, under a small
// rock, can be larger than it. So the largest component wins only among the
// compact ones; a non-compact one counts with its area scaled by solidity^2.
cv::Mat RockComponentFilled(const cv::Mat& evidence) {
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(evidence, labels, stats, centroids, 8, CV_32S);
  if (n <= 2) return LargestComponentFilled(evidence);
  int max_area = 0;
  for (int i = 1; i < n; ++i) max_area = std::max(max_area, stats.at<int>(i, cv::CC_STAT_AREA));
  int best = -1;
  double best_score = -1;
  for (int i = 1; i < n; ++i) {
    const int area = stats.at<int>(i, cv::CC_STAT_AREA);
    if (area < 0.05 * max_area) continue;
    const cv::Rect box(stats.at<int>(i, cv::CC_STAT_LEFT), stats.at<int>(i, cv::CC_STAT_TOP),
                       stats.at<int>(i, cv::CC_STAT_WIDTH), stats.at<int>(i, cv::CC_STAT_HEIGHT));
    std::vector<std::vector<cv::Point>> contours;
    cv::findContours(labels(box) == i, contours, cv::RETR_EXTERNAL, cv::CHAIN_APPROX_SIMPLE);
    std::vector<cv::Point> all;
    for (const auto& c : contours) all.insert(all.end(), c.begin(), c.end());
    std::vector<cv::Point> hull;
    if (all.size() >= 3) cv::convexHull(all, hull);
    const double hull_area = hull.size() >= 3 ? cv::contourArea(hull) : 0.0;
    const double solidity = hull_area > 0 ? std::min(1.0, area / hull_area) : 1.0;
    const double score = solidity >= 0.5 ? area : area * solidity * solidity;
    if (score > best_score) best_score = score, best = i;
  }
  return LargestComponentFilled(labels == best);
}

cv::Mat CleanEvidence(cv::Mat evidence, const MaskOptions& o) {
  cv::morphologyEx(evidence, evidence, cv::MORPH_OPEN, Disk(o.open_radius));
  cv::morphologyEx(evidence, evidence, cv::MORPH_CLOSE, Disk(o.close_radius));
  return RockComponentFilled(evidence);
}

// Coarse rock mask at the working resolution (0/255), holes filled.
cv::Mat CoarseMask(Scene& s, const MaskOptions& o) {
  const cv::Mat& tex = s.texture;
  // A busy background (cloth, wood grain) raises the bar until the border
  // itself is not "textured"; the rig's plain table leaves it at the floor.
  const double tex_threshold =
      std::max(o.texture_threshold, o.texture_border_factor * StripQuantile(tex, o, 0.99));
  cv::Mat evidence = (tex > tex_threshold) | (s.color_distance > o.color_threshold);
  // A busy background (stone2: a patterned cloth) widens its colour clusters,
  // which shrinks every distance measured in their spread: the rock may lie
  // clearly apart from the border's colours and still stay under
  // color_threshold but for a few pixels. Regions above a lower threshold
  // join where they hold such a pixel (hysteresis, as in Canny's edge linking);
  // the lower threshold never drops into the border's own distances.
  const double weak_threshold =
      std::max(o.color_weak_ratio * o.color_threshold,
               o.color_border_factor * StripQuantile(s.color_distance, o, 0.99));
  if (weak_threshold < o.color_threshold)
    evidence = Hysteresis(evidence, s.color_distance > weak_threshold);
  // First estimate with everything, for the rock's colour. The graph cut takes
  // it as it is (paint is neutral there); the other refinements want the paint
  // set aside (a label touching the rock must not join it) and re-attach
  // markers by their rim.
  cv::Mat all = CleanEvidence(evidence, o);
  SetRockColor(s, all, o);
  if (o.refine == MaskRefine::kGraphCut) return all;
  return CleanEvidence(evidence & ~s.paint, o);
}

// Paint blobs as thick as a colour label (0/255): the study's labels are
// 20 mm squares, the object markers 4 mm wide strokes. Thickness is twice the
// largest inscribed radius; the reference is the thickest blob clear of the
// rock (`seed`, working resolution), which can only be a label, and a blob at
// least label_thickness of it is a label too. Nothing is thick when no blob
// stands clear of the rock.
cv::Mat ThickPaint(const cv::Mat& paint, const cv::Mat& seed, const MaskOptions& o) {
  cv::Mat out = cv::Mat::zeros(paint.size(), CV_8UC1);
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(paint, labels, stats, centroids, 8, CV_32S);
  if (n <= 1) return out;
  cv::Mat dist, near_rock;
  cv::distanceTransform(paint, dist, cv::DIST_L2, 3);
  cv::dilate(seed, near_rock, Disk(3));
  std::vector<float> radius(static_cast<size_t>(n), 0.0f);
  std::vector<uchar> touches(static_cast<size_t>(n), 0);
  for (int y = 0; y < labels.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    const float* d = dist.ptr<float>(y);
    const uchar* r = near_rock.ptr<uchar>(y);
    for (int x = 0; x < labels.cols; ++x) {
      const auto i = static_cast<size_t>(l[x]);
      radius[i] = std::max(radius[i], d[x]);
      if (r[x]) touches[i] = 1;
    }
  }
  float reference = 0;
  for (int i = 1; i < n; ++i)
    if (!touches[static_cast<size_t>(i)])
      reference = std::max(reference, radius[static_cast<size_t>(i)]);
  if (reference < 2.0f) return out;
  std::vector<uchar> thick(static_cast<size_t>(n), 0);
  for (int i = 1; i < n; ++i)
    if (radius[static_cast<size_t>(i)] >= o.label_thickness * reference)
      thick[static_cast<size_t>(i)] = 255;
  for (int y = 0; y < labels.rows; ++y) {
    const int* l = labels.ptr<int>(y);
    uchar* p = out.ptr<uchar>(y);
    for (int x = 0; x < labels.cols; ++x) p[x] = thick[static_cast<size_t>(l[x])];
  }
  return out;
}

// Graph cut (mask_graphcut.h) on the neighbourhood of `seed` (working
// resolution): sure rock well inside, sure background well outside and on the
// paint outside the seed (labels), the band between left to the colour and
// texture models and the contrast-sensitive smoothness term.
cv::Mat GraphCutRefine(const Scene& s, const cv::Mat& seed, const MaskOptions& o) {
  const cv::Rect box = cv::boundingRect(seed);
  if (box.area() == 0) return seed.clone();
  const double size = std::sqrt(static_cast<double>(cv::countNonZero(seed)));
  const int r = std::max(2, static_cast<int>(std::lround(o.graphcut_band * size)));
  const int margin = 3 * r + 4;
  const cv::Rect roi =
      cv::Rect(box.x - margin, box.y - margin, box.width + 2 * margin, box.height + 2 * margin) &
      cv::Rect(0, 0, seed.cols, seed.rows);
  const cv::Mat m = seed(roi);
  cv::Mat inner, outer;
  cv::erode(m, inner, Disk(r));
  cv::dilate(m, outer, Disk(r));
  cv::Mat gc(m.size(), CV_8UC1, cv::Scalar(cv::GC_BGD));
  gc.setTo(cv::GC_PR_BGD, outer);
  gc.setTo(cv::GC_PR_FGD, m);
  gc.setTo(cv::GC_FGD, inner);
  // Paint (labels, markers) within reach of the seed is left to the
  // smoothness term: the cheaper outline takes a label the rock touches out
  // (cut along the occlusion edge) and a marker running to the silhouette in
  // (cut along the silhouette). Paint in the sure background stays there.
  cv::Mat neutral, thick = ThickPaint(s.paint, seed, o)(roi);
  cv::dilate(s.paint(roi) & ~thick, neutral,
             Disk(o.paint_fringe_px));  // the blurred rim of the paint is mixed colour
  neutral &= outer;
  cv::dilate(thick, thick, Disk(o.paint_fringe_px));
  gc.setTo(cv::GC_BGD, thick);
  gc.setTo(cv::GC_PR_FGD, neutral & m);
  if (cv::countNonZero(gc == cv::GC_BGD) == 0 || cv::countNonZero(gc == cv::GC_FGD) == 0)
    return seed.clone();

  const double f =
      o.refine_long_side > 0
          ? std::min(1.0, static_cast<double>(o.refine_long_side) / std::max(roi.width, roi.height))
          : 1.0;
  cv::Mat img = s.small(roi), tex = s.texture(roi);
  if (f < 1.0) {
    cv::resize(img, img, cv::Size(), f, f, cv::INTER_AREA);
    cv::resize(tex, tex, img.size(), 0, 0, cv::INTER_AREA);
    cv::resize(gc, gc, img.size(), 0, 0, cv::INTER_NEAREST);
    cv::resize(neutral, neutral, img.size(), 0, 0, cv::INTER_NEAREST);
  }
  mask_detail::GraphCutOptions g;
  g.iterations = o.graphcut_iterations;
  g.texture_weight = o.graphcut_texture_weight;
  cv::Mat fg = mask_detail::SegmentGraphCut(img, o.graphcut_texture_weight > 0 ? tex : cv::Mat(),
                                            gc, neutral, g);
  if (f < 1.0) {
    cv::resize(fg, fg, roi.size(), 0, 0, cv::INTER_LINEAR);
    fg = fg > 127;
  }
  cv::Mat out = cv::Mat::zeros(seed.size(), CV_8UC1);
  fg.copyTo(out(roi));
  return LargestComponentFilled(out);
}

// Paint blobs next to the rock: an object marker that runs to the silhouette
// edge (or wraps over it) is rock, a colour label that the rock touches or
// partly hides is not. The two differ in shape, which survives whatever the
// segmentation did around them: labels are thick (`thick`, ThickPaint at the
// working resolution, brought to this one), markers are thin strokes. A blob
// that is not thick joins the rock when at least marker_touch_fraction of its
// rim is rock; a thick one never does. (Deciding by the graph cut's labelling
// instead failed on markers lying along the silhouette: the cut, with paint
// neutral, sided with the background and left a notch that carved a groove
// into the visual hull.)
void AttachPaintBlobs(const cv::Mat& paint, const cv::Mat& thick, const MaskOptions& o,
                      cv::Mat& mask) {
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(paint, labels, stats, centroids, 8, CV_32S);
  const cv::Mat k = Disk(2);
  for (int i = 1; i < n; ++i) {
    cv::Rect box(stats.at<int>(i, cv::CC_STAT_LEFT), stats.at<int>(i, cv::CC_STAT_TOP),
                 stats.at<int>(i, cv::CC_STAT_WIDTH), stats.at<int>(i, cv::CC_STAT_HEIGHT));
    box = (box + cv::Size(6, 6) - cv::Point(3, 3)) & cv::Rect(0, 0, mask.cols, mask.rows);
    const cv::Mat blob = labels(box) == i;
    const double blob_n = cv::countNonZero(blob);
    if (cv::countNonZero(mask(box) & blob) == blob_n) continue;  // already inside
    if (!thick.empty() && cv::countNonZero(thick(box) & blob) > 0.5 * blob_n) continue;  // a label
    cv::Mat grown;
    cv::dilate(blob, grown, k);
    const cv::Mat rim = grown & ~blob;
    const double rim_n = cv::countNonZero(rim);
    if (rim_n > 0 && cv::countNonZero(rim & mask(box)) >= o.marker_touch_fraction * rim_n)
      mask(box).setTo(255, blob);
  }
}

// Full-resolution band step around `coarse_full` (ROI-sized 0/255): each band
// pixel goes to the nearer of the local rock and local background mean colours.
cv::Mat BandRefine(const cv::Mat& bgr_roi, const cv::Mat& coarse_full, const cv::Mat& saturated,
                   int inner_px, int outer_px, const MaskOptions& o) {
  cv::Mat lab = ToLab(bgr_roi, 1.0);
  {
    cv::Mat ch[3];
    cv::split(lab, ch);
    ch[1] *= o.chroma_weight;
    ch[2] *= o.chroma_weight;
    cv::merge(ch, 3, lab);
  }
  cv::Mat sure_fg, grown;
  cv::erode(coarse_full, sure_fg, Disk(inner_px));
  cv::dilate(coarse_full, grown, Disk(outer_px));
  cv::Mat sure_bg = ~grown;
  const cv::Mat band_mask = grown & ~sure_fg;
  sure_fg &= ~saturated;
  sure_bg &= ~saturated;

  // Local mean colour of each side (normalised convolution).
  auto local_mean = [&](const cv::Mat& sel) {
    cv::Mat w;
    sel.convertTo(w, CV_32F, 1.0 / 255.0);
    cv::Mat num, den;
    cv::Mat w3;
    cv::merge(std::vector<cv::Mat>{w, w, w}, w3);
    cv::GaussianBlur(lab.mul(w3), num, cv::Size(0, 0), o.local_sigma_px);
    cv::GaussianBlur(w, den, cv::Size(0, 0), o.local_sigma_px);
    den = cv::max(den, 1e-4);
    cv::Mat den3;
    cv::merge(std::vector<cv::Mat>{den, den, den}, den3);
    return cv::Mat(num / den3);
  };
  const cv::Mat mfg = local_mean(sure_fg), mbg = local_mean(sure_bg);

  cv::Mat refined = sure_fg.clone();
  for (int y = 0; y < lab.rows; ++y) {
    const uchar* b = band_mask.ptr<uchar>(y);
    const cv::Vec3f* px = lab.ptr<cv::Vec3f>(y);
    const cv::Vec3f* f = mfg.ptr<cv::Vec3f>(y);
    const cv::Vec3f* g = mbg.ptr<cv::Vec3f>(y);
    uchar* r = refined.ptr<uchar>(y);
    for (int x = 0; x < lab.cols; ++x) {
      if (!b[x]) continue;
      const cv::Vec3f df = px[x] - f[x], dg = px[x] - g[x];
      if (df.dot(df) < dg.dot(dg)) r[x] = 255;
    }
  }
  return refined;
}

// Working-resolution mask -> full-resolution mask, refined as opts say.
// `narrow`: the band after a graph cut seeded by our own coarse mask is
// graphcut_band_px wide; a rough mask from elsewhere (a network's blurred
// map) keeps the wide band of kBand.
cv::Mat FinishMask(const cv::Mat& bgr, const cv::Mat& empty, const Scene& s, cv::Mat work,
                   const MaskOptions& o, bool narrow) {
  cv::Mat out = cv::Mat::zeros(bgr.size(), CV_8UC1);
  if (o.refine == MaskRefine::kGraphCut) work = GraphCutRefine(s, work, o);
  const cv::Rect wbox = cv::boundingRect(work);
  if (wbox.area() == 0) return out;

  // Full-resolution region of interest around the silhouette.
  const double scale = s.scale;
  const int margin = o.band_outer_px + static_cast<int>(std::ceil(3 * o.local_sigma_px)) +
                     static_cast<int>(std::ceil(2 / scale));
  cv::Rect roi(cvFloor(wbox.x / scale) - margin, cvFloor(wbox.y / scale) - margin,
               cvCeil(wbox.width / scale) + 2 * margin, cvCeil(wbox.height / scale) + 2 * margin);
  roi &= cv::Rect(0, 0, bgr.cols, bgr.rows);

  cv::Mat full;
  if (scale < 1.0) {
    cv::Mat up;
    cv::resize(work, up, bgr.size(), 0, 0, cv::INTER_LINEAR);
    full = up(roi) > 127;
  } else {
    full = work(roi).clone();
  }

  // Saturated pixels the background does not explain (labels, markers), at
  // full resolution; decided by their surroundings, never by colour distance
  // (a yellow label is nearer to brown than to grey).
  cv::Mat saturated;
  {
    const cv::Mat f = ToFloatSmoothed(bgr(roi));
    cv::Mat distance;
    if (!empty.empty()) {
      // The working-resolution distance brought up: the full-resolution
      // photo's own gain is that of the working one.
      cv::resize(s.color_distance, distance, bgr.size(), 0, 0, cv::INTER_LINEAR);
      distance = distance(roi).clone();
    } else {
      distance = ColorDistanceMap(f, s.background, o);
    }
    saturated = PaintMap(AbOf(bgr(roi), 1.0), distance, s.rock_ab, o);
  }
  const bool band =
      o.refine == MaskRefine::kBand || (o.refine == MaskRefine::kGraphCut && scale < 1.0);
  const bool after_cut = narrow && o.refine == MaskRefine::kGraphCut;
  cv::Mat refined =
      band ? BandRefine(bgr(roi), full, saturated, after_cut ? o.graphcut_band_px : o.band_inner_px,
                        after_cut ? o.graphcut_band_px : o.band_outer_px, o)
           : full;
  refined &= ~saturated;
  cv::morphologyEx(refined, refined, cv::MORPH_OPEN, Disk(1));
  cv::morphologyEx(refined, refined, cv::MORPH_CLOSE, Disk(2));
  refined = LargestComponentFilled(refined);
  cv::Mat thick;  // label-thick paint, from the working resolution
  {
    const cv::Mat t = ThickPaint(s.paint, work, o);
    if (scale < 1.0) {
      cv::Mat up;
      cv::resize(t, up, bgr.size(), 0, 0, cv::INTER_NEAREST);
      thick = up(roi).clone();
    } else {
      thick = t(roi).clone();
    }
  }
  AttachPaintBlobs(saturated, thick, o, refined);
  refined = LargestComponentFilled(refined);
  refined.copyTo(out(roi));
  return out;
}

}  // namespace

cv::Mat TextureMap(const cv::Mat& bgr, const MaskOptions& o, const cv::Mat& empty32) {
  // Local RMS of the high-pass of log brightness: the rock is textured, the
  // table, disc and shadow are smooth. Albedo texture is multiplicative, so in
  // the log domain it has the same strength on the lit and the shaded side; the
  // high-pass (image minus its Gaussian blur) is blind to linear ramps such as a
  // shadow's penumbra. Against the empty turntable the log brightness is that
  // of the ratio of the two photos: the grain of a wooden disc, a rubber mat
  // or a gravel floor cancels, and so does it under the rock's shadow.
  cv::Mat gray, logi;
  cv::cvtColor(bgr, gray, cv::COLOR_BGR2GRAY);
  gray.convertTo(logi, CV_32F);
  cv::GaussianBlur(logi, logi, cv::Size(0, 0), 0.7);
  cv::log(logi + 8.0, logi);
  if (!empty32.empty()) {
    CV_Assert(empty32.type() == CV_32FC3 && empty32.size() == bgr.size());
    cv::Mat eg, loge;
    cv::cvtColor(empty32, eg, cv::COLOR_BGR2GRAY);
    cv::GaussianBlur(eg, eg, cv::Size(0, 0), 0.7);
    cv::log(eg + 8.0, loge);
    logi -= loge;
  }
  cv::Mat low;
  cv::GaussianBlur(logi, low, cv::Size(0, 0), o.texture_sigma);
  cv::Mat hp = logi - low;
  cv::Mat energy;
  cv::GaussianBlur(hp.mul(hp), energy, cv::Size(0, 0), o.texture_sigma);
  cv::sqrt(energy, energy);
  return energy;
}

cv::Mat BackgroundColorDistance(const cv::Mat& bgr, const MaskOptions& o, const cv::Mat& empty) {
  CV_Assert(bgr.type() == CV_8UC3 && !bgr.empty());
  CV_Assert(empty.empty() || (empty.type() == CV_8UC3 && empty.size() == bgr.size()));
  MaskOptions full = o;
  full.work_long_side = 0;
  return PrepareScene(bgr, empty, full).color_distance;
}

cv::Mat ComputeForegroundMask(const cv::Mat& bgr, const MaskOptions& o) {
  return ComputeForegroundMask(bgr, cv::Mat(), o);
}

cv::Mat ComputeForegroundMask(const cv::Mat& bgr, const cv::Mat& empty, const MaskOptions& o) {
  CV_Assert(bgr.type() == CV_8UC3 && !bgr.empty());
  CV_Assert(empty.empty() || (empty.type() == CV_8UC3 && empty.size() == bgr.size()));
  Scene s = PrepareScene(bgr, empty, o);
  const cv::Mat coarse = CoarseMask(s, o);
  return FinishMask(bgr, empty, s, coarse, o, /*narrow=*/true);
}

cv::Mat RefineForegroundMask(const cv::Mat& bgr, const cv::Mat& rough, const MaskOptions& o) {
  return RefineForegroundMask(bgr, cv::Mat(), rough, o);
}

cv::Mat RefineForegroundMask(const cv::Mat& bgr, const cv::Mat& empty, const cv::Mat& rough,
                             const MaskOptions& o) {
  CV_Assert(bgr.type() == CV_8UC3 && !bgr.empty() && rough.type() == CV_8UC1 && !rough.empty());
  CV_Assert(empty.empty() || (empty.type() == CV_8UC3 && empty.size() == bgr.size()));
  Scene s = PrepareScene(bgr, empty, o);
  cv::Mat work;
  if (rough.size() == s.small.size()) {
    work = rough > 127;
  } else {
    cv::resize(rough, work, s.small.size(), 0, 0, cv::INTER_LINEAR);
    work = work > 127;
  }
  work = LargestComponentFilled(work);
  SetRockColor(s, work, o);
  return FinishMask(bgr, empty, s, work, o, /*narrow=*/false);
}

}  // namespace aggscan
