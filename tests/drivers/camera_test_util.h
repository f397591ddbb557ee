// Helpers the camera backend tests against kernel test drivers share.
#pragma once

#include <fcntl.h>
#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <linux/videodev2.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <future>
#include <memory>
#include <string>
#include <thread>
#include <utility>

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

/// The first /dev/videoN whose driver (VIDIOC_QUERYCAP) is `driver` and that
/// captures video; "" when none.
inline std::string FindCaptureNode(const std::string& driver) {
  for (int i = 0; i < 16; ++i) {
    const std::string p = "/dev/video" + std::to_string(i);
    const int fd = ::open(p.c_str(), O_RDWR | O_CLOEXEC);
    if (fd < 0) continue;
    v4l2_capability cap{};
    const bool match = ::ioctl(fd, VIDIOC_QUERYCAP, &cap) == 0 &&
                       std::string(reinterpret_cast<const char*>(cap.driver)) == driver &&
                       (cap.device_caps & V4L2_CAP_VIDEO_CAPTURE);
    ::close(fd);
    if (match) return p;
  }
  return {};
}

/// The largest frame size the capture node lists for `fourcc` (the maximum
/// of a stepwise range); {0, 0} when it lists none.
inline std::pair<int, int> LargestFrameSize(const std::string& node, uint32_t fourcc) {
  int w = 0, h = 0;
  const int fd = ::open(node.c_str(), O_RDWR | O_CLOEXEC);
  if (fd < 0) return {0, 0};
  v4l2_frmsizeenum fs{};
  fs.pixel_format = fourcc;
  for (fs.index = 0; ::ioctl(fd, VIDIOC_ENUM_FRAMESIZES, &fs) == 0; ++fs.index) {
    if (fs.type != V4L2_FRMSIZE_TYPE_DISCRETE) {
      w = static_cast<int>(fs.stepwise.max_width);
      h = static_cast<int>(fs.stepwise.max_height);
      break;
    }
    if (static_cast<int64_t>(fs.discrete.width) * fs.discrete.height >
        static_cast<int64_t>(w) * h) {
      w = static_cast<int>(fs.discrete.width);
      h = static_cast<int>(fs.discrete.height);
    }
  }
  ::close(fd);
  return {w, h};
}

struct Rgb {
  int r, g, b;
};
inline Rgb At(const sim::RgbImage& img, int x, int y) {
  const size_t i = (static_cast<size_t>(y) * img.width + x) * 3;
  return {img.rgb[i], img.rgb[i + 1], img.rgb[i + 2]};
}

}  // namespace aggscan::testutil
