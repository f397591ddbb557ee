// Explicit device factory: one table per device kind maps the config's
// backend name to a constructor, so adding a backend is one line here.
#include "drivers/factory.h"

#include <string>
#include <vector>

#include "config/turntable_profile.h"
#include "drivers/evdev/evdev_button.h"
#include "drivers/gpio/gpio_button.h"
#include "drivers/gpio/gpio_light.h"
#include "drivers/manual_turntable.h"
#include "drivers/modbus/modbus_io.h"
#include "drivers/modbus/modbus_turntable.h"
#include "drivers/sim/sim_button.h"
#include "drivers/sim/sim_camera.h"
#include "drivers/sim/sim_hand.h"
#include "drivers/sim/sim_turntable.h"
#include "drivers/sim/sim_walker.h"
#include "drivers/sim/world.h"
#include "drivers/usb/usb_tic_turntable.h"
#include "drivers/v4l2/v4l2_camera.h"
#ifdef AGGSCAN_HAVE_LIBCAMERA
#include "drivers/libcamera/libcamera_camera.h"
#endif

namespace aggscan {
namespace {

// What the constructors share while one rig is being built.
struct Context {
  const Config& config;
  Clock& clock;
  RigDevices* rig;
  // Physical platter angle for the sim camera; empty when the turntable is
  // real (the sim camera then sees the platter at 0).
  std::function<double(TimeNs)> platter_angle_at;
  // Where the sim camera stands, for a camera walked round a still rock;
  // empty: the rig's fixed camera.
  std::function<sim::Rigid(TimeNs)> camera_pose_at;
  // The Modbus connection of the button, shared with a light on the same link.
  std::shared_ptr<modbus::BitLink> bit_link;
};

std::shared_ptr<modbus::BitLink> BitLinkFor(Context& ctx, const modbus::LinkSettings& s) {
  if (ctx.bit_link && ctx.bit_link->settings().SameLink(s)) return ctx.bit_link;
  ctx.bit_link = std::make_shared<modbus::BitLink>(s);
  return ctx.bit_link;
}

// The sim world is created once and shared by every sim device of the rig.
Status EnsureWorld(Context& ctx) {
  if (ctx.rig->world) return OkStatus();
  Result<std::shared_ptr<sim::SimWorld>> w = sim::SimWorld::Create(ctx.config);
  if (!w) return w.error();
  ctx.rig->world = *w;
  return OkStatus();
}

// The board of calibration captures: the charuco scene of the same rig.
Status EnsureBoardWorld(Context& ctx) {
  if (ctx.rig->board_world || ctx.config.sim.board_image.empty()) return OkStatus();
  if (ctx.config.sim.scene == "charuco") {
    ctx.rig->board_world = ctx.rig->world;
    return OkStatus();
  }
  Config board = ctx.config;
  board.sim.scene = "charuco";
  Result<std::shared_ptr<sim::SimWorld>> w = sim::SimWorld::Create(board);
  if (!w) return w.error();
  ctx.rig->board_world = *w;
  return OkStatus();
}

template <typename Device>
using Maker = Result<std::unique_ptr<Device>> (*)(Context&);

template <typename Device>
struct Backend {
  const char* name;
  Maker<Device> make;
};

Result<std::unique_ptr<Turntable>> MakeSimTurntable(Context& ctx) {
  Status s = EnsureWorld(ctx);
  if (!s) return s.error();
  auto t =
      std::make_unique<sim::SimTurntable>(ctx.clock, ctx.config.turntable, ctx.config.sim.seed);
  ctx.platter_angle_at = t->PhysicalAngleFunction();
  return std::unique_ptr<Turntable>(std::move(t));
}

// The register-map profile is loaded here, so a missing or contradictory
// profile stops start-up with its file and field named.
Result<std::unique_ptr<Turntable>> MakeModbusTurntable(Context& ctx, modbus::Transport transport) {
  const ModbusTurntableConfig& m = ctx.config.turntable.modbus;
  Result<TurntableProfile> profile = FindTurntableProfile(m.profile, m.profile_dir);
  if (!profile) return profile.error();
  return std::unique_ptr<Turntable>(std::make_unique<modbus::ModbusTurntable>(
      transport, ctx.config.turntable, std::move(*profile)));
}
Result<std::unique_ptr<Turntable>> MakeModbusTcpTurntable(Context& ctx) {
  return MakeModbusTurntable(ctx, modbus::Transport::kTcp);
}
Result<std::unique_ptr<Turntable>> MakeModbusRtuTurntable(Context& ctx) {
  return MakeModbusTurntable(ctx, modbus::Transport::kRtu);
}

// Nothing is opened here: a missing Tic is reported by Open().
Result<std::unique_ptr<Turntable>> MakeUsbTicTurntable(Context& ctx) {
  return std::unique_ptr<Turntable>(std::make_unique<usb::UsbTicTurntable>(ctx.config.turntable));
}

Result<std::unique_ptr<Camera>> MakeSimCamera(Context& ctx) {
  Status s = EnsureWorld(ctx);
  if (!s) return s.error();
  if (Status b = EnsureBoardWorld(ctx); !b) return b.error();
  auto cam = std::make_unique<sim::SimCamera>(ctx.rig->world, ctx.clock, ctx.config.camera,
                                              ctx.platter_angle_at, ctx.rig->board_world);
  if (ctx.camera_pose_at) cam->SetCameraPath(ctx.camera_pose_at);
  return std::unique_ptr<Camera>(std::move(cam));
}

// Nothing is opened here: a missing camera is reported by Open(), so the
// daemon can start and say what to check.
Result<std::unique_ptr<Camera>> MakeV4l2Camera(Context& ctx) {
  return std::unique_ptr<Camera>(std::make_unique<v4l2::V4l2Camera>(ctx.clock, ctx.config.camera));
}

// Like V4L2, nothing is opened here. A build without libcamera still knows
// the name, so the config names the missing package rather than a typo.
Result<std::unique_ptr<Camera>> MakeLibcameraCamera(Context& ctx) {
#ifdef AGGSCAN_HAVE_LIBCAMERA
  return std::unique_ptr<Camera>(
      std::make_unique<lc::LibcameraCamera>(ctx.clock, ctx.config.camera));
#else
  (void)ctx;
  return MakeError(ErrorClass::kInvalidConfig,
                   "camera.backend = \"libcamera\": this build has no libcamera support; install "
                   "libcamera-dev and rebuild (cmake -DAGGSCAN_WITH_LIBCAMERA=ON)");
#endif
}

Result<std::unique_ptr<Button>> MakeSimButton(Context& ctx) {
  Status s = EnsureWorld(ctx);  // RigDevices promises a world whenever any backend is sim
  if (!s) return s.error();
  return std::unique_ptr<Button>(std::make_unique<sim::SimButton>(ctx.clock, ctx.config.button));
}

// Nothing is opened here either: a missing chip or device is the button's
// health, reported by Start().
Result<std::unique_ptr<Button>> MakeGpioButton(Context& ctx) {
  return std::unique_ptr<Button>(std::make_unique<gpio::GpioButton>(ctx.clock, ctx.config.button));
}

Result<std::unique_ptr<Button>> MakeEvdevButton(Context& ctx) {
  return std::unique_ptr<Button>(
      std::make_unique<evdev::EvdevButton>(ctx.clock, ctx.config.button));
}
Result<std::unique_ptr<Button>> MakeModbusButton(Context& ctx) {
  return std::unique_ptr<Button>(std::make_unique<modbus::ModbusButton>(
      ctx.clock, ctx.config.button, BitLinkFor(ctx, modbus::ButtonLinkSettings(ctx.config))));
}

// The status light is optional: "none" makes no device.
Result<std::unique_ptr<StatusLight>> MakeNoLight(Context&) {
  return std::unique_ptr<StatusLight>();
}
Result<std::unique_ptr<StatusLight>> MakeGpioLight(Context& ctx) {
  return std::unique_ptr<StatusLight>(std::make_unique<gpio::GpioLight>(ctx.config.light.gpio));
}
Result<std::unique_ptr<StatusLight>> MakeModbusLight(Context& ctx) {
  return std::unique_ptr<StatusLight>(std::make_unique<modbus::ModbusLight>(
      ctx.config.light.modbus, BitLinkFor(ctx, modbus::LightLinkSettings(ctx.config))));
}

// A table turned by hand. With the sim camera, the sim's hand turns the sim
// platter at each prompt, so the whole protocol runs on the simulated rig.
Result<std::unique_ptr<Turntable>> MakeManualTurntable(Context& ctx) {
  if (ctx.config.camera.backend != "sim") {
    return std::unique_ptr<Turntable>(std::make_unique<ManualTurntable>());
  }
  Status s = EnsureWorld(ctx);
  if (!s) return s.error();
  if (ctx.config.capture.mode == "moving_camera") {
    // The table stays put; the sim's operator walks the sim camera round it.
    auto walker = std::make_shared<sim::SimWalker>(ctx.clock, ctx.config);
    ctx.camera_pose_at = walker->CameraFunction();
    return std::unique_ptr<Turntable>(std::make_unique<ManualTurntable>(
        [walker](double, double) { walker->Step(); }, [walker] { walker->Home(); }));
  }
  auto hand = std::make_shared<sim::SimHand>(ctx.clock, ctx.config);
  ctx.platter_angle_at = hand->AngleFunction();
  return std::unique_ptr<Turntable>(std::make_unique<ManualTurntable>(
      [hand](double from_deg, double to_deg) { hand->Turn(from_deg, to_deg); }));
}

// Real backends (modbus-rtu, usb, v4l2, gpio, ...) join these tables.
const Backend<Turntable> kTurntables[] = {{"sim", MakeSimTurntable},
                                          {"modbus-tcp", MakeModbusTcpTurntable},
                                          {"modbus-rtu", MakeModbusRtuTurntable},
                                          {"usb-tic", MakeUsbTicTurntable},
                                          {"manual", MakeManualTurntable}};
const Backend<Camera> kCameras[] = {
    {"sim", MakeSimCamera}, {"v4l2", MakeV4l2Camera}, {"libcamera", MakeLibcameraCamera}};
const Backend<Button> kButtons[] = {{"sim", MakeSimButton},
                                    {"gpio", MakeGpioButton},
                                    {"evdev", MakeEvdevButton},
                                    {"modbus", MakeModbusButton}};
const Backend<StatusLight> kLights[] = {
    {"none", MakeNoLight}, {"gpio", MakeGpioLight}, {"modbus", MakeModbusLight}};

template <typename Device, size_t N>
const Backend<Device>* Find(const Backend<Device> (&table)[N], const std::string& name) {
  for (const auto& b : table)
    if (name == b.name) return &b;
  return nullptr;
}

template <typename Device, size_t N>
std::string UnknownMessage(const char* key, const std::string& name,
                           const Backend<Device> (&table)[N]) {
  std::string known;
  for (const auto& b : table) known += (known.empty() ? "" : ", ") + std::string(b.name);
  return std::string(key) + " \"" + name + "\" is not known; available: " + known;
}

}  // namespace

Result<RigDevices> CreateRig(const Config& config, Clock& clock) {
  // Check every name first so one error lists every unknown backend.
  const auto* turntable = Find(kTurntables, config.turntable.backend);
  const auto* camera = Find(kCameras, config.camera.backend);
  const auto* button = Find(kButtons, config.button.backend);
  std::vector<std::string> unknown;
  if (!camera) unknown.push_back(UnknownMessage("camera.backend", config.camera.backend, kCameras));
  if (!turntable)
    unknown.push_back(UnknownMessage("turntable.backend", config.turntable.backend, kTurntables));
  if (!button) unknown.push_back(UnknownMessage("button.backend", config.button.backend, kButtons));
  const auto* light = Find(kLights, config.light.backend);
  if (!light) unknown.push_back(UnknownMessage("light.backend", config.light.backend, kLights));
  if (!unknown.empty()) {
    std::string msg;
    for (const auto& u : unknown) msg += (msg.empty() ? "" : "; ") + u;
    return MakeError(ErrorClass::kInvalidConfig, msg);
  }

  RigDevices rig;
  Context ctx{config, clock, &rig, {}, {}, {}};
  // The turntable first: the sim camera needs its platter angle.
  auto t = turntable->make(ctx);
  if (!t) return t.error();
  rig.turntable = std::move(*t);
  auto c = camera->make(ctx);
  if (!c) return c.error();
  rig.camera = std::move(*c);
  auto b = button->make(ctx);
  if (!b) return b.error();
  rig.button = std::move(*b);
  auto l = light->make(ctx);
  if (!l) return l.error();
  rig.light = std::move(*l);
  return rig;
}

CameraSettings CameraSettingsFor(const Config& config) {
  CameraSettings cs;
  cs.width = config.camera.width;
  cs.height = config.camera.height;
  cs.jpeg_quality = config.camera.jpeg_quality;
  cs.manual_exposure = config.camera.exposure.manual;
  cs.exposure_us = config.camera.exposure.exposure_us;
  cs.gain = config.camera.exposure.gain;
  cs.wb_red = config.camera.exposure.wb_red;
  cs.wb_blue = config.camera.exposure.wb_blue;
  return cs;
}

}  // namespace aggscan
