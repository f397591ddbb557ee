// V4L2 backend pieces that need no device: format choice, raw conversion,
// control mapping, device-name resolution and error classification; and the
// backend through the factory on a path where no camera is.
#include "drivers/v4l2/v4l2_util.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <linux/videodev2.h>
#include <unistd.h>

#include <cerrno>
#include <filesystem>
#include <fstream>
#include <map>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/factory.h"
#include "drivers/sim/jpeg.h"

namespace aggscan::v4l2 {
namespace {

using ::testing::HasSubstr;

TEST(V4l2Format, FourCcNames) {
  EXPECT_EQ(FourCcName(V4L2_PIX_FMT_YUYV), "YUYV");
  EXPECT_EQ(FourCcName(V4L2_PIX_FMT_MJPEG), "MJPG");
  EXPECT_EQ(FourCc('Y', 'U', 'Y', 'V'), static_cast<uint32_t>(V4L2_PIX_FMT_YUYV));
  EXPECT_EQ(FourCcName(0x01020304u), "????");
}

TEST(V4l2Format, AutoPrefersMjpegThenRawInOrder) {
  EXPECT_EQ(*ChooseFormat({V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_MJPEG}, "auto"), V4L2_PIX_FMT_MJPEG);
  EXPECT_EQ(*ChooseFormat({V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_JPEG}, "auto"), V4L2_PIX_FMT_JPEG);
  // The device's order does not matter: YUYV beats NV12 and RGB.
  EXPECT_EQ(*ChooseFormat({V4L2_PIX_FMT_RGB24, V4L2_PIX_FMT_NV12, V4L2_PIX_FMT_YUYV}, "auto"),
            V4L2_PIX_FMT_YUYV);
  EXPECT_EQ(*ChooseFormat({V4L2_PIX_FMT_SRGGB8, V4L2_PIX_FMT_GREY}, "auto"), V4L2_PIX_FMT_GREY);
}

TEST(V4l2Format, NamedFormatMustBeOffered) {
  EXPECT_EQ(*ChooseFormat({V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_NV12}, "nv12"), V4L2_PIX_FMT_NV12);
  Result<uint32_t> r = ChooseFormat({V4L2_PIX_FMT_YUYV, V4L2_PIX_FMT_NV12}, "mjpeg");
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(r.error().message, HasSubstr("offers: YUYV, NV12"));
}

TEST(V4l2Format, NothingUsableIsADeviceFault) {
  Result<uint32_t> r = ChooseFormat({V4L2_PIX_FMT_SRGGB10, V4L2_PIX_FMT_Y16}, "auto");
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kDeviceFault);
  EXPECT_THAT(r.error().message, HasSubstr("RG10"));
  EXPECT_FALSE(ChooseFormat({}, "auto").ok());
}

// BT.601 limited range: Y 16 black, 235 white; pure red is Y 81, Cb 90, Cr 240.
TEST(V4l2Convert, YuyvAndUyvyToRgb) {
  const std::vector<uint8_t> yuyv = {235, 128, 16, 128, 81, 90, 81, 240};
  Result<std::vector<uint8_t>> rgb = ToRgb(V4L2_PIX_FMT_YUYV, yuyv, 4, 1, 0);
  ASSERT_TRUE(rgb.ok());
  // Pixels 0,1 share chroma (128,128): white and black.
  EXPECT_EQ((std::vector<uint8_t>(rgb->begin(), rgb->begin() + 6)),
            (std::vector<uint8_t>{255, 255, 255, 0, 0, 0}));
  EXPECT_NEAR((*rgb)[6], 255, 2);
  EXPECT_NEAR((*rgb)[7], 0, 2);
  EXPECT_NEAR((*rgb)[8], 0, 2);
  const std::vector<uint8_t> uyvy = {128, 235, 128, 16};
  Result<std::vector<uint8_t>> u = ToRgb(V4L2_PIX_FMT_UYVY, uyvy, 2, 1, 0);
  ASSERT_TRUE(u.ok());
  EXPECT_EQ(*u, (std::vector<uint8_t>{255, 255, 255, 0, 0, 0}));
}

TEST(V4l2Convert, StrideAndPlanesAreHonoured) {
  // 2x2 BGR24 with 8 bytes per line (2 bytes of padding).
  const std::vector<uint8_t> bgr = {1, 2, 3, 4, 5, 6, 0, 0, 7, 8, 9, 10, 11, 12};
  Result<std::vector<uint8_t>> rgb = ToRgb(V4L2_PIX_FMT_BGR24, bgr, 2, 2, 8);
  ASSERT_TRUE(rgb.ok());
  EXPECT_EQ(*rgb, (std::vector<uint8_t>{3, 2, 1, 6, 5, 4, 9, 8, 7, 12, 11, 10}));
  // NV12 2x2: four Y then one interleaved CbCr pair (red).
  const std::vector<uint8_t> nv12 = {81, 81, 81, 81, 90, 240};
  Result<std::vector<uint8_t>> n = ToRgb(V4L2_PIX_FMT_NV12, nv12, 2, 2, 0);
  ASSERT_TRUE(n.ok());
  for (int i = 0; i < 4; ++i) {
    EXPECT_NEAR((*n)[i * 3], 255, 2);
    EXPECT_NEAR((*n)[i * 3 + 1], 0, 2);
  }
  const std::vector<uint8_t> grey = {7, 200};
  EXPECT_EQ(*ToRgb(V4L2_PIX_FMT_GREY, grey, 2, 1, 0),
            (std::vector<uint8_t>{7, 7, 7, 200, 200, 200}));
}

TEST(V4l2Convert, ShortFramesAndUnknownFormatsAreRefused) {
  const std::vector<uint8_t> half(640 * 480, 0);  // YUYV needs twice this
  Result<std::vector<uint8_t>> r = ToRgb(V4L2_PIX_FMT_YUYV, half, 640, 480, 1280);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kDeviceFault);
  EXPECT_THAT(r.error().message, HasSubstr("short frame"));
  EXPECT_FALSE(ToRgb(V4L2_PIX_FMT_SRGGB8, half, 640, 480, 0).ok());
  EXPECT_FALSE(ToRgb(V4L2_PIX_FMT_YUYV, half, 640, 480, 100).ok())
      << "bytesperline shorter than a row";
}

// A 64x48 test card encoded by libturbojpeg (which writes the standard
// Huffman tables of Annex K.3 unless told to optimise them).
std::vector<unsigned char> TestJpeg() {
  std::vector<uint8_t> rgb(64 * 48 * 3);
  for (int y = 0; y < 48; ++y)
    for (int x = 0; x < 64; ++x) {
      uint8_t* p = &rgb[(y * 64 + x) * 3];
      p[0] = static_cast<uint8_t>(x * 4);
      p[1] = static_cast<uint8_t>(y * 5);
      p[2] = static_cast<uint8_t>((x + y) % 2 ? 200 : 30);
    }
  return *sim::EncodeJpeg(rgb.data(), 64, 48, 90);
}

// Splits a JPEG's header into segments: (marker, whole segment bytes).
std::vector<std::pair<uint8_t, std::vector<unsigned char>>> Segments(
    const std::vector<unsigned char>& j) {
  std::vector<std::pair<uint8_t, std::vector<unsigned char>>> out;
  size_t pos = 2;
  while (pos + 4 <= j.size() && j[pos + 1] != 0xDA) {
    const size_t len = (static_cast<size_t>(j[pos + 2]) << 8) | j[pos + 3];
    out.emplace_back(j[pos + 1],
                     std::vector<unsigned char>(j.begin() + pos, j.begin() + pos + 2 + len));
    pos += 2 + len;
  }
  return out;
}

// Every Huffman table as class/id byte -> its counts and values.
std::map<int, std::vector<unsigned char>> HuffmanTables(const std::vector<unsigned char>& j) {
  std::map<int, std::vector<unsigned char>> t;
  for (const auto& [m, seg] : Segments(j)) {
    if (m != 0xC4) continue;
    size_t p = 4;
    while (p < seg.size()) {
      size_t n = 0;
      for (int i = 0; i < 16; ++i) n += seg[p + 1 + i];
      t[seg[p]] = std::vector<unsigned char>(seg.begin() + p + 1, seg.begin() + p + 17 + n);
      p += 17 + n;
    }
  }
  return t;
}

TEST(V4l2Mjpeg, PassedThroughUnchangedWhenComplete) {
  const std::vector<unsigned char> jpeg = TestJpeg();
  Result<std::vector<unsigned char>> still = EncodeStill(V4L2_PIX_FMT_MJPEG, jpeg, 64, 48, 0, 10);
  ASSERT_TRUE(still.ok());
  EXPECT_EQ(*still, jpeg) << "the camera's JPEG is stored as is, not re-encoded at quality 10";
}

TEST(V4l2Mjpeg, MissingHuffmanTablesAreTheStandardOnes) {
  const std::vector<unsigned char> jpeg = TestJpeg();
  const auto reference = HuffmanTables(jpeg);
  ASSERT_EQ(reference.size(), 4u);
  // Motion-JPEG as UVC cameras send it: the same stream without DHT segments.
  std::vector<unsigned char> bare(jpeg.begin(), jpeg.begin() + 2);
  size_t pos = 2;
  for (const auto& [m, seg] : Segments(jpeg)) {
    if (m != 0xC4) bare.insert(bare.end(), seg.begin(), seg.end());
    pos += seg.size();
  }
  bare.insert(bare.end(), jpeg.begin() + pos, jpeg.end());
  ASSERT_TRUE(HuffmanTables(bare).empty());
  Result<std::vector<unsigned char>> fixed = EncodeStill(V4L2_PIX_FMT_MJPEG, bare, 64, 48, 0, 90);
  ASSERT_TRUE(fixed.ok()) << fixed.error().ToString();
  EXPECT_EQ(HuffmanTables(*fixed), reference);
  Result<sim::RgbImage> a = sim::DecodeJpeg(jpeg);
  Result<sim::RgbImage> b = sim::DecodeJpeg(*fixed);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->rgb, b->rgb);
}

TEST(V4l2Mjpeg, GarbageIsADeviceFault) {
  const std::vector<uint8_t> junk = {0x00, 0x11, 0x22, 0x33, 0x44};
  Result<std::vector<unsigned char>> r = EncodeStill(V4L2_PIX_FMT_MJPEG, junk, 64, 48, 0, 90);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kDeviceFault);
  std::vector<unsigned char> cut = TestJpeg();
  cut.resize(40);  // header cut before any scan
  EXPECT_FALSE(EncodeStill(V4L2_PIX_FMT_JPEG, cut, 64, 48, 0, 90).ok());
}

TEST(V4l2Mjpeg, RawFramesAreEncoded) {
  std::vector<uint8_t> yuyv;
  for (int i = 0; i < 16 * 16 / 2; ++i) yuyv.insert(yuyv.end(), {81, 90, 81, 240});  // red
  Result<std::vector<unsigned char>> r = EncodeStill(V4L2_PIX_FMT_YUYV, yuyv, 16, 16, 32, 95);
  ASSERT_TRUE(r.ok());
  Result<sim::RgbImage> img = sim::DecodeJpeg(*r);
  ASSERT_TRUE(img.ok());
  EXPECT_EQ(img->width, 16);
  EXPECT_NEAR(img->rgb[0], 254, 6);
  EXPECT_NEAR(img->rgb[1], 0, 6);
}

TEST(V4l2Controls, QuantizeToTheStepGridWithinRange) {
  const ControlRange r{0, 255, 1, 100};
  EXPECT_EQ(*QuantizeControl(r, 149.6, "gain"), 150);
  const ControlRange stepped{3, 2047, 4, 250};  // UVC exposure_absolute-like
  EXPECT_EQ(*QuantizeControl(stepped, 80.0, "exposure"), 79);
  EXPECT_EQ(*QuantizeControl(stepped, 82.0, "exposure"), 83);
  Result<int64_t> high = QuantizeControl(r, 300, "gain");
  ASSERT_FALSE(high.ok());
  EXPECT_EQ(high.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(high.error().message,
              HasSubstr("gain: device value 300 is outside the control's range 0..255"));
  EXPECT_FALSE(QuantizeControl(stepped, 1.0, "exposure").ok());
}

TEST(V4l2Controls, ExposureIsInHundredMicroseconds) {
  EXPECT_DOUBLE_EQ(ExposureUsToV4l2(8000), 80.0);
  EXPECT_DOUBLE_EQ(V4l2ToExposureUs(80), 8000.0);
}

TEST(V4l2Controls, UnitlessFactorsScaleTheReference) {
  const ControlRange r{0, 255, 1, 100};
  EXPECT_DOUBLE_EQ(*UnitlessToDevice(r, 1.5, 0, "gain"), 150.0);  // the control's default is 1.0
  EXPECT_DOUBLE_EQ(*UnitlessToDevice(r, 1.5, 16, "gain"), 24.0);  // gain_unit overrides it
  Result<double> zero = UnitlessToDevice(ControlRange{0, 255, 1, 0}, 2.0, 0, "gain");
  ASSERT_FALSE(zero.ok());
  EXPECT_THAT(zero.error().message, HasSubstr("camera.v4l2.gain_unit"));
}

TEST(V4l2Device, MissingPathsAreDeviceMissing) {
  Result<std::string> r = ResolveDevice("/dev/aggscan-no-such-camera");
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_THAT(r.error().message, HasSubstr("/dev/aggscan-no-such-camera"));
  Result<std::string> name =
      ResolveDevice("usb-Acme_Cam-video-index0", {"/nonexistent/by-id", "/nonexistent/by-path"});
  ASSERT_FALSE(name.ok());
  EXPECT_EQ(name.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_THAT(name.error().message, HasSubstr("/nonexistent/by-id/usb-Acme_Cam-video-index0, "
                                              "/nonexistent/by-path/usb-Acme_Cam-video-index0"));
  EXPECT_EQ(ResolveDevice("").error().cls, ErrorClass::kInvalidConfig);
}

TEST(V4l2Device, UdevNamesAreFollowedToTheNode) {
  namespace fs = std::filesystem;
  const fs::path dir = fs::temp_directory_path() / ("v4l2-by-id-" + std::to_string(::getpid()));
  fs::create_directories(dir / "by-id");
  // /dev/null stands in for the character device a by-id link points at.
  fs::create_symlink("/dev/null", dir / "by-id" / "usb-Acme_Cam-video-index0");
  fs::create_symlink(dir / "by-id" / "usb-Acme_Cam-video-index0", dir / "chained");
  std::ofstream(dir / "plain-file") << "x";
  EXPECT_EQ(*ResolveDevice("usb-Acme_Cam-video-index0",
                           {(dir / "by-path").string(), (dir / "by-id").string()}),
            "/dev/null");
  EXPECT_EQ(*ResolveDevice((dir / "chained").string()), "/dev/null");
  Result<std::string> file = ResolveDevice((dir / "plain-file").string());
  ASSERT_FALSE(file.ok());
  EXPECT_THAT(file.error().message, HasSubstr("not a device node"));
  fs::remove_all(dir);
}

TEST(V4l2Errors, ClassifiedForTheOperator) {
  EXPECT_EQ(ClassifyErrno(ENOENT, false), ErrorClass::kDeviceMissing);
  EXPECT_EQ(ClassifyErrno(ENODEV, false), ErrorClass::kDeviceMissing);
  EXPECT_EQ(ClassifyErrno(ENODEV, true), ErrorClass::kDisconnected);
  EXPECT_EQ(ClassifyErrno(ENXIO, true), ErrorClass::kDisconnected);
  EXPECT_EQ(ClassifyErrno(ETIMEDOUT, true), ErrorClass::kTimeout);
  EXPECT_EQ(ClassifyErrno(EBUSY, false), ErrorClass::kDeviceFault);
  EXPECT_EQ(ClassifyErrno(EACCES, false), ErrorClass::kIo);
  Error e = V4l2Error("/dev/video0", "VIDIOC_DQBUF", ENODEV, true);
  EXPECT_EQ(e.cls, ErrorClass::kDisconnected);
  EXPECT_THAT(e.message, HasSubstr("/dev/video0: VIDIOC_DQBUF failed"));
  EXPECT_FALSE(e.detail.empty());
  EXPECT_THAT(V4l2Error("/dev/video0", "open", EBUSY, false).message, HasSubstr("another program"));
}

TEST(V4l2Camera, FactoryBuildsItAndOpenReportsAMissingCamera) {
  Config c;
  c.camera.backend = "v4l2";
  c.camera.device = "/dev/aggscan-test-no-camera";
  RealClock clock;
  Result<RigDevices> rig = CreateRig(c, clock);
  ASSERT_TRUE(rig.ok()) << rig.error().ToString();
  EXPECT_EQ(rig->camera->Info().backend, "v4l2");
  Status s = rig->camera->Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_EQ(rig->camera->state(), Camera::State::kClosed);
}

TEST(V4l2Camera, ANodeThatIsNoCameraIsRefused) {
  Config c;
  c.camera.backend = "v4l2";
  c.camera.device = "/dev/null";
  RealClock clock;
  Result<RigDevices> rig = CreateRig(c, clock);
  ASSERT_TRUE(rig.ok());
  Status s = rig->camera->Open();
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_THAT(s.error().message, HasSubstr("not a V4L2 device"));
}

}  // namespace
}  // namespace aggscan::v4l2
