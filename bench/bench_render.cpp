// Sim renderer throughput on one core. Target: <= 150 ms per 2016x1512 frame
// of a 100k-face rock in Release. Build build type Release and run e.g.
//   taskset -c 0 ./bench/bench_render --benchmark_min_time=2s
#include <benchmark/benchmark.h>

#include <map>
#include <memory>

#include "drivers/sim/jpeg.h"
#include "drivers/sim/render.h"

namespace {

using aggscan::Config;
using aggscan::sim::RenderedImage;
using aggscan::sim::Renderer;
using aggscan::sim::RenderOptions;
using aggscan::sim::SimWorld;

const SimWorld& World(int faces) {
  static std::map<int, std::unique_ptr<SimWorld>> worlds;
  auto& w = worlds[faces];
  if (!w) {
    Config c;
    c.sim.seed = 7;
    c.sim.rock_size_mm = 150.0;
    w = std::make_unique<SimWorld>(c, aggscan::sim::SimWorldOptions{.rock_faces = faces});
  }
  return *w;
}

// Args: width, height, faces.
void BM_Render(benchmark::State& state) {
  const int w = static_cast<int>(state.range(0)), h = static_cast<int>(state.range(1));
  const SimWorld& world = World(static_cast<int>(state.range(2)));
  Renderer r(world, w, h);
  RenderOptions o;
  RenderedImage img;
  int view = 0;
  for (auto _ : state) {
    o.noise_seed = static_cast<uint64_t>(view);
    r.RenderInto(1, 12.0 * view++, o, &img);
    benchmark::DoNotOptimize(img.rgb.data());
  }
  state.counters["faces"] = static_cast<double>(world.rock().faces.size());
}
BENCHMARK(BM_Render)
    ->Args({2016, 1512, 100000})
    ->Args({2016, 1512, 20000})
    ->Args({4032, 3024, 100000})
    ->Unit(benchmark::kMillisecond);

// Worst case: a new exposure every frame, so the cached static background
// (disc, rim, table) is re-shaded too. A capture locks exposure, so this
// happens once per capture.
void BM_RenderNewExposure(benchmark::State& state) {
  const SimWorld& world = World(100000);
  Renderer r(world, 2016, 1512);
  RenderOptions o;
  RenderedImage img;
  int view = 0;
  for (auto _ : state) {
    o.exposure.exposure_us = 8000.0 + view;
    r.RenderInto(1, 12.0 * view++, o, &img);
  }
}
BENCHMARK(BM_RenderNewExposure)->Unit(benchmark::kMillisecond);

void BM_RenderWithMask(benchmark::State& state) {
  const SimWorld& world = World(100000);
  Renderer r(world, 2016, 1512);
  RenderOptions o;
  o.want_mask = true;
  RenderedImage img;
  int view = 0;
  for (auto _ : state) r.RenderInto(1, 12.0 * view++, o, &img);
}
BENCHMARK(BM_RenderWithMask)->Unit(benchmark::kMillisecond);

// Scene "charuco" (a calibration capture): the board on the disc, no rock;
// the board's pixels are shaded per frame.
void BM_RenderCharuco(benchmark::State& state) {
  // A 2100 x 1500 checker PGM stands in for the printed board (same cost).
  const std::string path = "/tmp/aggscan-bench-board.pgm";
  std::vector<uint8_t> px(2100 * 1500);
  for (int y = 0; y < 1500; ++y)
    for (int x = 0; x < 2100; ++x) px[y * 2100 + x] = ((x / 300 + y / 300) % 2) ? 255 : 0;
  if (!aggscan::sim::WritePgm(px, 2100, 1500, path))
    state.SkipWithError("cannot write the board PGM");
  Config c;
  c.sim.scene = "charuco";
  c.sim.board_image = path;
  c.sim.board_yaw_deg = 12.0;
  const SimWorld world(c, aggscan::sim::SimWorldOptions{.rock_faces = 2000});
  Renderer r(world, static_cast<int>(state.range(0)), static_cast<int>(state.range(1)));
  RenderOptions o;
  RenderedImage img;
  int view = 0;
  for (auto _ : state) {
    o.noise_seed = static_cast<uint64_t>(view);
    r.RenderInto(1, 12.0 * view++, o, &img);
    benchmark::DoNotOptimize(img.rgb.data());
  }
}
BENCHMARK(BM_RenderCharuco)->Args({2016, 1512})->Unit(benchmark::kMillisecond);

void BM_EncodeJpeg(benchmark::State& state) {
  const int w = static_cast<int>(state.range(0)), h = static_cast<int>(state.range(1));
  Renderer r(World(100000), w, h);
  const RenderedImage img = r.Render(1, 0.0, {});
  for (auto _ : state) {
    auto jpeg = aggscan::sim::EncodeJpeg(img.rgb.data(), w, h, 92);
    benchmark::DoNotOptimize(jpeg.ok());
  }
}
BENCHMARK(BM_EncodeJpeg)->Args({2016, 1512})->Args({4032, 3024})->Unit(benchmark::kMillisecond);

void BM_BuildWorld(benchmark::State& state) {
  Config c;
  c.sim.seed = 11;
  for (auto _ : state) {
    SimWorld w(c, {.rock_faces = static_cast<int>(state.range(0))});
    benchmark::DoNotOptimize(w.volume_mm3());
  }
}
BENCHMARK(BM_BuildWorld)->Arg(20000)->Arg(100000)->Unit(benchmark::kMillisecond)->Iterations(2);

}  // namespace

BENCHMARK_MAIN();
