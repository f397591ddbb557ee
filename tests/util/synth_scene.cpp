#include "tests/util/synth_scene.h"

#include <cmath>
#include <numbers>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <random>

namespace aggscan::testing {
namespace {

constexpr double kPi = std::numbers::pi;

// Smooth random field in [-1, 1]-ish: sum of blurred white noise at a few scales.
cv::Mat NoiseField(cv::Size size, std::mt19937_64& rng, std::initializer_list<double> sigmas) {
  cv::Mat acc = cv::Mat::zeros(size, CV_32F);
  std::normal_distribution<float> n01(0, 1);
  for (double s : sigmas) {
    cv::Mat small(cv::Size(std::max(4, static_cast<int>(size.width / s)),
                           std::max(4, static_cast<int>(size.height / s))),
                  CV_32F);
    for (int y = 0; y < small.rows; ++y)
      for (int x = 0; x < small.cols; ++x) small.at<float>(y, x) = n01(rng);
    cv::Mat up;
    cv::resize(small, up, size, 0, 0, cv::INTER_CUBIC);
    acc += up * 0.5;
  }
  return acc;
}

}  // namespace

Scene MakeScene(const SceneParams& p) {
  std::mt19937_64 rng(p.seed);
  std::uniform_real_distribution<double> u01(0, 1);
  const int W = p.size.width, H = p.size.height;
  const double s = W / 2016.0;

  // Lighting: floor gets 1.0; a surface with unit normal n gets amb + dif * (n.l).
  const double el = 50 * kPi / 180, az = p.light_azimuth_deg * kPi / 180;
  const cv::Vec3d light(std::cos(el) * std::cos(az), -std::cos(el) * std::sin(az),
                        std::sin(el));  // x right, y down, z up
  const double amb = 0.35, dif = (1.0 - amb) / light[2];

  cv::Mat img(p.size, CV_32FC3);
  // White table with a slight vignette.
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) {
      const double r2 = (std::pow((x - W / 2.0) / W, 2) + std::pow((y - H / 2.0) / H, 2));
      const float v = static_cast<float>(240.0 * (1.0 - 0.12 * r2));
      img.at<cv::Vec3f>(y, x) = cv::Vec3f(v, v, v * 0.99f);
    }
  // Turntable disc (an ellipse in the view), light grey.
  const cv::Point2d disc_c(W * 0.5, H * 0.60);
  const cv::Size2d disc_ax(W * 0.32, W * 0.32 * std::sin(35 * kPi / 180));
  cv::Mat disc = cv::Mat::zeros(p.size, CV_8UC1);
  cv::ellipse(disc, cv::RotatedRect(disc_c, cv::Size2f(2 * disc_ax.width, 2 * disc_ax.height), 0),
              cv::Scalar(255), cv::FILLED, cv::LINE_AA);
  img.setTo(cv::Scalar(200, 202, 204), disc > 128);

  // Colour labels: 20 mm squares at 120 mm from the axis (disc radius 152.5 mm).
  Scene sc;
  sc.labels = cv::Mat::zeros(p.size, CV_8UC1);
  const cv::Scalar colors[4] = {
      {40, 40, 205}, {60, 175, 50}, {200, 90, 30}, {40, 215, 235}};  // BGR r, g, b, y
  for (int k = 0; k < 4; ++k) {
    const double a = (p.turntable_deg + 90.0 * k) * kPi / 180;
    const double rr = 120.0 / 152.5, half = 10.0 / 152.5;
    std::vector<cv::Point> quad;
    for (auto [dx, dy] : {std::pair{-1, -1}, {1, -1}, {1, 1}, {-1, 1}}) {
      const double lx = rr * std::cos(a) + half * (dx * std::cos(a) - dy * std::sin(a));
      const double ly = rr * std::sin(a) + half * (dx * std::sin(a) + dy * std::cos(a));
      quad.emplace_back(cvRound(disc_c.x + lx * disc_ax.width),
                        cvRound(disc_c.y + ly * disc_ax.height));
    }
    cv::fillConvexPoly(img, quad, colors[k], cv::LINE_AA);
    cv::fillConvexPoly(sc.labels, quad, cv::Scalar(255), cv::LINE_8);
  }

  // Rock: star-shaped blob with random harmonics, standing on the disc centre.
  const double R = p.rock_radius_frac * W;
  const cv::Point2d rc(disc_c.x + (u01(rng) - 0.5) * 0.2 * R, disc_c.y - 0.55 * R);
  double amp[6], ph[6];
  for (int k = 0; k < 6; ++k) {
    amp[k] = (k < 2 ? 0.12 : 0.05) * u01(rng);
    ph[k] = 2 * kPi * u01(rng);
  }
  const double elong = 1.0 + 0.5 * u01(rng), rot = kPi * u01(rng);
  std::vector<cv::Point> poly;
  constexpr int kShift = 4;
  for (int i = 0; i < 720; ++i) {
    const double t = 2 * kPi * i / 720;
    double r = 1.0;
    for (int k = 0; k < 6; ++k) r += amp[k] * std::cos((k + 2) * t + ph[k]);
    double x = r * std::cos(t) * elong, y = r * std::sin(t);
    const double xr = std::cos(rot) * x - std::sin(rot) * y,
                 yr = std::sin(rot) * x + std::cos(rot) * y;
    poly.emplace_back(cvRound((rc.x + R * xr / std::sqrt(elong)) * 16),
                      cvRound((rc.y + R * yr / std::sqrt(elong)) * 16));
  }
  sc.truth = cv::Mat::zeros(p.size, CV_8UC1);
  cv::fillPoly(sc.truth, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255), cv::LINE_8,
               kShift);

  // Cast shadow on the floor: the rock pushed away from the light, blurred.
  cv::Mat shadow = cv::Mat::zeros(p.size, CV_32F);
  {
    cv::Mat m;
    sc.truth.convertTo(m, CV_32F, 1.0 / 255);
    const cv::Mat shift =
        (cv::Mat_<double>(2, 3) << 1, 0, -light[0] * 0.45 * R, 0, 1, -light[1] * 0.25 * R);
    cv::Mat moved;
    cv::warpAffine(m, moved, shift, p.size);
    cv::max(moved, m, shadow);
    cv::GaussianBlur(shadow, shadow, cv::Size(0, 0), 0.08 * R);
  }
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) img.at<cv::Vec3f>(y, x) *= 1.0f - 0.6f * shadow.at<float>(y, x);

  // Rock shading: a dome height field from the distance transform gives normals.
  cv::Mat dist;
  cv::distanceTransform(sc.truth, dist, cv::DIST_L2, 5);
  cv::Mat h;
  cv::sqrt(dist * (0.6 * R), h);
  cv::Mat bumps = NoiseField(p.size, rng, {40 * s, 12 * s});
  h += bumps * (4 * s);
  cv::GaussianBlur(h, h, cv::Size(0, 0), 2 * s);
  cv::Mat gx, gy;
  cv::Sobel(h, gx, CV_32F, 1, 0, 3, 1.0 / 8);
  cv::Sobel(h, gy, CV_32F, 0, 1, 3, 1.0 / 8);
  cv::Mat tex = NoiseField(p.size, rng, {3 * s, 8 * s, 30 * s});
  cv::Mat grain = NoiseField(p.size, rng, {1.5 * s});
  const cv::Vec3f brown(0.72f, 0.86f, 1.0f);  // BGR reflectance ratios of a grey-brown stone
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) {
      if (!sc.truth.at<uchar>(y, x)) continue;
      cv::Vec3d n(-gx.at<float>(y, x), -gy.at<float>(y, x), 1.0);
      n /= cv::norm(n);
      const double shade = amb + dif * std::max(0.0, n.dot(light));
      const double alb = std::clamp(
          p.albedo * (1.0 + 0.22 * tex.at<float>(y, x) + 0.08 * grain.at<float>(y, x)), 0.05, 0.95);
      const float v = static_cast<float>(255.0 * alb * shade);
      img.at<cv::Vec3f>(y, x) = cv::Vec3f(v * brown[0], v * brown[1], v * brown[2]);
    }

  // Object markers: head-tail strokes (short + long) in purple and red, shaded.
  sc.markers = cv::Mat::zeros(p.size, CV_8UC1);
  {
    cv::Mat inner;
    cv::erode(sc.truth, inner, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(61, 61) * 1));
    const cv::Scalar stroke_col[2] = {{150, 40, 135}, {35, 35, 195}};
    for (int k = 0; k < 2; ++k) {
      const cv::Point2d c(rc.x + (k == 0 ? -0.35 : 0.3) * R, rc.y + (k == 0 ? -0.15 : 0.2) * R);
      const double a = u01(rng) * kPi;
      const cv::Point2d d(std::cos(a), std::sin(a));
      const double tail = (p.marker_on_edge && k == 1) ? 1.6 * R : 0.35 * R;
      cv::Mat stroke = cv::Mat::zeros(p.size, CV_8UC1);
      const int th = std::max(2, cvRound(9 * s));
      cv::line(stroke, c, c + d * (0.12 * R), cv::Scalar(255), th);                        // head
      cv::line(stroke, c + d * (0.2 * R), c + d * (0.2 * R + tail), cv::Scalar(255), th);  // tail
      if (!(p.marker_on_edge && k == 1)) stroke &= inner;
      stroke &= sc.truth;
      for (int y = 0; y < H; ++y)
        for (int x = 0; x < W; ++x)
          if (stroke.at<uchar>(y, x)) {
            const float v =
                img.at<cv::Vec3f>(y, x)[1] / (255.0f * static_cast<float>(p.albedo) * brown[1]);
            img.at<cv::Vec3f>(y, x) = cv::Vec3f(static_cast<float>(stroke_col[k][0]),
                                                static_cast<float>(stroke_col[k][1]),
                                                static_cast<float>(stroke_col[k][2])) *
                                      std::min(1.1f, v);
          }
      sc.markers |= stroke;
    }
  }
  sc.labels.setTo(0, sc.truth);

  // Optics and sensor: slight lens blur, noise, JPEG.
  cv::GaussianBlur(img, img, cv::Size(0, 0), 0.7 * std::max(1.0, s));
  cv::Mat noise(p.size, CV_32FC3);
  cv::randn(noise, 0, p.noise_sigma);
  img += noise;
  cv::Mat img8;
  img.convertTo(img8, CV_8UC3);
  cv::imencode(".jpg", img8, sc.jpeg, {cv::IMWRITE_JPEG_QUALITY, p.jpeg_quality});
  sc.bgr = cv::imdecode(sc.jpeg, cv::IMREAD_COLOR);
  return sc;
}

double MaskIoU(const cv::Mat& a, const cv::Mat& b, const cv::Mat& ignore) {
  cv::Mat valid = ignore.empty() ? cv::Mat(a.size(), CV_8UC1, cv::Scalar(255)) : (ignore == 0);
  const double inter = cv::countNonZero((a != 0) & (b != 0) & valid);
  const double uni = cv::countNonZero(((a != 0) | (b != 0)) & valid);
  return uni > 0 ? inter / uni : 1.0;
}

FloorScene MakeFloorScene(uint64_t seed) {
  const cv::Size size(1008, 756);
  cv::RNG rng(seed);
  cv::Mat scene(size, CV_32FC3, cv::Scalar(70, 82, 90));  // BGR: the floor between the pebbles
  for (int i = 0; i < 2500; ++i) {
    const cv::Point c(rng.uniform(0, size.width), rng.uniform(0, size.height));
    const double l = rng.uniform(0.6, 1.6);
    cv::ellipse(scene, c, cv::Size(rng.uniform(4, 14), rng.uniform(3, 9)), rng.uniform(0.0, 180.0),
                0, 360, cv::Scalar(95 * l, 105 * l, 115 * l), cv::FILLED, cv::LINE_AA);
  }
  const cv::Point centre(size.width / 2, size.height / 2 + 40);
  cv::ellipse(scene, centre, cv::Size(330, 190), 0, 0, 360, cv::Scalar(188, 190, 192), cv::FILLED,
              cv::LINE_AA);
  const cv::Mat empty_scene = scene.clone();
  // The stone: a textured grey ellipse, shaded, and its soft shadow on the disc.
  FloorScene sc;
  sc.truth = cv::Mat::zeros(size, CV_8UC1);
  const cv::Point c = centre + cv::Point(static_cast<int>(rng.uniform(-40, 40)), -30);
  const cv::Size axes(120 + static_cast<int>(rng.uniform(0, 30)),
                      80 + static_cast<int>(rng.uniform(0, 20)));
  cv::ellipse(sc.truth, c, axes, rng.uniform(0.0, 40.0), 0, 360, cv::Scalar(255), cv::FILLED,
              cv::LINE_8);
  cv::Mat shadow = cv::Mat::zeros(size, CV_32F);
  cv::ellipse(shadow, c + cv::Point(50, 40), axes, 0, 0, 360, cv::Scalar(1.0), cv::FILLED);
  cv::GaussianBlur(shadow, shadow, cv::Size(0, 0), 12);
  // Granite-like grain: dark and pale speckles of 2-3 px.
  cv::Mat grain = cv::Mat::zeros(size, CV_32F);
  for (int i = 0; i < 6000; ++i) {
    const cv::Point p =
        c + cv::Point(rng.uniform(-axes.width, axes.width), rng.uniform(-axes.width, axes.width));
    cv::circle(grain, p, rng.uniform(1, 3), cv::Scalar(rng.uniform(0, 2) ? 45.0 : -45.0),
               cv::FILLED);
  }
  for (int y = 0; y < size.height; ++y) {
    for (int x = 0; x < size.width; ++x) {
      cv::Vec3f& px = scene.at<cv::Vec3f>(y, x);
      if (sc.truth.at<uchar>(y, x)) {
        const double dx = (x - c.x) / static_cast<double>(axes.width),
                     dy = (y - c.y) / static_cast<double>(axes.height);
        const double shade = 1.0 - 0.3 * std::clamp(dx * 0.6 + dy * 0.8, -1.0, 1.0);
        const float gr = grain.at<float>(y, x);
        px = cv::Vec3f(static_cast<float>(105 * shade + gr), static_cast<float>(112 * shade + gr),
                       static_cast<float>(118 * shade + gr));
      } else {
        px *= static_cast<float>(1.0 - 0.45 * shadow.at<float>(y, x));
      }
    }
  }
  auto finish = [&](const cv::Mat& f32, double gain) {
    cv::Mat noise(size, CV_32FC3), out, lens;
    rng.fill(noise, cv::RNG::NORMAL, 0, 2.0);
    cv::GaussianBlur(f32, lens, cv::Size(0, 0), 0.8);  // the lens: no edge is one pixel sharp
    cv::Mat(lens * gain + noise).convertTo(out, CV_8UC3);
    std::vector<unsigned char> jpeg;
    cv::imencode(".jpg", out, jpeg, {cv::IMWRITE_JPEG_QUALITY, 92});
    return cv::imdecode(jpeg, cv::IMREAD_COLOR);
  };
  sc.photo = finish(scene, 1.0);
  sc.empty = finish(empty_scene, 1.08);
  return sc;
}

}  // namespace aggscan::testing
