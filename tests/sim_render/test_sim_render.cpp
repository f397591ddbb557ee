// Renderer: what the sim camera sees, checked against the world's ground truth.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <memory>

#include "common/fsutil.h"
#include "drivers/sim/jpeg.h"
#include "drivers/sim/render.h"

namespace aggscan::sim {
namespace {

Config TestConfig() {
  Config c;
  c.sim.seed = 3;
  c.sim.rock_size_mm = 120.0;
  c.camera.width = 640;
  c.camera.height = 480;
  return c;
}

// One world for the whole suite (building it is the slow part in Debug).
const SimWorld& World() {
  static const SimWorld w(TestConfig(), {.rock_faces = 20000});
  return w;
}

struct Hsv {
  double h, s, v;  // h in degrees
};
Hsv ToHsv(const uint8_t* p) {
  const double r = p[0] / 255.0, g = p[1] / 255.0, b = p[2] / 255.0;
  const double mx = std::max({r, g, b}), mn = std::min({r, g, b}), d = mx - mn;
  double h = 0;
  if (d > 0) {
    if (mx == r)
      h = 60 * std::fmod((g - b) / d + 6, 6);
    else if (mx == g)
      h = 60 * ((b - r) / d + 2);
    else
      h = 60 * ((r - g) / d + 4);
  }
  return {h, mx > 0 ? d / mx : 0, mx};
}
double HueDistance(double a, double b) {
  const double d = std::fmod(std::abs(a - b), 360.0);
  return std::min(d, 360 - d);
}
double ExpectedHue(const std::string& color) {
  if (color == "red") return 0;
  if (color == "yellow") return 55;
  if (color == "green") return 125;
  return 228;  // blue
}

// Mean over a small window (JPEG and noise make single pixels unreliable).
void WindowMean(const std::vector<uint8_t>& rgb, int w, int u, int v, int r, uint8_t out[3]) {
  double s[3] = {0, 0, 0};
  int n = 0;
  for (int y = v - r; y <= v + r; ++y)
    for (int x = u - r; x <= u + r; ++x) {
      for (int k = 0; k < 3; ++k) s[k] += rgb[(static_cast<size_t>(y) * w + x) * 3 + k];
      ++n;
    }
  for (int k = 0; k < 3; ++k) out[k] = static_cast<uint8_t>(s[k] / n + 0.5);
}

// Checks each label's colour at its projected centre; returns how many were checked.
int CheckLabels(const RgbImage& img, const std::vector<uint8_t>& mask, double platter_deg) {
  const Intrinsics k = World().IntrinsicsFor(img.width, img.height);
  int checked = 0;
  for (const RigMarker& m : World().config().rig.markers) {
    double u, v;
    EXPECT_TRUE(World().ProjectTurntablePoint({m.x_mm, m.y_mm, 0}, platter_deg, k, &u, &v));
    const int iu = static_cast<int>(std::lround(u)), iv = static_cast<int>(std::lround(v));
    if (iu < 3 || iv < 3 || iu >= img.width - 3 || iv >= img.height - 3) continue;
    bool hidden = false;  // behind the rock from this viewpoint
    for (int y = iv - 3; y <= iv + 3; ++y)
      for (int x = iu - 3; x <= iu + 3; ++x)
        hidden = hidden || mask[static_cast<size_t>(y) * img.width + x];
    if (hidden) continue;
    uint8_t c[3];
    WindowMean(img.rgb, img.width, iu, iv, 1, c);
    const Hsv hsv = ToHsv(c);
    EXPECT_GT(hsv.s, 0.5) << m.color << " at " << u << "," << v << " angle " << platter_deg;
    EXPECT_LT(HueDistance(hsv.h, ExpectedHue(m.color)), 25.0)
        << m.color << " hue " << hsv.h << " at " << u << "," << v << " angle " << platter_deg;
    ++checked;
  }
  return checked;
}

TEST(SimRender, FrameEncodesDecodesAndShowsTheRock) {
  Renderer r(World(), 640, 480);
  RenderOptions o;
  o.want_mask = true;
  o.noise_seed = 1;
  const RenderedImage img = r.Render(1, 0.0, o);
  ASSERT_EQ(img.rgb.size(), 640u * 480 * 3);
  ASSERT_EQ(img.mask.size(), 640u * 480);
  Result<std::vector<unsigned char>> jpeg = EncodeJpeg(img.rgb.data(), 640, 480, 92);
  ASSERT_TRUE(jpeg.ok());
  Result<RgbImage> dec = DecodeJpeg(*jpeg);
  ASSERT_TRUE(dec.ok()) << dec.error().ToString();
  EXPECT_EQ(dec->width, 640);
  EXPECT_EQ(dec->height, 480);
  // Plausible mask: a 120 mm rock at ~650 mm is a few percent of the frame,
  // one connected blob near the image centre.
  long area = 0;
  double mu = 0, mv = 0;
  for (int v = 0; v < 480; ++v)
    for (int u = 0; u < 640; ++u)
      if (img.mask[v * 640 + u]) ++area, mu += u, mv += v;
  const double frac = static_cast<double>(area) / (640 * 480);
  EXPECT_GT(frac, 0.01);
  EXPECT_LT(frac, 0.25);
  EXPECT_NEAR(mu / area, 320, 80);
  EXPECT_NEAR(mv / area, 240, 100);
  // The rock is darker than the white table around it.
  double rock_mean = 0, bg_mean = 0;
  long bg_n = 0;
  for (size_t i = 0; i < img.mask.size(); ++i) {
    const double y = (img.rgb[3 * i] + img.rgb[3 * i + 1] + img.rgb[3 * i + 2]) / 3.0;
    if (img.mask[i])
      rock_mean += y;
    else
      bg_mean += y, ++bg_n;
  }
  EXPECT_LT(rock_mean / area + 30, bg_mean / bg_n);
  WritePpm(dec->rgb, 640, 480, "/tmp/aggscan_sim_render_test.ppm").ok();
}

TEST(SimRender, LabelsAtProjectedPositionsAndRotateWithThePlatter) {
  Renderer r(World(), 640, 480);
  RenderOptions o;
  o.want_mask = true;
  for (double angle : {0.0, 90.0, 217.0}) {
    const RenderedImage img = r.Render(1, angle, o);
    auto jpeg = EncodeJpeg(img.rgb.data(), 640, 480, 92);
    ASSERT_TRUE(jpeg.ok());
    auto dec = DecodeJpeg(*jpeg);
    ASSERT_TRUE(dec.ok());
    EXPECT_GE(CheckLabels(*dec, img.mask, angle), 3) << angle;
  }
  // After 90 degrees, the red label is where the green one was (green at +y).
  const RenderedImage a = r.Render(1, 90.0, o);
  const Intrinsics k = r.intrinsics();
  double u, v;
  ASSERT_TRUE(World().ProjectTurntablePoint({0, 120, 0}, 0.0, k, &u, &v));
  double u2, v2;
  ASSERT_TRUE(World().ProjectTurntablePoint({120, 0, 0}, 90.0, k, &u2, &v2));
  EXPECT_NEAR(u, u2, 1e-6);
  EXPECT_NEAR(v, v2, 1e-6);
}

TEST(SimRender, DeterministicPerSeedAndNoiseDiffersAcrossSeeds) {
  Renderer r(World(), 320, 240);
  RenderOptions o;
  o.noise_seed = 42;
  const RenderedImage a = r.Render(2, 45.0, o);
  Renderer r2(World(), 320, 240);
  const RenderedImage b = r2.Render(2, 45.0, o);
  EXPECT_EQ(a.rgb, b.rgb);
  o.noise_seed = 43;
  const RenderedImage c = r.Render(2, 45.0, o);
  EXPECT_NE(a.rgb, c.rgb);
  // Noise has about the configured sigma.
  double s = 0, s2 = 0;
  for (size_t i = 0; i < a.rgb.size(); ++i) {
    const double d = static_cast<double>(a.rgb[i]) - c.rgb[i];
    s += d, s2 += d * d;
  }
  const double n = static_cast<double>(a.rgb.size());
  const double sigma = std::sqrt((s2 / n - (s / n) * (s / n)) / 2.0);
  EXPECT_NEAR(sigma, World().config().sim.noise_sigma, 0.5);
}

TEST(SimRender, ObjectMarkersArePaintedOnTheRock) {
  Renderer r(World(), 640, 480);
  RenderOptions o;
  o.want_mask = true;
  o.noise_seed = 5;
  // Over a full turn, purple pixels show up and are all on the rock.
  long purple = 0, outside = 0;
  for (int i = 0; i < 4; ++i) {
    const RenderedImage img = r.Render(1, i * 90.0, o);
    for (size_t p = 0; p < img.mask.size(); ++p) {
      const Hsv hsv = ToHsv(&img.rgb[3 * p]);
      if (hsv.s > 0.5 && hsv.v > 0.08 && HueDistance(hsv.h, 285) < 25) {
        ++purple;
        if (!img.mask[p]) ++outside;
      }
    }
  }
  EXPECT_GT(purple, 30);
  EXPECT_EQ(outside, 0);
}

TEST(SimRender, ObjectMarkerHeadProjectsOntoPaint) {
  // Each marker's truth head point, when facing the camera, lands on its paint.
  Renderer r(World(), 640, 480);
  RenderOptions o;
  o.want_mask = true;
  o.noise_seed = 9;
  const Intrinsics k = r.intrinsics();
  int seen = 0;
  for (int side = 1; side <= 2; ++side) {
    for (const ObjectMarker& m : World().object_markers()) {
      for (int i = 0; i < 12; ++i) {
        const double angle = i * 30.0;
        const Rigid rc = World().RockToCamera(side, angle);
        const Vec3 n_cam = rc.Rotate(m.normal);
        const Vec3 p_cam = rc.Apply(m.tail);
        if (Dot(n_cam, Normalized(p_cam)) > -0.6) continue;  // not facing the camera
        const RenderedImage img = r.Render(side, angle, o);
        double u, v;
        ASSERT_TRUE(k.Project(p_cam, &u, &v));
        const size_t idx = static_cast<size_t>(std::lround(v)) * 640 + std::lround(u);
        EXPECT_TRUE(img.mask[idx]);
        const Hsv hsv = ToHsv(&img.rgb[3 * idx]);
        EXPECT_GT(hsv.s, 0.45) << m.color << " side " << side << " angle " << angle;
        EXPECT_LT(HueDistance(hsv.h, m.color == "red" ? 0 : 285), 30)
            << m.color << " side " << side;
        ++seen;
        break;
      }
    }
  }
  EXPECT_GE(seen, 3);
}

TEST(SimRender, ExposureScalesBrightness) {
  Renderer r(World(), 320, 240);
  RenderOptions o;
  o.exposure.exposure_us = 4000;  // half the reference: darker
  const RenderedImage dark = r.Render(1, 0, o);
  o.exposure.exposure_us = 8000;
  const RenderedImage nominal = r.Render(1, 0, o);
  o.exposure.gain = 0.5;
  const RenderedImage half_gain = r.Render(1, 0, o);
  auto mean = [](const RenderedImage& i) {
    double s = 0;
    for (uint8_t c : i.rgb) s += c;
    return s / static_cast<double>(i.rgb.size());
  };
  EXPECT_LT(mean(dark) + 20, mean(nominal));
  EXPECT_NEAR(mean(dark), mean(half_gain), 1.0);
  o.exposure.gain = 1.0;
  o.exposure.wb_red = 1.3;
  const RenderedImage warm = r.Render(1, 0, o);
  double dr = 0, db = 0;
  for (size_t i = 0; i < warm.rgb.size(); i += 3)
    dr += warm.rgb[i] - nominal.rgb[i], db += warm.rgb[i + 2] - nominal.rgb[i + 2];
  EXPECT_GT(dr, 10.0 * warm.rgb.size() / 3);
  EXPECT_NEAR(db / (warm.rgb.size() / 3), 0.0, 1.0);
}

TEST(SimRender, ShadowDarkensTheDiscBesideTheRock) {
  // The disc just beyond the rock, away from the light, is in its cast shadow
  // and darker than the disc on the lit side.
  Config c = TestConfig();
  c.sim.noise_sigma = 0;
  const SimWorld w(c, {.rock_faces = 4000});
  Renderer r(w, 640, 480);
  RenderOptions o;
  o.want_mask = true;
  const RenderedImage img = r.Render(1, 0, o);
  const Intrinsics k = r.intrinsics();
  const Rigid rw = w.RockToWorld(1, 0);
  const Vec3 l = w.lighting().to_light;
  const Vec3 away = Normalized(Vec3{-l.x, -l.y, 0});  // the shadow falls this way
  const Vec3 com = rw.Apply(w.center_of_mass());
  const Vec3 foot{com.x, com.y, 0};
  const auto lum_at = [&](const Vec3& g, double* lum) {
    double u, v;
    if (!k.Project(w.world_to_camera().Apply(g), &u, &v)) return false;
    const size_t i = static_cast<size_t>(std::lround(v)) * 640 + std::lround(u);
    if (img.mask[i]) return false;  // hidden behind the rock
    *lum = (img.rgb[3 * i] + img.rgb[3 * i + 1] + img.rgb[3 * i + 2]) / 3.0;
    return true;
  };
  // First visible disc point beyond the rock's silhouette, then 3 mm further.
  double shadow = -1, lit = -1, s = 0;
  while (s < 150 && !lum_at(foot + away * s, &shadow)) s += 1.0;
  ASSERT_TRUE(lum_at(foot + away * (s + 3), &shadow));
  ASSERT_TRUE(lum_at(foot - away * 90, &lit));
  EXPECT_LT(shadow + 40, lit);
}

TEST(SimRender, AWetStoneHasHighlightsOnTheRockOnly) {
  // [sim] rock_gloss adds the key light's highlight: on the rock only, never
  // darkening it, the silhouette unchanged.
  Config c = TestConfig();
  c.sim.noise_sigma = 0;
  const SimWorld matte(c, {.rock_faces = 4000});
  c.sim.rock_gloss = 2.0;
  c.sim.rock_shininess = 40.0;
  const SimWorld wet(c, {.rock_faces = 4000});
  Renderer rm(matte, 640, 480), rw(wet, 640, 480);
  RenderOptions o;
  o.want_mask = true;
  for (const double angle : {0.0, 20.0}) {
    const RenderedImage m = rm.Render(1, angle, o), w = rw.Render(1, angle, o);
    ASSERT_EQ(m.mask, w.mask);
    int background_changed = 0, rock_darker = 0, highlight = 0;
    for (size_t i = 0; i < m.mask.size(); ++i) {
      int gain = 0;
      for (int ch = 0; ch < 3; ++ch) {
        const int d = w.rgb[3 * i + ch] - m.rgb[3 * i + ch];
        background_changed += !m.mask[i] && d != 0;
        rock_darker += m.mask[i] && d < 0;
        gain += d;
      }
      highlight += m.mask[i] && gain > 3 * 30;
    }
    EXPECT_EQ(background_changed, 0) << angle;
    EXPECT_EQ(rock_darker, 0) << angle;
    EXPECT_GT(highlight, 20) << angle;  // pixels at least 30 levels brighter
  }
}

TEST(SimJpeg, RejectsGarbageAndWritesPgm) {
  const std::vector<unsigned char> junk(100, 0x42);
  Result<RgbImage> r = DecodeJpeg(junk);
  ASSERT_FALSE(r.ok());
  EXPECT_EQ(r.error().cls, ErrorClass::kCorrupt);
  EXPECT_FALSE(EncodeJpeg(junk.data(), 0, 10, 90).ok());
  const std::string path = ::testing::TempDir() + "/sim_mask.pgm";
  std::vector<uint8_t> mask(6 * 4, 0);
  mask[5] = 255;
  ASSERT_TRUE(WritePgm(mask, 6, 4, path).ok());
  Result<std::string> bytes = ReadFile(path);
  ASSERT_TRUE(bytes.ok());
  EXPECT_EQ(bytes->substr(0, 9), "P5\n6 4\n25");
  EXPECT_EQ(bytes->size(), 11u + 24u);
  EXPECT_EQ(static_cast<unsigned char>((*bytes)[11 + 5]), 255);
  EXPECT_FALSE(WritePgm(mask, 7, 4, path).ok());  // size mismatch
}

}  // namespace
}  // namespace aggscan::sim
