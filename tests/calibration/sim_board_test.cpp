// The sim's charuco scene: the board is drawn where the world's truth says,
// so the solver is checked against a renderer that is itself checked.
#include <gtest/gtest.h>

#include <cmath>

#include "common/fsutil.h"
#include "drivers/sim/jpeg.h"
#include "drivers/sim/render.h"
#include "pipeline/calib/calibrate.h"
#include "tests/util/temp_dir.h"

namespace aggscan {
namespace {

struct CornerErrors {
  int n = 0;
  double mean = 0, max = 0, rms = 0;
  double mean_du = 0, mean_dv = 0;
};

// Renders the board at `platter_deg`, detects it and compares every corner
// with the projection of its true position.
CornerErrors RenderAndCompare(int width, int height, double platter_deg, bool jpeg) {
  test::TempDir tmp;
  Config c;
  c.camera.width = width;
  c.camera.height = height;
  c.sim.scene = "charuco";
  c.sim.board_image = tmp.path() + "/board.pgm";
  c.sim.board_x_mm = 6;
  c.sim.board_y_mm = -4;
  c.sim.board_yaw_deg = 12;
  EXPECT_TRUE(WriteBoardImage(c.calibration, c.sim.board_image, 10.0, 0.0));
  sim::SimWorld world(c, {.rock_faces = 2000});
  EXPECT_NE(world.board(), nullptr);
  sim::Renderer r(world, width, height);
  sim::RenderOptions o;
  o.noise_seed = 5;
  const sim::RenderedImage img = r.Render(1, platter_deg, o);
  const std::string path = tmp.path() + (jpeg ? "/view.jpg" : "/view.ppm");
  if (jpeg) {
    auto bytes = sim::EncodeJpeg(img.rgb.data(), width, height, c.camera.jpeg_quality);
    EXPECT_TRUE(bytes);
    EXPECT_TRUE(
        WriteFileAtomic(path, std::span<const unsigned char>(bytes->data(), bytes->size())));
  } else {
    EXPECT_TRUE(sim::WritePpm(img.rgb, width, height, path));
  }
  auto det = DetectBoardInImage(path, c.calibration);
  EXPECT_TRUE(det) << det.error().ToString();
  CornerErrors e;
  if (!det) return e;
  const double a = c.sim.board_yaw_deg * M_PI / 180;
  for (size_t k = 0; k < det->ids.size(); ++k) {
    const auto pb = BoardCornerMm(c.calibration, det->ids[k]);
    const sim::Vec3 pt{c.sim.board_x_mm + std::cos(a) * pb[0] - std::sin(a) * pb[1],
                       c.sim.board_y_mm + std::sin(a) * pb[0] + std::cos(a) * pb[1], 0};
    double u, v;
    EXPECT_TRUE(world.ProjectTurntablePoint(pt, platter_deg, r.intrinsics(), &u, &v));
    const double du = det->corners[k][0] - u, dv = det->corners[k][1] - v;
    const double d = std::hypot(du, dv);
    e.mean += d;
    e.rms += d * d;
    e.mean_du += du;
    e.mean_dv += dv;
    e.max = std::max(e.max, d);
    ++e.n;
  }
  if (e.n) e.mean /= e.n, e.rms = std::sqrt(e.rms / e.n), e.mean_du /= e.n, e.mean_dv /= e.n;
  return e;
}

TEST(SimBoard, CornersAreWhereTheTruthProjectsThem) {
  // (7-1) x (5-1) = 24 inner corners, all seen at every angle.
  for (double angle : {0.0, 77.0, 200.0}) {
    for (bool jpeg : {false, true}) {
      const CornerErrors e = RenderAndCompare(2016, 1512, angle, jpeg);
      std::printf(
          "2016x1512 %s %5.1f deg: %d corners, mean %.3f px, rms %.3f, max %.3f, bias (%.3f, "
          "%.3f)\n",
          jpeg ? "jpeg" : "ppm ", angle, e.n, e.mean, e.rms, e.max, e.mean_du, e.mean_dv);
      EXPECT_EQ(e.n, 24);
      EXPECT_LT(e.rms, 0.15);
      EXPECT_LT(e.max, 0.35);
    }
  }
  const CornerErrors half = RenderAndCompare(1008, 756, 77.0, true);
  std::printf(
      "1008x756 jpeg 77 deg: %d corners, mean %.3f px, rms %.3f, max %.3f, bias (%.3f, %.3f)\n",
      half.n, half.mean, half.rms, half.max, half.mean_du, half.mean_dv);
  EXPECT_EQ(half.n, 24);
  EXPECT_LT(half.rms, 0.25);
}

TEST(SimBoard, BoardImageMustMatchTheBoard) {
  test::TempDir tmp;
  Config c;
  c.sim.scene = "charuco";
  c.sim.board_image = tmp.path() + "/board.pgm";
  // A printable sheet (with margin) is not the squares area the sim maps.
  ASSERT_TRUE(WriteBoardImage(c.calibration, c.sim.board_image, 4.0, 10.0));
  auto w = sim::SimWorld::Create(c, {.rock_faces = 2000});
  ASSERT_FALSE(w);
  EXPECT_NE(w.error().ToString().find("--margin-mm 0"), std::string::npos) << w.error().ToString();
  c.sim.board_image = tmp.path() + "/missing.pgm";
  w = sim::SimWorld::Create(c, {.rock_faces = 2000});
  ASSERT_FALSE(w);
  EXPECT_NE(w.error().ToString().find("missing.pgm"), std::string::npos) << w.error().ToString();
}

TEST(SimBoard, CornerNumberingIsOpenCvs) {
  // BoardCornerMm against the corners found in the flat printed image itself.
  test::TempDir tmp;
  CalibrationConfig b;
  const double ppm = 4.0;
  ASSERT_TRUE(WriteBoardImage(b, tmp.path() + "/flat.png", ppm, 10.0));
  auto det = DetectBoardInImage(tmp.path() + "/flat.png", b);
  ASSERT_TRUE(det);
  ASSERT_EQ(det->ids.size(), 24u);
  for (size_t k = 0; k < det->ids.size(); ++k) {
    const auto p = BoardCornerMm(b, det->ids[k]);
    // Image x right = board x; image y down = -board y; margin 10 mm.
    const double u = (p[0] + b.squares_x * b.square_mm / 2 + 10) * ppm - 0.5;
    const double v = (b.squares_y * b.square_mm / 2 - p[1] + 10) * ppm - 0.5;
    EXPECT_NEAR(det->corners[k][0], u, 0.1) << det->ids[k];
    EXPECT_NEAR(det->corners[k][1], v, 0.1) << det->ids[k];
  }
}

}  // namespace
}  // namespace aggscan
