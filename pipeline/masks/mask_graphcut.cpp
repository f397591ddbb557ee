#include "pipeline/masks/mask_graphcut.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <numbers>
#include <opencv2/imgproc.hpp>
#include <opencv2/imgproc/detail/gcgraph.hpp>
#include <vector>

namespace aggscan::mask_detail {
namespace {

constexpr size_t kMaxSamples = 20000;  // per side, for fitting the models

// Gaussian mixture over BGR colour, fitted by hard EM: every sample goes to its
// most likely component, each component is re-estimated from its samples.
class ColorMixture {
 public:
  // k-means start (fixed seed: the result must not depend on the thread's RNG).
  void Init(const std::vector<cv::Vec3f>& samples, int k) {
    k = std::min<int>(k, static_cast<int>(samples.size()));
    g_.clear();
    if (k <= 0) return;
    const cv::Mat data(static_cast<int>(samples.size()), 3, CV_32F,
                       const_cast<cv::Vec3f*>(samples.data()));
    cv::Mat labels, centers;
    const uint64_t saved = cv::theRNG().state;
    cv::theRNG().state = 0x6d697874757265ULL;
    cv::kmeans(data, k, labels, cv::TermCriteria(cv::TermCriteria::COUNT, 10, 0), 1,
               cv::KMEANS_PP_CENTERS, centers);
    cv::theRNG().state = saved;
    std::vector<int> assign(samples.size());
    for (size_t i = 0; i < samples.size(); ++i) assign[i] = labels.at<int>(static_cast<int>(i));
    Estimate(samples, assign, k);
  }

  void Refit(const std::vector<cv::Vec3f>& samples) {
    if (g_.empty()) return;
    std::vector<int> assign(samples.size());
    for (size_t i = 0; i < samples.size(); ++i) assign[i] = Best(samples[i]);
    Estimate(samples, assign, static_cast<int>(g_.size()));
  }

  // -log p(c) under the mixture.
  double NegLogLikelihood(const cv::Vec3f& c) const {
    double best = -1e300;
    std::array<double, 16> e{};
    const size_t n = std::min(g_.size(), e.size());
    for (size_t k = 0; k < n; ++k) {
      e[k] = LogDensity(g_[k], c);
      best = std::max(best, e[k]);
    }
    if (n == 0) return 1e3;
    double sum = 0;
    for (size_t k = 0; k < n; ++k) sum += std::exp(e[k] - best);
    return -(best + std::log(sum));
  }

  bool empty() const { return g_.empty(); }

 private:
  struct Gaussian {
    cv::Vec3d mean;
    cv::Matx33d inv_cov;
    double log_coef = 0;  // log(weight) - log det(cov)/2 - (3/2) log(2 pi)
  };

  static double LogDensity(const Gaussian& g, const cv::Vec3f& c) {
    const cv::Vec3d d(c[0] - g.mean[0], c[1] - g.mean[1], c[2] - g.mean[2]);
    return g.log_coef - 0.5 * d.dot(g.inv_cov * d);
  }

  int Best(const cv::Vec3f& c) const {
    int best = 0;
    double bv = -1e300;
    for (size_t k = 0; k < g_.size(); ++k) {
      const double v = LogDensity(g_[k], c);
      if (v > bv) bv = v, best = static_cast<int>(k);
    }
    return best;
  }

  void Estimate(const std::vector<cv::Vec3f>& samples, const std::vector<int>& assign, int k) {
    std::vector<cv::Vec3d> sum(static_cast<size_t>(k), cv::Vec3d(0, 0, 0));
    std::vector<cv::Matx33d> prod(static_cast<size_t>(k), cv::Matx33d::zeros());
    std::vector<double> count(static_cast<size_t>(k), 0.0);
    for (size_t i = 0; i < samples.size(); ++i) {
      const auto j = static_cast<size_t>(assign[i]);
      const cv::Vec3d c(samples[i][0], samples[i][1], samples[i][2]);
      sum[j] += c;
      prod[j] += c * c.t();
      count[j] += 1;
    }
    g_.clear();
    const double total = static_cast<double>(samples.size());
    for (size_t j = 0; j < static_cast<size_t>(k); ++j) {
      if (count[j] < 1) continue;
      Gaussian g;
      g.mean = sum[j] / count[j];
      cv::Matx33d cov = prod[j] * (1.0 / count[j]) - g.mean * g.mean.t();
      // Sensor noise and JPEG put at least ~2 levels of spread on any colour;
      // the floor also keeps a flat region's covariance invertible.
      for (int a = 0; a < 3; ++a) cov(a, a) += 4.0;
      const double det = cv::determinant(cov);
      g.inv_cov = cov.inv();
      g.log_coef =
          std::log(count[j] / total) - 0.5 * std::log(det) - 1.5 * std::log(2 * std::numbers::pi);
      g_.push_back(g);
    }
  }

  std::vector<Gaussian> g_;
};

// Histogram of log texture, Laplace-smoothed, as -log p.
class TextureHistogram {
 public:
  static constexpr int kBins = 32;

  void Fit(const std::vector<float>& values) {
    std::array<double, kBins> count{};
    for (float v : values) count[static_cast<size_t>(Bin(v))] += 1;
    // A little spread between neighbouring bins: the estimate must not hinge
    // on where a bin edge falls.
    std::array<double, kBins> smooth{};
    for (int b = 0; b < kBins; ++b) {
      const double l = count[static_cast<size_t>(std::max(0, b - 1))];
      const double r = count[static_cast<size_t>(std::min(kBins - 1, b + 1))];
      smooth[static_cast<size_t>(b)] = 0.5 * count[static_cast<size_t>(b)] + 0.25 * (l + r) + 1.0;
    }
    double total = 0;
    for (double c : smooth) total += c;
    for (int b = 0; b < kBins; ++b)
      nll_[static_cast<size_t>(b)] = -std::log(smooth[static_cast<size_t>(b)] / total);
  }

  double NegLogLikelihood(float v) const { return nll_[static_cast<size_t>(Bin(v))]; }

 private:
  // log10 of the texture value over 1e-3 .. 1.
  static int Bin(float v) {
    const double t = (std::log10(std::max(v, 1e-3f)) + 3.0) / 3.0;
    return std::clamp(static_cast<int>(t * kBins), 0, kBins - 1);
  }
  std::array<double, kBins> nll_{};
};

// Samples of one side: every `step`-th pixel with (fg != 0) == want_fg, neutral pixels left out.
void Collect(const cv::Mat& bgr, const cv::Mat& texture, const cv::Mat& fg, const cv::Mat& neutral,
             bool want_fg, std::vector<cv::Vec3f>* colors, std::vector<float>* tex) {
  const int n =
      want_fg ? cv::countNonZero(fg) : static_cast<int>(fg.total()) - cv::countNonZero(fg);
  const size_t step = std::max<size_t>(1, static_cast<size_t>(n) / kMaxSamples);
  colors->clear();
  tex->clear();
  size_t i = 0;
  for (int y = 0; y < bgr.rows; ++y) {
    const cv::Vec3b* p = bgr.ptr<cv::Vec3b>(y);
    const uchar* f = fg.ptr<uchar>(y);
    const float* t = texture.empty() ? nullptr : texture.ptr<float>(y);
    const uchar* u = neutral.empty() ? nullptr : neutral.ptr<uchar>(y);
    for (int x = 0; x < bgr.cols; ++x) {
      if ((f[x] != 0) != want_fg || (u && u[x]) || i++ % step) continue;
      colors->push_back(cv::Vec3f(p[x][0], p[x][1], p[x][2]));
      if (t) tex->push_back(t[x]);
    }
  }
}

}  // namespace

cv::Mat SegmentGraphCut(const cv::Mat& bgr, const cv::Mat& texture, const cv::Mat& trimap,
                        const cv::Mat& neutral, const GraphCutOptions& o) {
  CV_Assert(bgr.type() == CV_8UC3 && trimap.type() == CV_8UC1 && trimap.size() == bgr.size());
  CV_Assert(neutral.empty() || (neutral.type() == CV_8UC1 && neutral.size() == bgr.size()));
  CV_Assert(texture.empty() || (texture.type() == CV_32F && texture.size() == bgr.size()));
  cv::Mat fg = (trimap & 1) * 255;  // GC_FGD = 1, GC_PR_FGD = 3
  const int n_fg = cv::countNonZero(fg);
  if (n_fg == 0 || n_fg == static_cast<int>(fg.total())) return fg;
  const bool use_texture = !texture.empty() && o.texture_weight > 0;

  // Contrast term: beta = 1 / (2 <|dI|^2>) over the 4 forward neighbours.
  const int w = bgr.cols, h = bgr.rows;
  auto diff2 = [&](int y0, int x0, int y1, int x1) {
    const cv::Vec3b &a = bgr.at<cv::Vec3b>(y0, x0), &b = bgr.at<cv::Vec3b>(y1, x1);
    const double d0 = a[0] - b[0], d1 = a[1] - b[1], d2 = a[2] - b[2];
    return d0 * d0 + d1 * d1 + d2 * d2;
  };
  double sum = 0;
  long count = 0;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      if (x > 0) sum += diff2(y, x, y, x - 1), ++count;
      if (y > 0) sum += diff2(y, x, y - 1, x), ++count;
      if (y > 0 && x > 0) sum += diff2(y, x, y - 1, x - 1), ++count;
      if (y > 0 && x + 1 < w) sum += diff2(y, x, y - 1, x + 1), ++count;
    }
  const double beta = sum > 0 ? 1.0 / (2.0 * sum / static_cast<double>(count)) : 0.0;
  // Pairwise weights (left, up, up-left, up-right), computed once.
  cv::Mat wl(h, w, CV_64F, cv::Scalar(0)), wu(h, w, CV_64F, cv::Scalar(0)),
      wul(h, w, CV_64F, cv::Scalar(0)), wur(h, w, CV_64F, cv::Scalar(0));
  const double diag = o.gamma / std::numbers::sqrt2;
  for (int y = 0; y < h; ++y)
    for (int x = 0; x < w; ++x) {
      if (x > 0) wl.at<double>(y, x) = o.gamma * std::exp(-beta * diff2(y, x, y, x - 1));
      if (y > 0) wu.at<double>(y, x) = o.gamma * std::exp(-beta * diff2(y, x, y - 1, x));
      if (y > 0 && x > 0) wul.at<double>(y, x) = diag * std::exp(-beta * diff2(y, x, y - 1, x - 1));
      if (y > 0 && x + 1 < w)
        wur.at<double>(y, x) = diag * std::exp(-beta * diff2(y, x, y - 1, x + 1));
    }
  const double hard = 8.0 * o.gamma + 1.0;  // more than any pixel's pairwise weights together

  ColorMixture col_fg, col_bg;
  TextureHistogram tex_fg, tex_bg;
  std::vector<cv::Vec3f> cs;
  std::vector<float> ts;
  for (int it = 0; it < std::max(1, o.iterations); ++it) {
    Collect(bgr, texture, fg, neutral, true, &cs, &ts);
    if (it == 0)
      col_fg.Init(cs, o.components);
    else
      col_fg.Refit(cs);
    if (use_texture) tex_fg.Fit(ts);
    Collect(bgr, texture, fg, neutral, false, &cs, &ts);
    if (it == 0)
      col_bg.Init(cs, o.components);
    else
      col_bg.Refit(cs);
    if (use_texture) tex_bg.Fit(ts);
    if (col_fg.empty() || col_bg.empty()) break;

    cv::detail::GCGraph<double> graph(static_cast<unsigned>(w * h),
                                      static_cast<unsigned>(2 * 4 * w * h));
    for (int y = 0; y < h; ++y) {
      const cv::Vec3b* p = bgr.ptr<cv::Vec3b>(y);
      const uchar* t = trimap.ptr<uchar>(y);
      const float* tx = use_texture ? texture.ptr<float>(y) : nullptr;
      const uchar* u = neutral.empty() ? nullptr : neutral.ptr<uchar>(y);
      for (int x = 0; x < w; ++x) {
        const int v = graph.addVtx();
        double from_source = 0, to_sink = 0;  // source = rock
        if (t[x] == cv::GC_FGD) {
          from_source = hard;
        } else if (t[x] == cv::GC_BGD) {
          to_sink = hard;
        } else if (u && u[x]) {
          to_sink = o.neutral_rock_cost;
        } else {
          const cv::Vec3f c(p[x][0], p[x][1], p[x][2]);
          from_source = col_bg.NegLogLikelihood(c);  // paid when the pixel ends up background
          to_sink = col_fg.NegLogLikelihood(c);
          if (tx) {
            from_source += o.texture_weight * tex_bg.NegLogLikelihood(tx[x]);
            to_sink += o.texture_weight * tex_fg.NegLogLikelihood(tx[x]);
          }
        }
        graph.addTermWeights(v, from_source, to_sink);
        if (x > 0) graph.addEdges(v, v - 1, wl.at<double>(y, x), wl.at<double>(y, x));
        if (y > 0) graph.addEdges(v, v - w, wu.at<double>(y, x), wu.at<double>(y, x));
        if (y > 0 && x > 0)
          graph.addEdges(v, v - w - 1, wul.at<double>(y, x), wul.at<double>(y, x));
        if (y > 0 && x + 1 < w)
          graph.addEdges(v, v - w + 1, wur.at<double>(y, x), wur.at<double>(y, x));
      }
    }
    graph.maxFlow();
    for (int y = 0; y < h; ++y) {
      uchar* f = fg.ptr<uchar>(y);
      for (int x = 0; x < w; ++x) f[x] = graph.inSourceSegment(y * w + x) ? 255 : 0;
    }
  }
  return fg;
}

}  // namespace aggscan::mask_detail
