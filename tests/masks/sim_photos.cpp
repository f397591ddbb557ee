#include "tests/masks/sim_photos.h"

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "config/config.h"

namespace aggscan::testing {

Result<SimPhotos> SimPhotos::Create(uint64_t seed) {
  Config cfg;
  cfg.sim.seed = seed;
  auto world = sim::SimWorld::Create(cfg);
  if (!world) return world.error();
  SimPhotos p;
  p.seed_ = seed;
  p.world_ = *world;
  p.renderer_ = std::make_unique<sim::Renderer>(*p.world_, 2016, 1512);
  return p;
}

SimPhoto SimPhotos::Render(int side, double angle) {
  sim::RenderOptions o;
  o.want_mask = true;
  o.noise_seed = seed_ * 100 + side;
  const sim::RenderedImage img = renderer_->Render(side, angle, o);
  cv::Mat rgb(img.height, img.width, CV_8UC3, const_cast<uint8_t*>(img.rgb.data()));
  SimPhoto v;
  cv::cvtColor(rgb, v.bgr, cv::COLOR_RGB2BGR);
  std::vector<unsigned char> jpg;
  cv::imencode(".jpg", v.bgr, jpg, {cv::IMWRITE_JPEG_QUALITY, 92});
  v.bgr = cv::imdecode(jpg, cv::IMREAD_COLOR);
  v.truth = cv::Mat(img.height, img.width, CV_8UC1, const_cast<uint8_t*>(img.mask.data())).clone();
  return v;
}

}  // namespace aggscan::testing
