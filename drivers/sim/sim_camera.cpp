#include "drivers/sim/sim_camera.h"

#include <algorithm>
#include <cmath>
#include <future>
#include <utility>

#include "common/log.h"
#include "drivers/sim/jpeg.h"
#include "drivers/sim/render.h"

namespace aggscan::sim {

namespace {

uint64_t Mix(uint64_t h, uint64_t v) {
  h ^= v + 0x9E3779B97F4A7C15ull + (h << 6) + (h >> 2);
  h ^= h >> 31;
  h *= 0xBF58476D1CE4E5B9ull;
  return h ^ (h >> 29);
}

}  // namespace

SimCamera::SimCamera(std::shared_ptr<const SimWorld> world, Clock& clock,
                     const CameraConfig& config, AngleFn platter_angle_at,
                     std::shared_ptr<const SimWorld> board_world)
    : world_(std::move(world)),
      board_world_(std::move(board_world)),
      clock_(clock),
      config_(config),
      angle_at_(std::move(platter_angle_at)) {
  if (!angle_at_) angle_at_ = [](TimeNs) { return 0.0; };
}

SimCamera::~SimCamera() { DoClose(); }

CameraInfo SimCamera::Info() const { return {config_.id, "sim", "aggscan simulated camera"}; }

void SimCamera::SetTruthSink(TruthSink sink) {
  std::lock_guard<std::mutex> l(mu_);
  truth_sink_ = std::move(sink);
}

void SimCamera::SetCameraPath(PoseFn pose_at) {
  std::lock_guard<std::mutex> l(mu_);
  pose_at_ = std::move(pose_at);
}

uint64_t SimCamera::frames_rendered() const {
  std::lock_guard<std::mutex> l(mu_);
  return sequence_;
}

Status SimCamera::DoOpen() {
  if (!world_) return MakeError(ErrorClass::kDeviceMissing, "sim camera has no sim world");
  std::lock_guard<std::mutex> l(mu_);
  stop_ = false;
  worker_ = std::thread([this] { WorkerLoop(); });
  return OkStatus();
}

Status SimCamera::DoConfigure(const CameraSettings& settings) {
  // Like a real camera, the sim is ready to shoot once configured: build the
  // renderer's tables and shade the background for these settings now, on the
  // camera's thread, so the first still of a capture is not late.
  std::promise<void> warmed;
  std::future<void> done = warmed.get_future();
  {
    std::lock_guard<std::mutex> l(mu_);
    active_ = settings;
    if (!worker_.joinable() || stop_) return OkStatus();
    Job job;
    job.warmup = true;
    job.done = [&warmed](const Result<FramePtr>&) { warmed.set_value(); };
    queue_.push_back(std::move(job));
  }
  cv_.notify_one();
  done.wait();
  return OkStatus();
}

Status SimCamera::DoRequestStill(const StillRequest& req, FrameCallback done) {
  std::lock_guard<std::mutex> l(mu_);
  if (!worker_.joinable() || stop_)
    return MakeError(ErrorClass::kInvalidState, "sim camera is not running");
  queue_.push_back({req, std::move(done)});
  cv_.notify_one();
  return OkStatus();
}

void SimCamera::DoClose() {
  std::thread t;
  {
    std::lock_guard<std::mutex> l(mu_);
    stop_ = true;
    t = std::move(worker_);
  }
  cv_.notify_all();
  if (t.joinable()) t.join();  // the worker drains the queue first
}

void SimCamera::WorkerLoop() {
  for (;;) {
    Job job;
    {
      std::unique_lock<std::mutex> l(mu_);
      cv_.wait(l, [this] { return stop_ || !queue_.empty(); });
      if (queue_.empty()) return;  // stopping and nothing left in flight
      job = std::move(queue_.front());
      queue_.pop_front();
    }
    Serve(job);
  }
}

void SimCamera::Serve(Job& job) {
  CameraSettings s;
  TruthSink sink;
  PoseFn pose_at;
  {
    std::lock_guard<std::mutex> l(mu_);
    s = active_;
    sink = truth_sink_;
    pose_at = pose_at_;
  }
  // Trigger: the exposure starts now; the platter angle is taken mid-exposure.
  const TimeNs start = clock_.Now();
  const int64_t utc = clock_.UtcNs();
  const double exposure_us =
      s.manual_exposure ? s.exposure_us : world_->config().camera.exposure.exposure_us;
  const double gain = s.manual_exposure ? s.gain : world_->config().camera.exposure.gain;
  const double angle =
      job.warmup ? 0.0 : angle_at_(start + static_cast<TimeNs>(exposure_us * 500.0));

  if (!renderer_ || renderer_->width() != s.width || renderer_->height() != s.height) {
    renderer_ = std::make_unique<Renderer>(*world_, s.width, s.height);
  }
  RenderOptions opt;
  if (job.warmup) {
    opt.exposure = {exposure_us, gain, s.wb_red, s.wb_blue};
    (void)renderer_->Render(1, 0.0, opt);
    // The board's tables too: its first view must not wait for them.
    if (board_world_) {
      board_renderer_ = std::make_unique<Renderer>(*board_world_, s.width, s.height);
      (void)board_renderer_->Render(1, 0.0, opt);
    }
    job.done(MakeError(ErrorClass::kInternal, "warm-up"));
    return;
  }
  if (job.req.board) {
    if (!board_world_) {
      job.done(MakeError(ErrorClass::kInvalidConfig,
                         "the sim camera has no calibration board to draw: set sim.board_image "
                         "(write it with `aggscan calibrate board --out FILE.pgm --margin-mm 0`)"));
      return;
    }
    if (!board_renderer_ || board_renderer_->width() != s.width ||
        board_renderer_->height() != s.height) {
      board_renderer_ = std::make_unique<Renderer>(*board_world_, s.width, s.height);
    }
  }
  Renderer& renderer = job.req.board ? *board_renderer_ : *renderer_;
  opt.exposure = {exposure_us, gain, s.wb_red, s.wb_blue};
  opt.noise_seed = Mix(
      Mix(Mix(world_->config().sim.seed, 0x53494D43414DULL), static_cast<uint64_t>(job.req.side)),
      static_cast<uint64_t>(job.req.view));
  // No rock, no rock truth on a board.
  if (job.req.board) sink = nullptr;
  opt.want_mask = static_cast<bool>(sink);
  if (pose_at && !job.req.board) {
    renderer.SetCamera(pose_at(start + static_cast<TimeNs>(exposure_us * 500.0)));
  }
  RenderedImage img = renderer.Render(job.req.side, angle, opt);
  // A platter turning during the exposure (a table turned by hand, late)
  // smears the photo: the average of sub-frames over the exposure, one per
  // ~0.1 deg of turn. The truth stays the mid-exposure pose.
  if (!job.req.board) {
    const auto exposure = static_cast<TimeNs>(exposure_us * 1000.0);
    const double swept = std::abs(angle_at_(start + exposure) - angle_at_(start));
    if (swept > 0.05) {
      const int k = std::min(32, static_cast<int>(std::ceil(swept / 0.1)) + 1);
      std::vector<float> sum(img.rgb.size(), 0.0f);
      RenderOptions sub = opt;
      sub.want_mask = false;
      for (int i = 0; i < k; ++i) {
        const TimeNs t = start + static_cast<TimeNs>((i + 0.5) / k * static_cast<double>(exposure));
        const RenderedImage f = renderer.Render(job.req.side, angle_at_(t), sub);
        for (size_t p = 0; p < sum.size(); ++p) sum[p] += f.rgb[p];
      }
      for (size_t p = 0; p < sum.size(); ++p)
        img.rgb[p] = static_cast<uint8_t>(std::lround(sum[p] / static_cast<float>(k)));
    }
  }

  Result<std::vector<unsigned char>> jpeg =
      EncodeJpeg(img.rgb.data(), img.width, img.height, s.jpeg_quality);
  if (!jpeg) {
    job.done(jpeg.error());
    return;
  }
  auto frame = std::make_shared<Frame>();
  frame->request_id = job.req.request_id;
  {
    std::lock_guard<std::mutex> l(mu_);
    frame->sequence = sequence_++;
  }
  frame->width = img.width;
  frame->height = img.height;
  frame->encoding = "jpeg";
  frame->data = std::move(jpeg).value();
  frame->exposure_start = start;
  frame->utc_ns = utc;
  frame->exposure_us = exposure_us;
  frame->gain = gain;
  frame->wb_red = s.wb_red;
  frame->wb_blue = s.wb_blue;

  if (sink) {
    TruthView truth;
    truth.side = job.req.side;
    truth.view = job.req.view;
    truth.platter_deg = angle;
    truth.width = img.width;
    truth.height = img.height;
    truth.mask = std::move(img.mask);
    truth.rock_to_camera = renderer.camera() * world_->RockToWorld(job.req.side, angle);
    truth.rock_to_camera_4x4 = truth.rock_to_camera.Matrix4();
    truth.intrinsics = renderer_->intrinsics();
    sink(job.req, truth);
  }
  job.done(FramePtr(std::move(frame)));
}

}  // namespace aggscan::sim
