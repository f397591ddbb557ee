// Measurement: does the sim rock give SIFT enough features? Renders views of
// procedural rocks at the rig's resolution, counts SIFT keypoints inside the
// ground-truth rock mask, and counts ratio-test matches (Lowe 0.8) between
// views one turntable step (30 deg) apart, i.e. what SfM needs.
//   sift_features [seeds=3] [width=2016 height=1512]
#include <cstdio>
#include <cstdlib>
#include <opencv2/features2d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "config/config.h"
#include "drivers/sim/render.h"
#include "drivers/sim/world.h"

using namespace aggscan;

namespace {
struct View {
  cv::Mat gray, mask;
};

View RenderView(const sim::SimWorld& w, sim::Renderer& r, int side, double deg) {
  sim::RenderOptions o;
  o.want_mask = true;
  sim::RenderedImage img = r.Render(side, deg, o);
  cv::Mat rgb(img.height, img.width, CV_8UC3, img.rgb.data());
  cv::Mat bgr, gray;
  cv::cvtColor(rgb, bgr, cv::COLOR_RGB2BGR);
  std::vector<unsigned char> jpg;  // what the worker sees: a JPEG
  cv::imencode(".jpg", bgr, jpg, {cv::IMWRITE_JPEG_QUALITY, 92});
  cv::cvtColor(cv::imdecode(jpg, cv::IMREAD_COLOR), gray, cv::COLOR_BGR2GRAY);
  View v;
  v.gray = gray;
  v.mask = cv::Mat(img.height, img.width, CV_8UC1, img.mask.data()).clone();
  (void)w;
  return v;
}
}  // namespace

int main(int argc, char** argv) {
  const int seeds = argc > 1 ? std::atoi(argv[1]) : 3;
  const int width = argc > 3 ? std::atoi(argv[2]) : 2016;
  const int height = argc > 3 ? std::atoi(argv[3]) : 1512;
  auto sift = cv::SIFT::create();
  cv::BFMatcher matcher(cv::NORM_L2);
  std::printf("seed side  keypoints_on_rock(view0)  matches_30deg  rock_px\n");
  for (int seed = 1; seed <= seeds; ++seed) {
    Config c;
    c.sim.seed = static_cast<uint64_t>(seed);
    c.camera.width = width;
    c.camera.height = height;
    auto w = sim::SimWorld::Create(c);
    if (!w) {
      std::fprintf(stderr, "%s\n", w.error().ToString().c_str());
      return 1;
    }
    sim::Renderer r(**w, width, height);
    for (int side = 1; side <= 2; ++side) {
      View a = RenderView(**w, r, side, 0.0), b = RenderView(**w, r, side, 30.0);
      std::vector<cv::KeyPoint> ka, kb;
      cv::Mat da, db;
      sift->detectAndCompute(a.gray, a.mask, ka, da);
      sift->detectAndCompute(b.gray, b.mask, kb, db);
      std::vector<std::vector<cv::DMatch>> knn;
      if (!da.empty() && !db.empty()) matcher.knnMatch(da, db, knn, 2);
      int good = 0;
      for (const auto& m : knn) good += m.size() == 2 && m[0].distance < 0.8f * m[1].distance;
      std::printf("%4d %4d  %23zu  %13d  %7d\n", seed, side, ka.size(), good,
                  cv::countNonZero(a.mask));
    }
  }
  return 0;
}
