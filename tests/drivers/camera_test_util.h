// Helpers the camera backend tests against kernel test drivers share.
#pragma once

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <chrono>
#include <future>
#include <memory>
#include <string>
#include <thread>

#include "drivers/camera.h"
#include "drivers/sim/jpeg.h"

namespace aggscan::testutil {

/// Takes one still and waits for it (bounded); `on` receives the thread the
/// callback ran on.
inline Result<FramePtr> TakeStill(Camera& cam, const StillRequest& req,
                                  std::thread::id* on = nullptr,
                                  std::chrono::seconds wait = std::chrono::seconds(90)) {
  auto prom = std::make_shared<std::promise<Result<FramePtr>>>();
  auto fut = prom->get_future();
  Status s = cam.RequestStill(req, [prom, on](Result<FramePtr> r) {
    if (on) *on = std::this_thread::get_id();
    prom->set_value(std::move(r));
  });
  if (!s) return s.error();
  if (fut.wait_for(wait) != std::future_status::ready)
    return MakeError(ErrorClass::kInternal, "callback never came");
  return fut.get();
}

/// Configure must be refused as a config error naming `message_part`, and
/// leave the camera opened (not half-configured).
inline void ExpectConfigureRefused(Camera& cam, const CameraSettings& s,
                                   const std::string& message_part) {
  Status st = cam.Configure(s);
  ASSERT_FALSE(st.ok());
  EXPECT_EQ(st.error().cls, ErrorClass::kInvalidConfig) << st.error().ToString();
  EXPECT_THAT(st.error().message, ::testing::HasSubstr(message_part));
  EXPECT_EQ(cam.state(), Camera::State::kOpened);
}

struct Rgb {
  int r, g, b;
};
inline Rgb At(const sim::RgbImage& img, int x, int y) {
  const size_t i = (static_cast<size_t>(y) * img.width + x) * 3;
  return {img.rgb[i], img.rgb[i + 1], img.rgb[i + 2]};
}

}  // namespace aggscan::testutil
