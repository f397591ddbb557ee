#include "pipeline/mask.h"

#include <algorithm>
#include <cmath>

#include <opencv2/imgproc.hpp>

#include "pipeline/morph2d.h"

namespace aggscan {
namespace {

cv::Mat Disk(int r) { return cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(2 * r + 1, 2 * r + 1)); }

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

cv::Mat Chroma(const cv::Mat& lab) {
  cv::Mat ch[3];
  cv::split(lab, ch);
  cv::Mat c;
  cv::magnitude(ch[1], ch[2], c);
  return c;
}

}  // namespace

cv::Mat TextureMap(const cv::Mat& bgr, const MaskOptions& o) {
  // Local RMS of the high-pass of log brightness: the rock is textured, the
  // table, disc and shadow are smooth. Albedo texture is multiplicative, so in
  // the log domain it has the same strength on the lit and the shaded side; the
  // high-pass (image minus its Gaussian blur) is blind to linear ramps such as a
  // shadow's penumbra.
  cv::Mat gray, logi;
  cv::cvtColor(bgr, gray, cv::COLOR_BGR2GRAY);
  gray.convertTo(logi, CV_32F);
  cv::GaussianBlur(logi, logi, cv::Size(0, 0), 0.7);
  cv::log(logi + 8.0, logi);
  cv::Mat low;
  cv::GaussianBlur(logi, low, cv::Size(0, 0), o.texture_sigma);
  cv::Mat hp = logi - low;
  cv::Mat energy;
  cv::GaussianBlur(hp.mul(hp), energy, cv::Size(0, 0), o.texture_sigma);
  cv::sqrt(energy, energy);
  return energy;
}

namespace {

// Coarse rock mask at the working resolution (0/255), holes filled.
cv::Mat CoarseMask(const cv::Mat& small_bgr, const MaskOptions& o) {
  const cv::Mat lab = ToLab(small_bgr, 0.8);
  cv::Mat ch[3];
  cv::split(lab, ch);
  cv::Mat chroma;
  cv::magnitude(ch[1], ch[2], chroma);

  const cv::Mat sd = TextureMap(small_bgr, o);
  const cv::Mat saturated = chroma > o.saturated_chroma;
  cv::Mat evidence = ((sd > o.texture_threshold) | (chroma > o.chroma_threshold)) & ~saturated;
  cv::morphologyEx(evidence, evidence, cv::MORPH_OPEN, Disk(o.open_radius));
  cv::morphologyEx(evidence, evidence, cv::MORPH_CLOSE, Disk(o.close_radius));
  return LargestComponentFilled(evidence);
}

// Saturated blobs (object markers crossing the silhouette border) whose rim is
// mostly rock join the rock; labels lying on the disc touch it little or not at all.
void AttachSaturatedBlobs(const cv::Mat& saturated, double touch_fraction, cv::Mat& mask) {
  cv::Mat labels, stats, centroids;
  const int n = cv::connectedComponentsWithStats(saturated, labels, stats, centroids, 8, CV_32S);
  const cv::Mat k = Disk(2);
  for (int i = 1; i < n; ++i) {
    cv::Rect box(stats.at<int>(i, cv::CC_STAT_LEFT), stats.at<int>(i, cv::CC_STAT_TOP),
                 stats.at<int>(i, cv::CC_STAT_WIDTH), stats.at<int>(i, cv::CC_STAT_HEIGHT));
    box = (box + cv::Size(6, 6) - cv::Point(3, 3)) & cv::Rect(0, 0, mask.cols, mask.rows);
    const cv::Mat blob = labels(box) == i;
    if (cv::countNonZero(mask(box) & blob) == cv::countNonZero(blob)) continue;  // already inside
    cv::Mat grown;
    cv::dilate(blob, grown, k);
    const cv::Mat rim = grown & ~blob;
    const double rim_n = cv::countNonZero(rim);
    if (rim_n > 0 && cv::countNonZero(rim & mask(box)) >= touch_fraction * rim_n) mask(box).setTo(255, blob);
  }
}

}  // namespace

cv::Mat ComputeForegroundMask(const cv::Mat& bgr, const MaskOptions& o) {
  CV_Assert(bgr.type() == CV_8UC3 && !bgr.empty());
  const int long_side = std::max(bgr.cols, bgr.rows);
  const double scale = (o.work_long_side > 0 && long_side > o.work_long_side)
                           ? static_cast<double>(o.work_long_side) / long_side
                           : 1.0;
  cv::Mat small = bgr;
  if (scale < 1.0) cv::resize(bgr, small, cv::Size(), scale, scale, cv::INTER_AREA);
  const cv::Mat coarse = CoarseMask(small, o);
  cv::Mat out = cv::Mat::zeros(bgr.size(), CV_8UC1);
  const cv::Rect cbox = cv::boundingRect(coarse);
  if (cbox.area() == 0) return out;

  // Full-resolution region of interest around the coarse silhouette.
  const int margin = o.band_outer_px + static_cast<int>(std::ceil(3 * o.local_sigma_px)) + static_cast<int>(std::ceil(2 / scale));
  cv::Rect roi(cvFloor(cbox.x / scale) - margin, cvFloor(cbox.y / scale) - margin,
               cvCeil(cbox.width / scale) + 2 * margin, cvCeil(cbox.height / scale) + 2 * margin);
  roi &= cv::Rect(0, 0, bgr.cols, bgr.rows);

  cv::Mat coarse_full;
  if (scale < 1.0) {
    // Map the ROI back onto the coarse grid and interpolate the 0/255 mask.
    cv::Mat up;
    cv::resize(coarse, up, bgr.size(), 0, 0, cv::INTER_LINEAR);
    coarse_full = up(roi) > 127;
  } else {
    coarse_full = coarse(roi).clone();
  }

  // Per-pixel features for the band decision: Lab (a, b weighted) and texture.
  cv::Mat lab = ToLab(bgr(roi), 1.0);
  {
    MaskOptions fine = o;
    fine.texture_sigma = o.refine_texture_sigma_px;
    cv::Mat tex = TextureMap(bgr(roi), fine) * o.texture_weight;
    cv::Mat ch[3];
    cv::split(lab, ch);
    ch[1] *= o.chroma_weight;
    ch[2] *= o.chroma_weight;
    cv::merge(std::vector<cv::Mat>{ch[0], ch[1], ch[2], tex}, lab);
  }
  const cv::Mat chroma = Chroma(ToLab(bgr(roi), 1.0));
  const cv::Mat saturated = chroma > o.saturated_chroma;

  cv::Mat sure_fg, grown;
  cv::erode(coarse_full, sure_fg, Disk(o.band_inner_px));
  cv::dilate(coarse_full, grown, Disk(o.band_outer_px));
  cv::Mat sure_bg = ~grown;
  const cv::Mat band_mask = grown & ~sure_fg;
  sure_fg &= ~saturated;
  sure_bg &= ~saturated;

  // Local mean colour of each side (normalised convolution).
  auto local_mean = [&](const cv::Mat& sel) {
    cv::Mat w;
    sel.convertTo(w, CV_32F, 1.0 / 255.0);
    cv::Mat num;
    cv::Mat w4;
    cv::merge(std::vector<cv::Mat>{w, w, w, w}, w4);
    cv::GaussianBlur(lab.mul(w4), num, cv::Size(0, 0), o.local_sigma_px);
    cv::Mat den;
    cv::GaussianBlur(w, den, cv::Size(0, 0), o.local_sigma_px);
    den = cv::max(den, 1e-4);
    cv::Mat den4;
    cv::merge(std::vector<cv::Mat>{den, den, den, den}, den4);
    return cv::Mat(num / den4);
  };
  const cv::Mat mfg = local_mean(sure_fg), mbg = local_mean(sure_bg);

  cv::Mat refined = sure_fg.clone();
  for (int y = 0; y < roi.height; ++y) {
    const uchar* b = band_mask.ptr<uchar>(y);
    const cv::Vec4f* px = lab.ptr<cv::Vec4f>(y);
    const cv::Vec4f* f = mfg.ptr<cv::Vec4f>(y);
    const cv::Vec4f* g = mbg.ptr<cv::Vec4f>(y);
    uchar* r = refined.ptr<uchar>(y);
    for (int x = 0; x < roi.width; ++x) {
      if (!b[x]) continue;
      const cv::Vec4f df = px[x] - f[x], dg = px[x] - g[x];
      if (df.dot(df) < dg.dot(dg)) r[x] = 255;
    }
  }
  // Saturated pixels (labels, markers) are decided below by their surroundings,
  // never by colour distance: a yellow label is nearer to brown than to grey.
  refined &= ~saturated;
  cv::morphologyEx(refined, refined, cv::MORPH_OPEN, Disk(1));
  cv::morphologyEx(refined, refined, cv::MORPH_CLOSE, Disk(2));
  refined = LargestComponentFilled(refined);
  AttachSaturatedBlobs(saturated, o.marker_touch_fraction, refined);
  refined = LargestComponentFilled(refined);
  refined.copyTo(out(roi));
  return out;
}

}  // namespace aggscan
