// The device-free parts of the libcamera camera backend: role and pixel-format
// choice (checked by encoding a frame in each mapped layout), the mapping of
// locked settings onto libcamera controls and back from metadata, camera
// selection, error classes, the [camera.libcamera] config block and the
// factory. The backend against a real pipeline (vimc) is libcamera_vimc_vm_test.
// A build without libcamera runs the config and factory tests only.
#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cerrno>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/factory.h"

#ifdef AGGSCAN_HAVE_LIBCAMERA
#include <libcamera/control_ids.h>
#include <libcamera/formats.h>

#include "drivers/libcamera/libcamera_util.h"
#include "drivers/sim/jpeg.h"
#include "drivers/v4l2/v4l2_util.h"
#endif

namespace aggscan::lc {
namespace {

using ::testing::HasSubstr;

#ifdef AGGSCAN_HAVE_LIBCAMERA
namespace formats = libcamera::formats;
namespace controls = libcamera::controls;
using ::testing::ElementsAre;
using ::testing::IsEmpty;

TEST(LibcameraUtil, RolesByName) {
  EXPECT_EQ(RoleFromName("still"), libcamera::StreamRole::StillCapture);
  EXPECT_EQ(RoleFromName("raw"), libcamera::StreamRole::Raw);
  EXPECT_EQ(RoleFromName("video"), libcamera::StreamRole::VideoRecording);
  EXPECT_EQ(RoleFromName("viewfinder"), libcamera::StreamRole::Viewfinder);
  EXPECT_FALSE(RoleFromName("StillCapture").has_value());
}

TEST(LibcameraUtil, FormatNamesAndTheirV4l2Layouts) {
  EXPECT_EQ(FormatFromName("bgr888"), formats::BGR888);
  EXPECT_EQ(FormatFromName("nv12"), formats::NV12);
  EXPECT_FALSE(FormatFromName("auto").has_value());
  EXPECT_FALSE(FormatFromName("rgb24").has_value()) << "V4L2's names are not libcamera's";
  EXPECT_EQ(V4l2FourCcFor(formats::YUYV), v4l2::FourCc('Y', 'U', 'Y', 'V'));
  EXPECT_EQ(V4l2FourCcFor(formats::MJPEG), v4l2::FourCc('M', 'J', 'P', 'G'));
  EXPECT_EQ(V4l2FourCcFor(formats::SGRBG10), 0u) << "Bayer cannot be encoded";
}

// DRM names count bits in a little-endian word, so libcamera's BGR888 holds
// R, G, B in memory and RGB888 holds B, G, R: a red frame in each layout must
// come out red, not blue.
TEST(LibcameraUtil, Rgb888LayoutsEncodeWithTheRightColours) {
  const int w = 16, h = 8;
  for (auto [fmt, r_index] : {std::pair{formats::BGR888, 0}, std::pair{formats::RGB888, 2}}) {
    SCOPED_TRACE(fmt.toString());
    std::vector<uint8_t> px(static_cast<size_t>(w) * h * 3, 0);
    for (size_t i = 0; i < px.size(); i += 3) px[i + r_index] = 220;
    auto jpeg = v4l2::EncodeStill(V4l2FourCcFor(fmt), px, w, h, w * 3, 95);
    ASSERT_TRUE(jpeg.ok()) << jpeg.error().ToString();
    auto img = sim::DecodeJpeg(*jpeg);
    ASSERT_TRUE(img.ok());
    const size_t mid = (static_cast<size_t>(h / 2) * w + w / 2) * 3;
    EXPECT_GT(img->rgb[mid], 180);
    EXPECT_LT(img->rgb[mid + 1], 40);
    EXPECT_LT(img->rgb[mid + 2], 40);
  }
}

TEST(LibcameraUtil, PixelFormatChoice) {
  const std::vector<libcamera::PixelFormat> vimc = {formats::BGR888, formats::RGB888};
  // auto: the pipeline's default when it can be encoded.
  EXPECT_EQ(*ChoosePixelFormat(vimc, formats::RGB888, "auto"), formats::RGB888);
  // A Bayer default (a raw stream) is passed over for the first encodable.
  const std::vector<libcamera::PixelFormat> mixed = {formats::SGRBG10, formats::NV12,
                                                     formats::YUYV};
  EXPECT_EQ(*ChoosePixelFormat(mixed, formats::SGRBG10, "auto"), formats::YUYV);
  EXPECT_EQ(*ChoosePixelFormat(mixed, formats::SGRBG10, "nv12"), formats::NV12);
  Result<libcamera::PixelFormat> absent = ChoosePixelFormat(vimc, formats::BGR888, "yuyv");
  ASSERT_FALSE(absent.ok());
  EXPECT_EQ(absent.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(absent.error().message, HasSubstr("does not offer YUYV"));
  EXPECT_THAT(absent.error().message, HasSubstr("it offers BGR888, RGB888"));
  Result<libcamera::PixelFormat> bayer =
      ChoosePixelFormat({formats::SGRBG10}, formats::SGRBG10, "auto");
  ASSERT_FALSE(bayer.ok());
  EXPECT_THAT(bayer.error().message, HasSubstr("no pixel format this backend can encode"));
}

libcamera::ControlInfoMap FullInfo() {
  libcamera::ControlInfoMap::Map m;
  m.emplace(&controls::AeEnable, libcamera::ControlInfo(false, true));
  m.emplace(&controls::AwbEnable, libcamera::ControlInfo(false, true));
  m.emplace(&controls::ExposureTime,
            libcamera::ControlInfo(int32_t{100}, int32_t{66666}, int32_t{10000}));
  m.emplace(&controls::AnalogueGain, libcamera::ControlInfo(1.0f, 16.0f, 1.0f));
  m.emplace(&controls::ColourGains, libcamera::ControlInfo(0.0f, 32.0f));
  return libcamera::ControlInfoMap(std::move(m), controls::controls);
}

CameraSettings Manual() {
  CameraSettings s;
  s.manual_exposure = true;
  s.exposure_us = 6000;
  s.gain = 1.5;
  s.wb_red = 1.8;
  s.wb_blue = 1.3;
  return s;
}

TEST(LibcameraUtil, ManualSettingsBecomeControlsWithTheLoopsOff) {
  Result<ControlPlan> p = PlanControls(FullInfo(), Manual());
  ASSERT_TRUE(p.ok()) << p.error().ToString();
  EXPECT_THAT(p->missing, IsEmpty());
  EXPECT_EQ(p->controls.get(controls::AeEnable), false);
  EXPECT_EQ(p->controls.get(controls::AwbEnable), false);
  EXPECT_EQ(p->controls.get(controls::ExposureTime), 6000);
  EXPECT_FLOAT_EQ(*p->controls.get(controls::AnalogueGain), 1.5f);
  auto wb = p->controls.get(controls::ColourGains);
  ASSERT_TRUE(wb.has_value());
  EXPECT_FLOAT_EQ((*wb)[0], 1.8f);
  EXPECT_FLOAT_EQ((*wb)[1], 1.3f);
}

TEST(LibcameraUtil, ACameraWithoutControlsReportsEveryLockedSettingMissing) {
  // vimc's shape: only brightness, contrast and saturation.
  libcamera::ControlInfoMap::Map m;
  m.emplace(&controls::Brightness, libcamera::ControlInfo(-1.0f, 1.0f, 0.0f));
  Result<ControlPlan> p =
      PlanControls(libcamera::ControlInfoMap(std::move(m), controls::controls), Manual());
  ASSERT_TRUE(p.ok());
  EXPECT_THAT(p->missing, ElementsAre("exposure", "gain", "wb_red", "wb_blue"));
  EXPECT_TRUE(p->controls.empty());
}

TEST(LibcameraUtil, ValuesOutsideTheControlRangeAreRefused) {
  CameraSettings s = Manual();
  s.exposure_us = 100000;
  Result<ControlPlan> p = PlanControls(FullInfo(), s);
  ASSERT_FALSE(p.ok());
  EXPECT_EQ(p.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(p.error().message,
              HasSubstr("exposure 100000 us is outside the camera's range 100..66666 us"));
  s = Manual();
  s.gain = 20;
  p = PlanControls(FullInfo(), s);
  ASSERT_FALSE(p.ok());
  EXPECT_THAT(p.error().message, HasSubstr("gain 20 is outside the camera's range 1..16"));
}

TEST(LibcameraUtil, AutomaticExposureSwitchesTheLoopsOnAndLocksNothing) {
  CameraSettings s = Manual();
  s.manual_exposure = false;
  Result<ControlPlan> p = PlanControls(FullInfo(), s);
  ASSERT_TRUE(p.ok());
  EXPECT_EQ(p->controls.get(controls::AeEnable), true);
  EXPECT_EQ(p->controls.get(controls::AwbEnable), true);
  EXPECT_FALSE(p->controls.contains(controls::ExposureTime.id()));
  EXPECT_THAT(p->missing, IsEmpty());
}

TEST(LibcameraUtil, MetadataIsReadBackAndCheckedAgainstTheLockedValues) {
  libcamera::ControlList md(controls::controls);
  EXPECT_FALSE(ReadMetadata(md).has_exposure);
  EXPECT_EQ(UnsettledReason(ReadMetadata(md), Manual(), {}), "")
      << "nothing reported, nothing to check";
  md.set(controls::ExposureTime, 5990);  // quantised to sensor lines: within 2 %
  md.set(controls::AnalogueGain, 1.5f);
  md.set(controls::ColourGains, libcamera::Span<const float, 2>({1.8f, 1.3f}));
  ReadBack rb = ReadMetadata(md);
  EXPECT_TRUE(rb.has_exposure && rb.has_gain && rb.has_wb);
  EXPECT_DOUBLE_EQ(rb.exposure_us, 5990);
  EXPECT_DOUBLE_EQ(rb.gain, 1.5);
  EXPECT_FLOAT_EQ(static_cast<float>(rb.wb_red), 1.8f);
  EXPECT_EQ(UnsettledReason(rb, Manual(), {}), "");
  // A frame still shot with the previous exposure (controls take a few
  // frames to reach the sensor) is not the still.
  md.set(controls::ExposureTime, 3000);
  md.set(controls::AnalogueGain, 4.0f);
  EXPECT_EQ(UnsettledReason(ReadMetadata(md), Manual(), {}),
            "exposure 3000 us (set 6000 us), gain 4 (set 1.5)");
  EXPECT_EQ(UnsettledReason(ReadMetadata(md), Manual(), {"exposure", "gain"}), "")
      << "settings without a control are not held to the config";
  CameraSettings automatic = Manual();
  automatic.manual_exposure = false;
  EXPECT_EQ(UnsettledReason(ReadMetadata(md), automatic, {}), "");
}

TEST(LibcameraUtil, CameraPickedByIdOrIndexElseMissingWithTheList) {
  const std::vector<std::string> ids = {"platform/vimc.0 Sensor B", "/base/usb-cam"};
  EXPECT_EQ(*PickCamera(ids, "/base/usb-cam", 0), "/base/usb-cam");
  EXPECT_EQ(*PickCamera(ids, "", 1), "/base/usb-cam");
  EXPECT_EQ(*PickCamera(ids, "", 0), "platform/vimc.0 Sensor B");
  Result<std::string> r = PickCamera(ids, "imx477", 0);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_THAT(r.error().message,
              HasSubstr("no libcamera camera \"imx477\"; cameras found: \"platform/vimc.0 Sensor "
                        "B\", \"/base/usb-cam\""));
  Result<std::string> none = PickCamera({}, "", 0);
  ASSERT_FALSE(none.ok());
  EXPECT_THAT(none.error().message,
              HasSubstr("no libcamera camera at index 0; cameras found: none"));
}

TEST(LibcameraUtil, ErrorsAreClassifiedLikeV4l2s) {
  EXPECT_EQ(LibcameraError("c", "queueing a request", -ENODEV, true).cls,
            ErrorClass::kDisconnected);
  EXPECT_EQ(LibcameraError("c", "acquire", -ENODEV, false).cls, ErrorClass::kDeviceMissing);
  EXPECT_EQ(LibcameraError("c", "start", -ETIMEDOUT, true).cls, ErrorClass::kTimeout);
  Error busy = LibcameraError("c", "acquire", -EBUSY, false);
  EXPECT_EQ(busy.cls, ErrorClass::kDeviceFault);
  EXPECT_THAT(busy.message, HasSubstr("another program is using the camera"));
  EXPECT_FALSE(busy.detail.empty());
}

#endif  // AGGSCAN_HAVE_LIBCAMERA

TEST(LibcameraConfig, BlockParsesValidatesAndPrints) {
  std::vector<ConfigProblem> problems;
  Result<Config> c = LoadConfigString(R"(
[camera]
backend = "libcamera"
[camera.libcamera]
camera_id = "platform/vimc.0 Sensor B"
role = "video"
pixel_format = "bgr888"
buffers = 6
frame_timeout = "750ms"
strict_controls = false
)",
                                      "t.toml", &problems);
  ASSERT_TRUE(c.ok()) << (problems.empty() ? "" : problems[0].ToString());
  EXPECT_EQ(c->camera.backend, "libcamera");
  EXPECT_EQ(c->camera.libcamera.camera_id, "platform/vimc.0 Sensor B");
  EXPECT_EQ(c->camera.libcamera.role, "video");
  EXPECT_EQ(c->camera.libcamera.pixel_format, "bgr888");
  EXPECT_EQ(c->camera.libcamera.buffers, 6);
  EXPECT_EQ(c->camera.libcamera.frame_timeout, 750 * kNsPerMs);
  EXPECT_FALSE(c->camera.libcamera.strict_controls);
  // The printed config loads back to the same values.
  std::vector<ConfigProblem> p2;
  Result<Config> again = LoadConfigString(ConfigToToml(*c), "printed.toml", &p2);
  ASSERT_TRUE(again.ok()) << (p2.empty() ? "" : p2[0].ToString());
  EXPECT_EQ(again->camera.libcamera, c->camera.libcamera);

  problems.clear();
  Result<Config> bad = LoadConfigString(R"(
[camera.libcamera]
role = "stills"
pixel_format = "rgb24"
buffers = 99
index = -1
frame_timeout = "0s"
)",
                                        "bad.toml", &problems);
  ASSERT_FALSE(bad.ok());
  std::string all;
  for (const auto& p : problems) all += p.ToString() + "\n";
  for (const char* key :
       {"camera.libcamera.role", "camera.libcamera.pixel_format", "camera.libcamera.buffers",
        "camera.libcamera.index", "camera.libcamera.frame_timeout"})
    EXPECT_THAT(all, HasSubstr(key));
}

TEST(LibcameraFactory, BackendIsBuiltOrNamesThePackage) {
  Config c;
  c.camera.backend = "libcamera";
  c.camera.libcamera.camera_id = "no-such-camera";
  RealClock clock;
  Result<RigDevices> rig = CreateRig(c, clock);
#ifdef AGGSCAN_HAVE_LIBCAMERA
  ASSERT_TRUE(rig.ok()) << rig.error().ToString();
  EXPECT_EQ(rig->camera->Info().backend, "libcamera");
  // The real CameraManager on this machine: the named camera is not there,
  // and the error lists what libcamera did find (usually nothing).
  Status s = rig->camera->Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing) << s.error().ToString();
  EXPECT_THAT(s.error().message,
              HasSubstr("no libcamera camera \"no-such-camera\"; cameras found: "));
  EXPECT_EQ(rig->camera->state(), Camera::State::kClosed);
#else
  ASSERT_FALSE(rig.ok());
  EXPECT_EQ(rig.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(rig.error().message, HasSubstr("this build has no libcamera support"));
#endif
}

}  // namespace
}  // namespace aggscan::lc
