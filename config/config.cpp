// Config loading, validation and printing, driven by declarative field tables.
//
// Every config field is one line in Fields() (or MarkerFields()): its dotted
// key (the member path itself, so the TOML key and the struct cannot drift),
// its type (taken from the member), the values it accepts and its comment.
// Parsing, range validation and ConfigToToml all walk those tables, so adding
// a field to config.h and one line here is all it takes.
#include "config/config.h"

#include <arpa/inet.h>
#include <toml++/toml.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <type_traits>
#include <variant>

#include "common/fsutil.h"

namespace aggscan {
namespace {

// ---------------------------------------------------------------------------
// Field tables

struct DurRef {
  TimeNs* p;
};
struct OptDurRef {
  std::optional<TimeNs>* p;
};
// A typed pointer to one field. int64_t members are always durations (TimeNs)
// and go through DurRef, so a plain integer field must be int or uint64_t.
using Ref = std::variant<bool*, int*, uint64_t*, double*, std::string*, DurRef,
                         std::optional<double>*, OptDurRef>;

inline Ref DurationRef(TimeNs* p) { return DurRef{p}; }
inline Ref DurationRef(std::optional<TimeNs>* p) { return OptDurRef{p}; }

constexpr double kInf = std::numeric_limits<double>::infinity();

// Which values a field accepts.
struct Check {
  enum Kind { kAny, kRange, kOneOf, kBackend, kNonEmpty };
  Kind kind = kAny;
  double lo = -kInf;
  double hi = kInf;
  bool lo_open = false;                // lo itself is not allowed ("> 0")
  std::vector<std::string> choices;    // kOneOf
  const char* backend_kind = nullptr;  // kBackend: KnownBackends(backend_kind)
};

Check Any() { return {}; }
Check Range(double lo, double hi) { return {Check::kRange, lo, hi, false, {}, nullptr}; }
Check Above(double lo, double hi = kInf) { return {Check::kRange, lo, hi, true, {}, nullptr}; }
Check OneOf(std::vector<std::string> v) {
  return {Check::kOneOf, -kInf, kInf, false, std::move(v), nullptr};
}
Check Backend(const char* kind) { return {Check::kBackend, -kInf, kInf, false, {}, kind}; }
Check NonEmpty() { return {Check::kNonEmpty, -kInf, kInf, false, {}, nullptr}; }

constexpr double kSec = static_cast<double>(kNsPerSec);
constexpr double kMs = static_cast<double>(kNsPerMs);

template <class S>
struct Field {
  const char* key;      // dotted TOML key, relative to S
  Ref (*ref)(S&);       // the member
  Check check;          // accepted values
  const char* comment;  // written above the key by ConfigToToml
};

// One line per field. The key is the member path, stringified.
// clang-format off
// NOLINTBEGIN(bugprone-macro-parentheses): S is a type, path a member path.
#define AGG_FIELD(S, path, check, comment) \
  Field<S>{#path, [](S& s) -> Ref { return &s.path; }, check, comment}
#define AGG_DURATION(S, path, check, comment) \
  Field<S>{#path, [](S& s) -> Ref { return DurationRef(&s.path); }, check, comment}
// NOLINTEND(bugprone-macro-parentheses)
// clang-format on
#define F(path, check, comment) AGG_FIELD(Config, path, check, comment)
#define D(path, check, comment) AGG_DURATION(Config, path, check, comment)

const std::vector<std::string>& LogLevels() {
  static const std::vector<std::string> k = {"error", "warning", "notice", "info", "debug"};
  return k;
}
const std::vector<std::string>& MarkerColors() {
  static const std::vector<std::string> k = {"red", "green", "blue", "yellow"};
  return k;
}
// ArUco dictionaries by OpenCV name, with their marker counts (a board needs
// one marker per white square; an ArUco scale marker's id must be below it).
const std::vector<std::pair<std::string, int>>& BoardDictionaries() {
  static const std::vector<std::pair<std::string, int>> k = {
      {"DICT_4X4_50", 50},     {"DICT_4X4_100", 100},        {"DICT_4X4_250", 250},
      {"DICT_4X4_1000", 1000}, {"DICT_5X5_50", 50},          {"DICT_5X5_100", 100},
      {"DICT_5X5_250", 250},   {"DICT_5X5_1000", 1000},      {"DICT_6X6_50", 50},
      {"DICT_6X6_100", 100},   {"DICT_6X6_250", 250},        {"DICT_6X6_1000", 1000},
      {"DICT_7X7_50", 50},     {"DICT_7X7_100", 100},        {"DICT_7X7_250", 250},
      {"DICT_7X7_1000", 1000}, {"DICT_ARUCO_ORIGINAL", 1024}};
  return k;
}
const std::vector<std::string>& BoardDictionaryNames() {
  static const std::vector<std::string> k = [] {
    std::vector<std::string> v;
    for (const auto& d : BoardDictionaries()) v.push_back(d.first);
    return v;
  }();
  return k;
}
const std::vector<std::string>& Profiles() {
  static const std::vector<std::string> k = {"paper", "full-turn", "custom"};
  return k;
}

const std::vector<Field<Config>>& Fields() {
  static const std::vector<Field<Config>> k = {
      F(daemon.state_dir, NonEmpty(),
        "samples/, queue.db and calibration live here (absolute path for a service)"),
      F(daemon.listen_address, NonEmpty(), "HTTP API bind address"),
      F(daemon.listen_port, Range(0, 65535), "HTTP API port (0 = pick a free one, tests)"),
      F(daemon.log_level, OneOf(LogLevels()), "error | warning | notice | info | debug"),
      F(daemon.time_scale, Range(1, 1000),
        "sim rig only: clock runs this many times faster than real time (1..1000); above 1 with "
        "any real device is an error"),
      D(daemon.reopen_backoff_min, Range(10 * kMs, 600 * kSec),
        "first retry of a device that failed to open (real time); doubles per failure"),
      D(daemon.reopen_backoff_max, Range(10 * kMs, 3600 * kSec),
        "longest wait between retries of an unhealthy device; reset when it opens"),
      D(daemon.health_probe_interval, Range(0, 3600 * kSec),
        "read the turntable's status this often while no side runs, so health notices a lost "
        "controller before a capture does (0 = off)"),
      F(daemon.allowed_hosts, Any(),
        "Host names the API answers to besides localhost, 127.0.0.1, [::1] and listen_address "
        "(DNS-rebinding defence): comma-separated, each with or without :port, e.g. "
        "\"rig.local, 192.168.1.20\""),
      F(daemon.allowed_origins, Any(),
        "web origins allowed to change state (POST) besides those of the allowed hosts: "
        "comma-separated, e.g. \"http://console.local:8080\""),
      D(daemon.preview_interval, Range(0, 60 * kSec),
        "live camera view (GET /api/v1/preview): one still this often while a screen watches "
        "and no side runs (0 = no live view)"),
      F(daemon.preview_max_side, Range(64, 4096),
        "live view frames are scaled down to at most this many pixels on their longer side"),
      F(daemon.credentials_file, Any(),
        "accounts every API request is checked against (name:role:hash lines, mode 600; "
        "`aggscan user add NAME --role operator|viewer --file FILE`); empty = no credentials, "
        "allowed only when listen_address is a loopback address"),
      F(daemon.tls_certificate, Any(),
        "PEM certificate (chain) of the API's HTTPS; with tls_key; empty = plain HTTP"),
      F(daemon.tls_key, Any(), "PEM private key of tls_certificate (readable by the service only)"),
      F(daemon.web_root, Any(),
        "folder of the operator's console served at / (index.html and ui/); empty = the one "
        "installed beside the binaries"),

      F(capture.profile, OneOf(Profiles()),
        "paper (fixes sides 2, views_per_side 30, step_deg 30, interval 2s) | "
        "full-turn (step_deg = 360/views_per_side) | custom (every value as given)"),
      F(capture.mode, OneOf({"turntable", "moving_camera"}),
        "turntable (the rock turns before a fixed camera) | moving_camera (the rock lies still "
        "and the operator walks the camera round it; turntable.backend = \"manual\")"),
      F(capture.sides, Range(1, 4), "poses of the rock (operator flips between sides)"),
      F(capture.views_per_side, Range(1, 360), "photos per side"),
      F(capture.step_deg, Above(0, 360),
        "turntable step between views, degrees (full-turn: 360/views_per_side)"),
      D(capture.interval, Above(0, 3600 * kSec), "view i of a side is due at t0 + i*interval"),
      D(capture.settle, Range(0, 10 * kSec),
        "wait after in-position before the shot (platter oscillation)"),
      D(capture.home_timeout, Above(0, 3600 * kSec), "homing must finish within this"),
      D(capture.move_timeout, Above(0, 3600 * kSec), "one step must reach in-position within this"),
      D(capture.frame_timeout, Above(0, 3600 * kSec),
        "a still must arrive within this after the trigger"),
      D(capture.poll_interval, Above(0, 10 * kSec), "turntable status polling period while moving"),
      D(capture.stall_timeout, Above(0, 600 * kSec),
        "moving but position unchanged this long = stalled"),
      F(capture.comm_retries, Range(0, 10), "turntable communication retries before a fault"),

      F(camera.backend, Backend("camera"), "camera backend: sim | v4l2 | libcamera"),
      F(camera.id, NonEmpty(), "camera id recorded in every sidecar"),
      F(camera.device, Any(),
        "device path or udev name for real backends, e.g. /dev/aggscan/camera or a /dev/v4l/by-id "
        "name"),
      F(camera.width, Range(16, 16384), "still width, pixels"),
      F(camera.height, Range(16, 16384), "still height, pixels"),
      F(camera.jpeg_quality, Range(1, 100), "1..100, when the driver encodes JPEG itself"),
      F(camera.lens_focal_mm, Range(0, 1000),
        "the lens's nominal focal length, mm (0 = unknown); with sensor_width_mm, the SfM "
        "path's focal when the rig has no calibration"),
      F(camera.sensor_width_mm, Range(0, 100),
        "the sensor's active width at this resolution, mm (0 = unknown; a cropping mode "
        "narrows it)"),
      F(camera.exposure.manual, Any(), "lock exposure so all views of a rock share it"),
      F(camera.exposure.exposure_us, Above(0, 10'000'000), "shutter time, microseconds"),
      F(camera.exposure.gain, Range(1, 64), "analogue gain (1.0 = base ISO)"),
      F(camera.exposure.wb_red, Above(0, 16), "white balance red gain, locked like exposure"),
      F(camera.exposure.wb_blue, Above(0, 16), "white balance blue gain, locked like exposure"),
      F(camera.v4l2.pixel_format,
        OneOf({"auto", "mjpeg", "yuyv", "uyvy", "nv12", "rgb24", "bgr24", "grey"}),
        "auto (MJPEG if offered, else a raw format encoded to JPEG) | mjpeg | yuyv | uyvy | nv12 | "
        "rgb24 | bgr24 | grey"),
      F(camera.v4l2.buffers, Range(2, 32), "mmap buffers requested from the driver"),
      D(camera.v4l2.frame_timeout, Above(0, 600 * kSec),
        "no frame this long after a still request = camera timeout"),
      F(camera.v4l2.gain_unit, Range(0, 1'000'000),
        "device gain value meaning gain 1.0 (0 = the gain control's default value)"),
      F(camera.v4l2.focus, Range(-1, 1'000'000),
        "manual focus position in device units (FOCUS_ABSOLUTE); -1 = leave focus alone"),
      F(camera.v4l2.strict_controls, Any(),
        "refuse to configure when the device lacks a control for a locked setting"),
      F(camera.libcamera.camera_id, Any(),
        "libcamera camera id as `cam -l` lists it; empty = the camera at index"),
      F(camera.libcamera.index, Range(0, 63),
        "position in libcamera's camera list (camera_id empty)"),
      F(camera.libcamera.role, OneOf({"still", "raw", "video", "viewfinder"}),
        "stream role asked of the pipeline: still | raw | video | viewfinder"),
      F(camera.libcamera.pixel_format,
        OneOf({"auto", "mjpeg", "yuyv", "uyvy", "nv12", "rgb888", "bgr888", "r8"}),
        "auto (the pipeline's choice for the role) | mjpeg | yuyv | uyvy | nv12 | rgb888 | "
        "bgr888 | r8 (libcamera/DRM names: bgr888 is R, G, B in memory)"),
      F(camera.libcamera.buffers, Range(0, 32),
        "frame buffers to allocate; 0 = the pipeline's default"),
      D(camera.libcamera.frame_timeout, Above(0, 600 * kSec),
        "no completed frame this long after a still request = camera timeout"),
      F(camera.libcamera.strict_controls, Any(),
        "refuse to configure when the camera lacks a control for a locked setting"),

      F(turntable.backend, Backend("turntable"),
        "turntable backend: sim | modbus-tcp | modbus-rtu | usb-tic | manual (turned by hand)"),
      D(turntable.manual_hands_off, Range(0, 60 * kSec),
        "manual: the prompt to turn ends this long before the next view is due"),
      F(turntable.max_speed_deg_s, Above(0, 3600), "trapezoidal profile speed limit, degrees/s"),
      F(turntable.accel_deg_s2, Above(0, 36000),
        "trapezoidal profile acceleration limit, degrees/s^2"),
      F(turntable.repeatability_deg, Range(0, 5),
        "sim: 1-sigma random angle error per move, degrees"),
      F(turntable.backlash_deg, Range(0, 5), "sim: lost motion on direction reversal, degrees"),
      F(turntable.settle_amplitude_deg, Range(0, 10),
        "sim: oscillation amplitude when the move ends, degrees"),
      D(turntable.settle_time_constant, Above(0, 10 * kSec),
        "sim: exponential decay of that oscillation"),
      F(turntable.settle_frequency_hz, Above(0, 100), "sim: its frequency, Hz"),
      D(turntable.home_duration, Range(0, 600 * kSec), "sim: homing time"),
      F(turntable.faults.stall_at_deg, Range(-3600, 3600),
        "motion stops at this absolute angle, degrees (stall)"),
      F(turntable.faults.timeout_every_n_moves, Range(0, 1'000'000),
        "every n-th move the controller stops answering (0 = never)"),
      D(turntable.faults.disconnect_after, Above(0), "device disappears this long after open"),
      F(turntable.modbus.profile, NonEmpty(),
        "register-map profile: a name in profile_dir (generic, leadshine-iem-rs) or a .toml path"),
      F(turntable.modbus.profile_dir, Any(), "where profile names are looked up"),
      F(turntable.modbus.unit_id, Range(0, 255), "Modbus unit (slave) id; RTU: 1..247"),
      F(turntable.modbus.host, Any(), "modbus-tcp: controller or gateway address"),
      F(turntable.modbus.port, Range(1, 65535), "modbus-tcp: port (502 is Modbus/TCP's)"),
      F(turntable.modbus.device, Any(),
        "modbus-rtu: serial device, e.g. /dev/ttyUSB0 or /dev/aggscan/turntable"),
      F(turntable.modbus.baud, Range(300, 4'000'000), "modbus-rtu: line speed, bit/s"),
      F(turntable.modbus.parity, OneOf({"none", "even", "odd"}), "modbus-rtu: none | even | odd"),
      F(turntable.modbus.data_bits, Range(5, 8), "modbus-rtu: data bits, 5..8 (Modbus RTU: 8)"),
      F(turntable.modbus.stop_bits, Range(1, 2), "modbus-rtu: stop bits, 1 | 2"),
      F(turntable.modbus.rs485, Any(),
        "modbus-rtu: switch the port to RS-485 mode (TIOCSRS485) where the adapter supports it"),
      D(turntable.modbus.response_timeout, Above(0, 10 * kSec),
        "one request must be answered within this"),
      F(turntable.modbus.retries, Range(0, 10),
        "a request without an answer is repeated this many times"),
      F(turntable.modbus.motor_steps_per_rev, Range(1, 1'000'000),
        "full steps (or encoder counts) per motor revolution"),
      F(turntable.modbus.microsteps, Range(1, 100'000), "microstepping factor set on the drive"),
      F(turntable.modbus.gear_ratio, Above(0, 10'000),
        "motor revolutions per platter revolution (steps/rev = motor steps x microsteps x this)"),
      F(turntable.modbus.shortest_path, Any(),
        "go to the target's position modulo 360 the shorter way round (angles stay cumulative)"),
      F(turntable.modbus.backlash_comp_deg, Range(0, 10),
        "approach every target from one side, overshooting by this many degrees (0 = off)"),
      F(turntable.modbus.backlash_approach, OneOf({"positive", "negative"}),
        "positive | negative: the direction every target is finally approached in"),
      F(turntable.modbus.in_position_window_deg, Above(0, 10),
        "in-position also needs the measured angle this close to the target, degrees"),
      F(turntable.usb.serial_number, Any(),
        "the Tic's USB serial number (ticcmd --list, lsusb -v); empty = the only Tic attached"),
      F(turntable.usb.vendor_id, Range(0, 0xFFFF), "USB vendor ID (0x1FFB, Pololu)"),
      F(turntable.usb.product_id, Range(0, 0xFFFF),
        "USB product ID; 0 = any Tic (T825 0xB3, T834 0xB5, T500 0xBD, N825 0xC3, T249 0xC9, "
        "36v4 0xCB)"),
      F(turntable.usb.motor_steps_per_rev, Range(1, 1'000'000), "full steps per motor revolution"),
      F(turntable.usb.microsteps, Range(1, 256),
        "step mode set on open: 1 2 4 8 16 32 (36v4 also 64 128 256)"),
      F(turntable.usb.gear_ratio, Above(0, 10'000),
        "motor revolutions per platter revolution (steps/rev = motor steps x microsteps x this)"),
      F(turntable.usb.home, OneOf({"reverse", "forward", "here"}),
        "reverse | forward: the Tic's homing run toward its limit switch; here: the platter's "
        "place when homing is angle 0"),
      D(turntable.usb.timeout, Above(0, 10 * kSec),
        "one USB control transfer must end within this"),
      F(turntable.usb.shortest_path, Any(),
        "go to the target's position modulo 360 the shorter way round (angles stay cumulative)"),
      F(turntable.usb.backlash_comp_deg, Range(0, 10),
        "approach every target from one side, overshooting by this many degrees (0 = off)"),
      F(turntable.usb.backlash_approach, OneOf({"positive", "negative"}),
        "positive | negative: the direction every target is finally approached in"),
      F(turntable.usb.in_position_window_deg, Above(0, 10),
        "in-position also needs the position this close to the target, degrees"),

      F(button.backend, Backend("button"), "button backend: sim | gpio | evdev | modbus"),
      D(button.debounce, Range(0, 1 * kSec), "presses closer than this are one press"),
      F(button.gpio.chip, NonEmpty(),
        "gpio: chip name (gpiochip0), path (/dev/gpiochip0), number or label"),
      F(button.gpio.line, NonEmpty(), "gpio: line offset (\"17\") or line name (\"start\")"),
      F(button.gpio.active_low, Any(), "gpio: pressed = low level (a switch to ground)"),
      F(button.gpio.bias, OneOf({"as-is", "pull-up", "pull-down", "disable"}),
        "gpio: as-is | pull-up | pull-down | disable (pull-up for a switch to ground)"),
      F(button.evdev.device, Any(),
        "evdev: /dev/input/eventN, or a name in /dev/input/by-id or /dev/input/by-path"),
      F(button.evdev.key, NonEmpty(), "evdev: key code name (KEY_F1, BTN_0, ...) or number"),
      F(button.evdev.grab, Any(), "evdev: grab the device (EVIOCGRAB) so no other reader sees it"),
      F(button.modbus.link, OneOf({"turntable", "tcp", "rtu"}),
        "modbus: turntable (a second connection with [turntable.modbus]'s TCP settings) | tcp | "
        "rtu (the settings below)"),
      F(button.modbus.host, Any(), "modbus tcp: controller or gateway address"),
      F(button.modbus.port, Range(1, 65535), "modbus tcp: port"),
      F(button.modbus.device, Any(), "modbus rtu: serial device, e.g. /dev/ttyUSB1"),
      F(button.modbus.baud, Range(300, 4'000'000),
        "modbus rtu: line speed, bit/s (8 data, 1 stop)"),
      F(button.modbus.parity, OneOf({"none", "even", "odd"}), "modbus rtu: none | even | odd"),
      F(button.modbus.unit_id, Range(0, 255), "modbus: unit (slave) id"),
      D(button.modbus.response_timeout, Above(0, 10 * kSec),
        "modbus: one request must be answered within this"),
      F(button.modbus.input, OneOf({"discrete", "coil"}),
        "modbus: discrete (discrete input, function 2) | coil (function 1)"),
      F(button.modbus.address, Range(0, 65535), "modbus: bit address, 0-based as on the wire"),
      D(button.modbus.poll_interval, Range(5 * kMs, 1 * kSec),
        "modbus: read period; a press must be held longer than this to be seen"),

      F(light.backend, OneOf({"none", "gpio", "modbus"}), "status light: none | gpio | modbus"),
      F(light.gpio.chip, NonEmpty(), "gpio: chip name, path, number or label"),
      F(light.gpio.line, NonEmpty(), "gpio: line offset or line name"),
      F(light.gpio.active_low, Any(), "gpio: lit = low level"),
      F(light.gpio.bias, OneOf({"as-is", "pull-up", "pull-down", "disable"}),
        "gpio: unused for an output"),
      F(light.modbus.link, OneOf({"turntable", "button"}),
        "modbus: turntable ([turntable.modbus], modbus-tcp) | button ([button.modbus]'s link)"),
      F(light.modbus.coil, Range(0, 65535), "modbus: coil address, 0-based as on the wire"),

      F(sim.seed, Any(), "procedural rock, noise and turntable errors"),
      F(sim.rock_mesh, Any(), "PLY/OBJ/STL file; empty = procedural rock from seed"),
      F(sim.rock_unit, OneOf({"mm", "cm", "m"}), "unit of rock_mesh coordinates: mm | cm | m"),
      F(sim.rock_size_mm, Range(0, 1000),
        "procedural rock longest dimension, mm; 0 = random 70..200 mm"),
      F(sim.camera_elevation_deg, Range(10, 80),
        "camera above the turntable plane, degrees (the paper: 30..45)"),
      F(sim.camera_distance_mm, Range(50, 10000), "camera distance from the turntable centre, mm"),
      F(sim.hfov_deg, Range(5, 150), "horizontal field of view, degrees"),
      F(sim.k1, Range(-1, 1), "radial distortion (Brown) coefficient k1"),
      F(sim.k2, Range(-1, 1), "radial distortion (Brown) coefficient k2"),
      F(sim.noise_sigma, Range(0, 64), "sensor noise, 8-bit levels"),
      F(sim.rock_gloss, Range(0, 4),
        "wet or polished stone: the key light's highlight against its diffuse light (0 = matte)"),
      F(sim.rock_shininess, Range(1, 10000), "the highlight's sharpness (Phong exponent)"),
      F(sim.write_truth, Any(), "write ground-truth masks/poses next to the sample (tests)"),
      F(sim.hand_angle_error_deg, Range(0, 60),
        "hand-turned table: each turn is the step plus a uniform error within +-this, degrees"),
      D(sim.hand_reaction_min, Range(0, 60 * kSec), "hand-turned table: shortest reaction time"),
      D(sim.hand_reaction_max, Range(0, 60 * kSec), "hand-turned table: longest reaction time"),
      D(sim.hand_turn_min, Above(0, 60 * kSec), "hand-turned table: shortest turn"),
      D(sim.hand_turn_max, Above(0, 60 * kSec), "hand-turned table: longest turn"),
      F(sim.hand_late_every, Range(0, 1000),
        "hand-turned table: every n-th view is turned while exposed (blurred); 0 = never"),
      F(sim.walk_elevation_spread_deg, Range(0, 60),
        "moving camera: the walked views' elevations alternate over this range, degrees"),
      F(sim.walk_shuffle, Any(), "moving camera: the walker visits the positions in random order"),
      F(sim.scene, OneOf({"rock", "charuco"}),
        "what lies on the disc: rock | charuco (the [calibration] board, no rock)"),
      F(sim.board_image, Any(),
        "charuco: greyscale PGM of the board area without margin "
        "(aggscan calibrate board --out FILE.pgm --margin-mm 0)"),
      F(sim.board_x_mm, Range(-200, 200), "charuco: board centre on the disc, turntable frame, mm"),
      F(sim.board_y_mm, Range(-200, 200), "charuco: board centre on the disc, turntable frame, mm"),
      F(sim.board_yaw_deg, Range(-360, 360),
        "charuco: board x axis from the turntable x axis, counter-clockwise, degrees"),
      F(sim.aruco_image, Any(),
        "rig.aruco_markers: greyscale PGM of the markers side by side in list order, black "
        "squares only (aggscan calibrate aruco --out FILE.pgm); the sim camera draws them from it"),

      F(rig.turntable_diameter_mm, Above(0, 5000), "turntable disc diameter, mm (the paper: 305)"),
      F(rig.marker_size_mm, Above(0, 1000), "side of each square colour label, mm"),
      F(rig.aruco_dictionary, OneOf(BoardDictionaryNames()),
        "ArUco dictionary of rig.aruco_markers (OpenCV name, e.g. DICT_4X4_50)"),
      F(rig.aruco_size_mm, Above(0, 1000),
        "side of each ArUco scale marker's black square as printed, mm (measure the print)"),

      F(calibration.dictionary, OneOf(BoardDictionaryNames()),
        "ArUco dictionary of the board's markers (OpenCV name, e.g. DICT_5X5_100)"),
      F(calibration.squares_x, Range(3, 40), "chessboard squares along the board's x axis"),
      F(calibration.squares_y, Range(3, 40), "chessboard squares along the board's y axis"),
      F(calibration.square_mm, Above(0, 1000), "side of one chessboard square as printed, mm"),
      F(calibration.marker_mm, Above(0, 1000),
        "side of one ArUco marker as printed, mm (smaller than square_mm)"),

      F(mask.method, OneOf({"classical", "onnx"}),
        "classical (colour, texture, graph cut) | onnx (a salient-object network seeds the "
        "refinement)"),
      F(mask.model, Any(), "onnx: path of the .onnx network file"),
      F(mask.input_width, Range(8, 4096), "onnx: network input width, pixels"),
      F(mask.input_height, Range(8, 4096), "onnx: network input height, pixels"),
      F(mask.mean_r, Range(-10, 10), "onnx: mean subtracted from red/255"),
      F(mask.mean_g, Range(-10, 10), "onnx: mean subtracted from green/255"),
      F(mask.mean_b, Range(-10, 10), "onnx: mean subtracted from blue/255"),
      F(mask.std_r, Above(0, 10), "onnx: standard deviation red is divided by"),
      F(mask.std_g, Above(0, 10), "onnx: standard deviation green is divided by"),
      F(mask.std_b, Above(0, 10), "onnx: standard deviation blue is divided by"),
      F(mask.output, OneOf({"probability", "logits"}),
        "onnx: probability (sigmoid already applied) | logits"),
      F(mask.threshold, Above(0, 1), "onnx: probability above which a pixel is rock (0..1)"),
      F(mask.empty_turntable_max_angle_deg, Range(0, 5),
        "a view is masked against the empty-turntable photo shot within this many degrees of its "
        "angle, or without one"),

      D(worker.poll_interval, Above(0, 60 * kSec), "queue polling period when idle"),
      F(worker.nice, Range(0, 19), "CPU priority below the capture daemon (0..19)"),
      F(worker.poses, OneOf({"turntable+ba", "turntable", "sfm", "auto"}),
        "poses: turntable+ba (rig calibration + measured angles refined by bundle adjustment) | "
        "turntable (rig calibration + measured angles as read) | sfm (full SfM through COLMAP, "
        "scaled by the background labels; minutes a side) | auto (turntable+ba with a "
        "calibration, sfm without)"),
      F(worker.max_attempts, Range(1, 100),
        "failed or crashed runs after which a job is marked failed (retry it with `aggscan retry "
        "ID`)"),
      F(worker.max_interruptions, Range(1, 1000),
        "starts in a row that find a job cut off (worker killed, power lost) before it is marked "
        "failed"),
      D(worker.heartbeat_interval, Range(100 * kMs, 600 * kSec),
        "the worker reports its state, job and stage this often (and when its stage changes)"),
      D(worker.silent_after, Range(0, 24 * 3600 * kSec),
        "aggscand calls the worker unhealthy when it has not reported for this long (0 = not "
        "watched)"),

      F(material.name, Any(),
        "the stone measured, as the report names it (e.g. \"granite, pit 3\")"),
      F(material.specific_gravity, Range(0, 6),
        "its specific gravity (density relative to water), for mass = volume x this; 0 = "
        "unknown: no mass until a sample or this gives one (riprap: typically 2.5-3.0)"),
      F(material.basis, OneOf({"bulk-ssd", "oven-dry"}),
        "what the specific gravity was measured on: bulk-ssd (saturated surface-dry, what "
        "gradations by mass use) | oven-dry"),
  };
  return k;
}

#undef F
#undef D

// [[rig.markers]] entries.
constexpr const char* kMarkersKey = "rig.markers";
const std::vector<Field<RigMarker>>& MarkerFields() {
  static const std::vector<Field<RigMarker>> k = {
      AGG_FIELD(RigMarker, color, OneOf(MarkerColors()),
                "red | green | blue | yellow, each at most once"),
      AGG_FIELD(RigMarker, x_mm, Range(-5000, 5000),
                "centre in the turntable frame (z up, origin at the axis), mm"),
      AGG_FIELD(RigMarker, y_mm, Range(-5000, 5000), "centre in the turntable frame, mm"),
  };
  return k;
}

// [[rig.aruco_markers]] entries.
constexpr const char* kArucoKey = "rig.aruco_markers";
const std::vector<Field<ArucoMarker>>& ArucoFields() {
  static const std::vector<Field<ArucoMarker>> k = {
      AGG_FIELD(ArucoMarker, id, Range(0, 1'000'000),
                "marker id in rig.aruco_dictionary, each at most once"),
      AGG_FIELD(ArucoMarker, x_mm, Range(-5000, 5000),
                "centre of the black square in the turntable frame (z up, origin at the axis), mm"),
      AGG_FIELD(ArucoMarker, y_mm, Range(-5000, 5000), "centre in the turntable frame, mm"),
      AGG_FIELD(ArucoMarker, yaw_deg, Range(-360, 360),
                "marker x axis (printed columns) from the turntable x axis, counter-clockwise, "
                "degrees"),
  };
  return k;
}

#undef AGG_FIELD
#undef AGG_DURATION

struct Section {
  const char* name;
  const char* comment;
};
// Output order; a parent table comes before its sub-tables.
const std::vector<Section>& Sections() {
  static const std::vector<Section> k = {
      {"daemon", "Capture daemon: state directory, HTTP API, logging."},
      {"capture", "Capture schedule and device deadlines."},
      {"camera", "Camera backend and still format."},
      {"camera.exposure", "Locked exposure: every view of a rock shares it."},
      {"camera.v4l2",
       "V4L2 camera (backend v4l2): pixel format, buffers, timeout, control mapping."},
      {"camera.libcamera",
       "libcamera camera (backend libcamera): camera, stream role and format, buffers, timeout."},
      {"turntable", "Turntable backend, motion limits and the sim platter model."},
      {"turntable.faults", "Sim turntable fault injection (tests); unset = no fault."},
      {"turntable.modbus",
       "Modbus turntable (backend modbus-tcp or modbus-rtu): link, register-map profile, scaling."},
      {"turntable.usb",
       "USB turntable (backend usb-tic): a Pololu Tic stepper controller on its native USB "
       "interface."},
      {"button", "Operator start button."},
      {"button.gpio", "GPIO button (backend gpio): a line through libgpiod."},
      {"button.evdev", "Input-device button (backend evdev): a key of a foot pedal or keypad."},
      {"button.modbus", "Modbus button (backend modbus): a polled discrete input or coil."},
      {"light",
       "Status light: ready steady, capturing slow blink, flip the rock fast blink, fault double "
       "flash."},
      {"light.gpio", "GPIO status light (backend gpio): an output line."},
      {"light.modbus", "Modbus status light (backend modbus): one coil."},
      {"sim", "Simulated rig: rock, camera geometry and sensor."},
      {"rig", "Rig geometry: turntable and the background scale markers."},
      {"calibration",
       "ChArUco board of the rig calibration (aggscan calibrate), laid flat on the disc."},
      {"mask",
       "Foreground masks: classical segmentation, or an ONNX salient-object network that seeds "
       "its refinement."},
      {"worker", "Reconstruction worker."},
      {"material",
       "Default material of the samples armed without one: name, specific gravity (mass) and "
       "its basis."},
  };
  return k;
}

template <class S>
const Field<S>* FindField(const std::vector<Field<S>>& fields, const std::string& key) {
  for (const auto& f : fields) {
    if (key == f.key) return &f;
  }
  return nullptr;
}

bool IsSection(const std::string& key) {
  for (const auto& s : Sections()) {
    if (key == s.name) return true;
  }
  return false;
}

// ---------------------------------------------------------------------------
// Formatting helpers

template <class... Ts>
struct Overloaded : Ts... {
  using Ts::operator()...;
};
template <class... Ts>
Overloaded(Ts...) -> Overloaded<Ts...>;

// Shortest text that reads back to the same double, always a TOML float.
std::string FormatDouble(double v) {
  char buf[64];
  auto res = std::to_chars(buf, buf + sizeof(buf), v);
  std::string s(buf, res.ptr);
  if (s.find_first_of(".eni") == std::string::npos) s += ".0";
  return s;
}

// TOML basic string.
std::string Quote(const std::string& s) {
  std::string out = "\"";
  for (unsigned char ch : s) {
    switch (ch) {
      case '"':
        out += "\\\"";
        break;
      case '\\':
        out += "\\\\";
        break;
      case '\b':
        out += "\\b";
        break;
      case '\t':
        out += "\\t";
        break;
      case '\n':
        out += "\\n";
        break;
      case '\f':
        out += "\\f";
        break;
      case '\r':
        out += "\\r";
        break;
      default:
        if (ch < 0x20 || ch == 0x7f) {
          char buf[8];
          std::snprintf(buf, sizeof(buf), "\\u%04X", ch);
          out += buf;
        } else {
          out += static_cast<char>(ch);
        }
    }
  }
  return out + "\"";
}

std::string Join(const std::vector<std::string>& v, const char* sep) {
  std::string out;
  for (size_t i = 0; i < v.size(); ++i) {
    if (i) out += sep;
    out += v[i];
  }
  return out;
}

// Value as TOML text; nullopt for an unset optional.
std::optional<std::string> ToTomlValue(const Ref& ref) {
  return std::visit(
      Overloaded{
          [](bool* p) -> std::optional<std::string> { return *p ? "true" : "false"; },
          [](int* p) -> std::optional<std::string> { return std::to_string(*p); },
          [](uint64_t* p) -> std::optional<std::string> { return std::to_string(*p); },
          [](double* p) -> std::optional<std::string> { return FormatDouble(*p); },
          [](std::string* p) -> std::optional<std::string> { return Quote(*p); },
          [](DurRef r) -> std::optional<std::string> { return Quote(FormatDuration(*r.p)); },
          [](std::optional<double>* p) -> std::optional<std::string> {
            if (!*p) return std::nullopt;
            return FormatDouble(**p);
          },
          [](OptDurRef r) -> std::optional<std::string> {
            if (!*r.p) return std::nullopt;
            return Quote(FormatDuration(**r.p));
          },
      },
      ref);
}

const char* TypeName(const toml::node& n) {
  switch (n.type()) {
    case toml::node_type::table:
      return "a table";
    case toml::node_type::array:
      return "an array";
    case toml::node_type::string:
      return "a string";
    case toml::node_type::integer:
      return "an integer";
    case toml::node_type::floating_point:
      return "a float";
    case toml::node_type::boolean:
      return "a boolean";
    case toml::node_type::date:
      return "a date";
    case toml::node_type::time:
      return "a time";
    case toml::node_type::date_time:
      return "a date-time";
    default:
      return "nothing";
  }
}

// Stores a TOML value into the field; returns a message on a type mismatch.
std::string Assign(const toml::node& n, const Ref& ref) {
  auto got = [&](const char* expected) {
    return std::string("expected ") + expected + ", got " + TypeName(n);
  };
  auto number = [&](double* out) -> std::string {
    if (auto i = n.as_integer()) {
      *out = static_cast<double>(i->get());
    } else if (auto d = n.as_floating_point()) {
      *out = d->get();
    } else {
      return got("a number");
    }
    return {};
  };
  auto duration = [&](TimeNs* out) -> std::string {
    const auto* s = n.as_string();
    if (!s) return got("a duration string with a unit, e.g. \"2s\" or \"500ms\"");
    if (!ParseDuration(s->get(), out)) {
      return "\"" + s->get() +
             "\" is not a duration; write a number and a unit (ns, us, ms, s, min, h), e.g. \"2s\"";
    }
    return {};
  };
  return std::visit(
      Overloaded{
          [&](bool* p) -> std::string {
            const auto* b = n.as_boolean();
            if (!b) return got("a boolean (true or false)");
            *p = b->get();
            return {};
          },
          [&](int* p) -> std::string {
            const auto* i = n.as_integer();
            if (!i) return got("an integer");
            int64_t v = i->get();
            if (v < std::numeric_limits<int>::min() || v > std::numeric_limits<int>::max()) {
              return "integer " + std::to_string(v) + " is out of range";
            }
            *p = static_cast<int>(v);
            return {};
          },
          [&](uint64_t* p) -> std::string {
            const auto* i = n.as_integer();
            if (!i) return got("an integer");
            if (i->get() < 0) return "must be >= 0, got " + std::to_string(i->get());
            *p = static_cast<uint64_t>(i->get());
            return {};
          },
          [&](double* p) -> std::string { return number(p); },
          [&](std::string* p) -> std::string {
            const auto* s = n.as_string();
            if (!s) return got("a string");
            *p = s->get();
            return {};
          },
          [&](DurRef r) -> std::string { return duration(r.p); },
          [&](std::optional<double>* p) -> std::string {
            double v = 0;
            std::string err = number(&v);
            if (err.empty()) *p = v;
            return err;
          },
          [&](OptDurRef r) -> std::string {
            TimeNs v = 0;
            std::string err = duration(&v);
            if (err.empty()) *r.p = v;
            return err;
          },
      },
      ref);
}

// ---------------------------------------------------------------------------
// Field validation

struct Numeric {
  double value;
  bool is_duration;
  bool is_integer;
};

// The field's value as a number; nullopt for strings, bools and unset optionals.
std::optional<Numeric> NumericValue(const Ref& ref) {
  return std::visit(Overloaded{
                        [](bool*) -> std::optional<Numeric> { return std::nullopt; },
                        [](int* p) -> std::optional<Numeric> {
                          return Numeric{static_cast<double>(*p), false, true};
                        },
                        [](uint64_t* p) -> std::optional<Numeric> {
                          return Numeric{static_cast<double>(*p), false, true};
                        },
                        [](double* p) -> std::optional<Numeric> {
                          return Numeric{*p, false, false};
                        },
                        [](std::string*) -> std::optional<Numeric> { return std::nullopt; },
                        [](DurRef r) -> std::optional<Numeric> {
                          return Numeric{static_cast<double>(*r.p), true, true};
                        },
                        [](std::optional<double>* p) -> std::optional<Numeric> {
                          if (!*p) return std::nullopt;
                          return Numeric{**p, false, false};
                        },
                        [](OptDurRef r) -> std::optional<Numeric> {
                          if (!*r.p) return std::nullopt;
                          return Numeric{static_cast<double>(**r.p), true, true};
                        },
                    },
                    ref);
}

std::string FormatNumber(double v, const Numeric& n) {
  if (n.is_duration) return FormatDuration(static_cast<TimeNs>(v));
  if (n.is_integer && std::abs(v) < 1e18) return std::to_string(static_cast<int64_t>(v));
  std::string s = FormatDouble(v);
  if (s.size() > 2 && s.compare(s.size() - 2, 2, ".0") == 0) s.resize(s.size() - 2);
  return s;
}

// Message if the value breaks the check, empty if it passes.
std::string CheckValue(const Ref& ref, const Check& check) {
  switch (check.kind) {
    case Check::kAny:
      return {};
    case Check::kRange: {
      auto n = NumericValue(ref);
      if (!n) return {};
      double v = n->value;
      bool ok = (check.lo_open ? v > check.lo : v >= check.lo) && v <= check.hi;  // false for NaN
      if (ok) return {};
      std::string want;
      if (check.lo_open) {
        want = "must be > " + FormatNumber(check.lo, *n);
        if (check.hi != kInf) want += " and <= " + FormatNumber(check.hi, *n);
      } else {
        want = "must be in " + FormatNumber(check.lo, *n) + ".." + FormatNumber(check.hi, *n);
      }
      return want + ", got " + FormatNumber(v, *n);
    }
    case Check::kOneOf:
    case Check::kBackend: {
      const auto* s = std::get_if<std::string*>(&ref);
      if (!s) return {};
      const auto& choices =
          check.kind == Check::kOneOf ? check.choices : KnownBackends(check.backend_kind);
      if (std::find(choices.begin(), choices.end(), **s) != choices.end()) return {};
      if (check.kind == Check::kBackend) {
        return std::string("unknown ") + check.backend_kind + " backend \"" + **s +
               "\"; known: " + Join(choices, ", ");
      }
      return "must be one of " + Join(choices, " | ") + ", got \"" + **s + "\"";
    }
    case Check::kNonEmpty: {
      const auto* s = std::get_if<std::string*>(&ref);
      if (s && (*s)->empty()) return "must not be empty";
      return {};
    }
  }
  return {};
}

// ---------------------------------------------------------------------------
// Edit distance for "did you mean"

// Optimal string alignment distance: Levenshtein plus adjacent transpositions
// ("widht" -> "width" is one edit), the commonest typo in a key.
size_t EditDistance(const std::string& a, const std::string& b) {
  std::vector<std::vector<size_t>> d(a.size() + 1, std::vector<size_t>(b.size() + 1));
  for (size_t i = 0; i <= a.size(); ++i) d[i][0] = i;
  for (size_t j = 0; j <= b.size(); ++j) d[0][j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    for (size_t j = 1; j <= b.size(); ++j) {
      size_t cost = a[i - 1] == b[j - 1] ? 0 : 1;
      d[i][j] = std::min({d[i - 1][j] + 1, d[i][j - 1] + 1, d[i - 1][j - 1] + cost});
      if (i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1]) {
        d[i][j] = std::min(d[i][j], d[i - 2][j - 2] + 1);
      }
    }
  }
  return d[a.size()][b.size()];
}

std::string Parent(const std::string& key) {
  auto dot = key.rfind('.');
  return dot == std::string::npos ? std::string() : key.substr(0, dot);
}
std::string Leaf(const std::string& key) {
  auto dot = key.rfind('.');
  return dot == std::string::npos ? key : key.substr(dot + 1);
}

// ---------------------------------------------------------------------------
// Validation shared by the loader (with lines) and ValidateConfig (without).

// "name", "name:port", "[v6]" or "[v6]:port", as a Host header carries it.
bool IsHostEntry(const std::string& s) {
  std::string host = s, port;
  if (!s.empty() && s[0] == '[') {
    const size_t close = s.find(']');
    if (close == std::string::npos || close < 3) return false;
    host = s.substr(1, close - 1);
    if (host.find_first_not_of("0123456789abcdefABCDEF:.") != std::string::npos) return false;
    if (close + 1 < s.size()) {
      if (s[close + 1] != ':') return false;
      port = s.substr(close + 2);
      if (port.empty()) return false;
    }
  } else {
    const size_t colon = s.find(':');
    if (colon != std::string::npos) {
      host = s.substr(0, colon);
      port = s.substr(colon + 1);
      if (port.empty()) return false;
    }
    if (host.empty() || host.size() > 253) return false;
    for (unsigned char ch : host) {
      if (!std::isalnum(ch) && ch != '.' && ch != '-' && ch != '_') return false;
    }
  }
  if (!port.empty()) {
    if (port.size() > 5 || port.find_first_not_of("0123456789") != std::string::npos) return false;
    const int p = std::stoi(port);
    if (p < 1 || p > 65535) return false;
  }
  return true;
}

using LineMap = std::map<std::string, int>;

class Validator {
 public:
  Validator(const std::string& file, const LineMap* lines, std::vector<ConfigProblem>* problems)
      : file_(file), lines_(lines), problems_(problems) {}

  void Add(const std::string& key, const std::string& message) {
    int line = 0;
    if (lines_) {
      auto it = lines_->find(key);
      if (it != lines_->end()) line = it->second;
    }
    problems_->push_back(ConfigProblem{file_, line, key, message});
  }

  void Run(const Config& config) {
    Config& c = const_cast<Config&>(config);  // refs are only read here
    for (const auto& f : Fields()) {
      std::string msg = CheckValue(f.ref(c), f.check);
      if (!msg.empty()) Add(f.key, msg);
    }
    for (const std::string& h : SplitCommaList(c.daemon.allowed_hosts)) {
      if (!IsHostEntry(h)) {
        Add("daemon.allowed_hosts",
            "\"" + h +
                "\" is not a host name or address with an optional :port (IPv6 in "
                "brackets, e.g. [fe80::1]:8470)");
      }
    }
    for (const std::string& o : SplitCommaList(c.daemon.allowed_origins)) {
      const bool http = o.rfind("http://", 0) == 0;
      const bool https = o.rfind("https://", 0) == 0;
      if ((!http && !https) || !IsHostEntry(o.substr(http ? 7 : 8))) {
        Add("daemon.allowed_origins", "\"" + o +
                                          "\" is not an origin: use http://host[:port] or "
                                          "https://host[:port], without a path");
      }
    }
    std::set<std::string> colors;
    for (size_t i = 0; i < c.rig.markers.size(); ++i) {
      RigMarker& m = c.rig.markers[i];
      std::string prefix = std::string(kMarkersKey) + "[" + std::to_string(i) + "].";
      for (const auto& f : MarkerFields()) {
        std::string msg = CheckValue(f.ref(m), f.check);
        if (std::string(f.key) == "color" && m.color.empty()) {
          msg = "missing; every marker needs a colour (red | green | blue | yellow)";
        }
        if (!msg.empty()) Add(prefix + f.key, msg);
      }
      if (!m.color.empty() && !colors.insert(m.color).second) {
        Add(prefix + "color",
            "colour \"" + m.color + "\" is used by another marker; each colour at most once");
      }
    }
    for (size_t i = 0; i < c.rig.aruco_markers.size(); ++i) {
      ArucoMarker& m = c.rig.aruco_markers[i];
      std::string prefix = std::string(kArucoKey) + "[" + std::to_string(i) + "].";
      for (const auto& f : ArucoFields()) {
        std::string msg = CheckValue(f.ref(m), f.check);
        if (std::string(f.key) == "id" && m.id == -1) {
          msg = "missing; every ArUco marker needs its id in rig.aruco_dictionary";
        }
        if (!msg.empty()) Add(prefix + f.key, msg);
      }
    }
    CrossField(c);
  }

 private:
  void CrossField(const Config& c) {
    const bool loopback = IsLoopbackAddress(c.daemon.listen_address);
    if (!loopback && c.daemon.credentials_file.empty()) {
      Add("daemon.listen_address",
          "\"" + c.daemon.listen_address +
              "\" opens the API to the network, where anyone could drive the rig: set "
              "daemon.credentials_file (accounts made with `aggscan user add NAME --role operator "
              "--file /etc/aggscan/accounts`) and daemon.tls_certificate and daemon.tls_key, or "
              "keep 127.0.0.1 behind a reverse proxy that terminates TLS");
    } else if (!loopback && c.daemon.tls_certificate.empty()) {
      Add("daemon.tls_certificate",
          "missing: with listen_address \"" + c.daemon.listen_address +
              "\" passwords and session tokens would cross the network in clear; set "
              "tls_certificate and tls_key (PEM), or keep 127.0.0.1 behind a reverse proxy that "
              "terminates TLS");
    }
    if (c.daemon.tls_certificate.empty() != c.daemon.tls_key.empty()) {
      Add(c.daemon.tls_key.empty() ? "daemon.tls_key" : "daemon.tls_certificate",
          "missing: HTTPS needs both daemon.tls_certificate and daemon.tls_key");
    }
    if (c.worker.silent_after > 0 && c.worker.silent_after < 2 * c.worker.heartbeat_interval) {
      Add("worker.silent_after", FormatDuration(c.worker.silent_after) +
                                     " is shorter than twice worker.heartbeat_interval (" +
                                     FormatDuration(c.worker.heartbeat_interval) +
                                     "): a worker that is running would be called silent; raise it "
                                     "or set 0 to not watch the worker");
    }
    if (c.material.specific_gravity > 0 && c.material.specific_gravity < 1.0) {
      Add("material.specific_gravity",
          FormatDouble(c.material.specific_gravity) +
              " is below 1 (a stone that floats): give the stone's specific gravity, riprap "
              "is about 2.3-3.2, or 0 for unknown");
    }
    if (c.daemon.reopen_backoff_max < c.daemon.reopen_backoff_min) {
      Add("daemon.reopen_backoff_max", FormatDuration(c.daemon.reopen_backoff_max) +
                                           " is shorter than daemon.reopen_backoff_min (" +
                                           FormatDuration(c.daemon.reopen_backoff_min) + ")");
    }
    if (c.daemon.time_scale > 1.0) {
      // The scaled clock drives every deadline, timer and timestamp, a real
      // device's as well: its moves, exposures and time-outs would be scaled
      // too, and no real platter turns ten times faster on request.
      std::vector<std::string> real;
      auto device = [&](const char* key, const std::string& backend, const char* simulated) {
        if (backend != simulated) real.push_back(std::string(key) + " = \"" + backend + "\"");
      };
      device("camera.backend", c.camera.backend, "sim");
      // A hand-turned table before the sim camera is the sim's hand, which
      // keeps any clock; before a real camera it is a person.
      if (c.turntable.backend != "manual" || c.camera.backend != "sim") {
        device("turntable.backend", c.turntable.backend, "sim");
      }
      device("button.backend", c.button.backend, "sim");
      device("light.backend", c.light.backend, "none");
      if (!real.empty()) {
        Add("daemon.time_scale",
            FormatDouble(c.daemon.time_scale) +
                " runs the clock faster than real time, which only the sim rig can follow; " +
                Join(real, ", ") + (real.size() > 1 ? " are real devices" : " is a real device") +
                ": set daemon.time_scale = 1");
      }
    }
    const CaptureConfig& cap = c.capture;
    if (cap.profile == "paper") {
      // Only reachable for a struct that skipped ApplyProfile; files are fixed up.
      if (cap.sides != 2 || cap.views_per_side != 30 || cap.step_deg != 30.0 ||
          cap.interval != 2 * kNsPerSec) {
        Add("capture.profile",
            "profile \"paper\" means sides 2, views_per_side 30, step_deg 30, interval 2s; call "
            "ApplyProfile or "
            "set capture.profile = \"custom\"");
      }
    } else if (cap.profile == "full-turn" && cap.views_per_side >= 1) {
      if (std::abs(cap.step_deg - 360.0 / cap.views_per_side) > 1e-9) {
        Add("capture.step_deg", "profile \"full-turn\" means step_deg = 360/views_per_side = " +
                                    FormatDouble(360.0 / cap.views_per_side) + ", got " +
                                    FormatDouble(cap.step_deg));
      }
    }

    // One step (trapezoidal profile) plus the settle wait must fit in the
    // interval, and the move deadline must allow the move itself.
    const TurntableConfig& tt = c.turntable;
    if (cap.mode == "moving_camera" && tt.backend != "manual") {
      Add("capture.mode",
          "moving_camera leaves the rock still and the camera is walked round it: nothing is "
          "driven; set turntable.backend = \"manual\" (now \"" +
              tt.backend + "\")");
    }
    if (tt.backend == "manual") {
      // A person turns the table between the hands-off moment and the
      // previous shot: the interval must leave them time to do it.
      if (cap.views_per_side > 1 && cap.interval > 0 &&
          tt.manual_hands_off + kNsPerSec > cap.interval) {
        Add("turntable.manual_hands_off",
            FormatDuration(tt.manual_hands_off) + " leaves less than 1s of capture.interval (" +
                FormatDuration(cap.interval) +
                ") to turn the table by hand; lengthen the interval or shorten the hands-off time");
      }
      const SimConfig& h = c.sim;
      if (h.hand_reaction_max < h.hand_reaction_min) {
        Add("sim.hand_reaction_max", "is shorter than sim.hand_reaction_min");
      }
      if (h.hand_turn_max < h.hand_turn_min) {
        Add("sim.hand_turn_max", "is shorter than sim.hand_turn_min");
      }
    } else if (tt.max_speed_deg_s > 0 && tt.accel_deg_s2 > 0 && cap.step_deg > 0 &&
               std::isfinite(cap.step_deg)) {
      double v = tt.max_speed_deg_s, a = tt.accel_deg_s2, d = cap.step_deg;
      double move_s = d >= v * v / a ? d / v + v / a : 2.0 * std::sqrt(d / a);
      // Rounded up to whole milliseconds: exact enough, and readable in messages.
      auto move_ns = static_cast<TimeNs>(std::ceil(move_s * 1000.0)) * kNsPerMs;
      if (cap.views_per_side > 1 && cap.interval > 0 && move_ns + cap.settle > cap.interval) {
        Add("capture.interval", FormatDuration(cap.interval) + " is shorter than one step (" +
                                    FormatDouble(d) + " deg at " + FormatDouble(v) + " deg/s, " +
                                    FormatDouble(a) + " deg/s^2: " + FormatDuration(move_ns) +
                                    ") plus capture.settle " + FormatDuration(cap.settle) +
                                    "; raise the interval or the turntable speed");
      }
      if (cap.move_timeout > 0 && move_ns > cap.move_timeout) {
        Add("capture.move_timeout", FormatDuration(cap.move_timeout) +
                                        " is shorter than one step's motion (" +
                                        FormatDuration(move_ns) + ")");
      }
    }
    if (cap.stall_timeout > 0 && cap.poll_interval > 0 && cap.stall_timeout <= cap.poll_interval) {
      Add("capture.stall_timeout", "must be longer than capture.poll_interval (" +
                                       FormatDuration(cap.poll_interval) +
                                       ") or no stall can be seen");
    }
    if (c.sim.seed > static_cast<uint64_t>(std::numeric_limits<int64_t>::max())) {
      Add("sim.seed", "must be <= " + std::to_string(std::numeric_limits<int64_t>::max()) +
                          " (TOML integers are signed 64-bit)");
    }
    if (c.sim.rock_size_mm > 0 && c.sim.rock_size_mm < 10) {
      Add("sim.rock_size_mm",
          "must be 0 (random) or at least 10 mm, got " + FormatDouble(c.sim.rock_size_mm));
    }
    if ((c.camera.lens_focal_mm > 0) != (c.camera.sensor_width_mm > 0)) {
      Add(c.camera.lens_focal_mm > 0 ? "camera.sensor_width_mm" : "camera.lens_focal_mm",
          "camera.lens_focal_mm and camera.sensor_width_mm go together (the focal in pixels "
          "is their ratio times the width): set both from the datasheets, or neither");
    }
    CheckBoard(c);
    CheckAruco(c);
    CheckModbus(c);
    CheckUsbTic(c);
    CheckButtonAndLight(c);
    if (c.mask.method == "onnx" && c.mask.model.empty()) {
      Add("mask.model",
          "mask.method = \"onnx\" needs the network: name its .onnx file here, or set "
          "mask.method = \"classical\"");
    }
    if (c.mask.threshold == 1.0) {
      Add("mask.threshold", "must be < 1 (a probability), got " + FormatDouble(c.mask.threshold));
    }
    if (c.sim.camera_distance_mm <= c.rig.turntable_diameter_mm / 2) {
      Add("sim.camera_distance_mm", "camera must stand outside the turntable (radius " +
                                        FormatDouble(c.rig.turntable_diameter_mm / 2) + " mm)");
    }
  }

  // The Modbus link named by the backend must be complete; the line settings
  // must be ones a serial port can take.
  void CheckModbus(const Config& c) {
    const ModbusTurntableConfig& m = c.turntable.modbus;
    if (c.turntable.backend == "modbus-tcp" && m.host.empty()) {
      Add("turntable.modbus.host",
          "turntable.backend = \"modbus-tcp\" needs the controller's address, e.g. "
          "host = \"192.168.1.50\"");
    }
    if (c.turntable.backend == "modbus-rtu") {
      if (m.device.empty()) {
        Add("turntable.modbus.device",
            "turntable.backend = \"modbus-rtu\" needs the serial device, e.g. "
            "device = \"/dev/ttyUSB0\"");
      }
      if (m.unit_id < 1 || m.unit_id > 247) {
        Add("turntable.modbus.unit_id",
            "a Modbus RTU unit id is 1..247 (0 is broadcast), got " + std::to_string(m.unit_id));
      }
    }
    static const int kBauds[] = {300,     600,     1200,    1800,    2400,    4800,
                                 9600,    19200,   38400,   57600,   115200,  230400,
                                 460800,  500000,  576000,  921600,  1000000, 1152000,
                                 1500000, 2000000, 2500000, 3000000, 3500000, 4000000};
    if (std::find(std::begin(kBauds), std::end(kBauds), m.baud) == std::end(kBauds)) {
      Add("turntable.modbus.baud", std::to_string(m.baud) +
                                       " is not a serial line speed; use one of 9600, 19200, "
                                       "38400, 57600, 115200 (what the controller is set to)");
    }
    const double spr = m.steps_per_rev();
    if (spr * 1000.0 > 2147483647.0) {
      Add("turntable.modbus.microsteps",
          "steps per revolution " + FormatDouble(spr) +
              " leave fewer than 1000 turns in an int32 position; lower the microstepping");
    }
  }

  // The Tic: a step mode it has, and room for many turns in its int32 position.
  void CheckUsbTic(const Config& c) {
    if (c.turntable.backend != "usb-tic") return;
    const UsbTicConfig& u = c.turntable.usb;
    const double spr = u.steps_per_rev();
    if (spr * 1000.0 > 2147483647.0) {
      Add("turntable.usb.microsteps",
          "microsteps per revolution " + FormatDouble(spr) +
              " leave fewer than 1000 turns in the Tic's int32 position; lower the microstepping");
    }
    const int m = u.microsteps;
    if (m < 1 || m > 256 || (m & (m - 1)) != 0) {
      Add("turntable.usb.microsteps",
          "the Tic's step modes are 1, 2, 4, 8, 16, 32 (36v4 also 64, 128, 256) microsteps, got " +
              std::to_string(m));
    }
    // Speed and acceleration in the Tic's units are checked when the backend
    // opens (drivers/usb/tic_protocol.h), where the model is known.
  }

  // The button's and the light's device must be named; a Modbus link shared
  // with the turntable must be a TCP one (a second connection): two masters
  // on one serial line would garble each other's frames.
  void CheckButtonAndLight(const Config& c) {
    if (c.button.backend == "evdev" && c.button.evdev.device.empty()) {
      Add("button.evdev.device",
          "button.backend = \"evdev\" needs the input device, e.g. device = "
          "\"/dev/input/by-id/usb-pedal-event-kbd\"");
    }
    const bool modbus_button = c.button.backend == "modbus";
    const bool modbus_light = c.light.backend == "modbus";
    if (modbus_light && c.light.modbus.link == "button" && !modbus_button) {
      Add("light.modbus.link",
          "link = \"button\" needs button.backend = \"modbus\"; use link = "
          "\"turntable\" or configure [button.modbus]");
    }
    const bool button_link_used = modbus_button;  // a light on it needs the button (above)
    const ModbusButtonConfig& l = c.button.modbus;
    const bool turntable_link_used = (button_link_used && l.link == "turntable") ||
                                     (modbus_light && c.light.modbus.link == "turntable");
    if (turntable_link_used && c.turntable.backend != "modbus-tcp") {
      Add(modbus_light && c.light.modbus.link == "turntable" ? "light.modbus.link"
                                                             : "button.modbus.link",
          "the turntable's Modbus link can be shared only when turntable.backend = \"modbus-tcp\" "
          "(got \"" +
              c.turntable.backend +
              "\"); give the button its own link (link = \"tcp\" or \"rtu\")");
    }
    if (button_link_used && l.link == "tcp" && l.host.empty()) {
      Add("button.modbus.host",
          "link = \"tcp\" needs the controller's address, e.g. host = \"192.168.1.50\"");
    }
    if (button_link_used && l.link == "rtu" && l.device.empty()) {
      Add("button.modbus.device",
          "link = \"rtu\" needs the serial device, e.g. device = \"/dev/ttyUSB1\"");
    }
  }

  // The ArUco scale markers: ids unique and in the dictionary, each marker
  // with its paper on the disc and clear of the other markers and the colour
  // labels (an overlapped marker is neither detected nor measured).
  void CheckAruco(const Config& c) {
    auto FormatDouble = [](double v) {  // "305", "22.5": no trailing ".0" in messages
      std::string t = aggscan::FormatDouble(v);
      if (t.size() > 2 && t.compare(t.size() - 2, 2, ".0") == 0) t.resize(t.size() - 2);
      return t;
    };
    const RigConfig& rig = c.rig;
    if (rig.aruco_markers.empty()) return;
    int dict_size = 0;
    for (const auto& [name, size] : BoardDictionaries()) {
      if (name == rig.aruco_dictionary) dict_size = size;
    }
    // Outline of a square of side `side` centred at (x, y), turned by yaw.
    using Quad = std::array<std::array<double, 2>, 4>;
    auto square = [](double x, double y, double yaw_deg, double side) {
      const double a = yaw_deg * M_PI / 180.0, h = side / 2;
      Quad q;
      const double cx[4] = {-h, h, h, -h}, cy[4] = {-h, -h, h, h};
      for (int k = 0; k < 4; ++k) {
        q[k] = {x + cx[k] * std::cos(a) - cy[k] * std::sin(a),
                y + cx[k] * std::sin(a) + cy[k] * std::cos(a)};
      }
      return q;
    };
    // Separating-axis test of two convex quadrilaterals (touching is no overlap).
    auto overlap = [](const Quad& p, const Quad& q) {
      for (const Quad* s : {&p, &q}) {
        for (int k = 0; k < 4; ++k) {
          const double nx = (*s)[(k + 1) % 4][1] - (*s)[k][1];
          const double ny = (*s)[k][0] - (*s)[(k + 1) % 4][0];
          double p0 = 1e300, p1 = -1e300, q0 = 1e300, q1 = -1e300;
          for (int j = 0; j < 4; ++j) {
            const double a = nx * p[j][0] + ny * p[j][1], b = nx * q[j][0] + ny * q[j][1];
            p0 = std::min(p0, a), p1 = std::max(p1, a), q0 = std::min(q0, b), q1 = std::max(q1, b);
          }
          if (p1 <= q0 + 1e-9 || q1 <= p0 + 1e-9) return false;
        }
      }
      return true;
    };
    const double paper = rig.aruco_size_mm * (1 + 2 * kArucoPaperMarginFrac);
    const double disc_r = rig.turntable_diameter_mm / 2;
    std::map<int, size_t> first_with_id;
    std::vector<Quad> papers;
    for (size_t i = 0; i < rig.aruco_markers.size(); ++i) {
      const ArucoMarker& m = rig.aruco_markers[i];
      const std::string prefix = std::string(kArucoKey) + "[" + std::to_string(i) + "].";
      if (m.id >= 0) {
        auto [it, fresh] = first_with_id.emplace(m.id, i);
        if (!fresh) {
          Add(prefix + "id", "id " + std::to_string(m.id) + " is also used by " + kArucoKey + "[" +
                                 std::to_string(it->second) +
                                 "]; each marker needs its own id (print another one)");
        }
        if (dict_size > 0 && m.id >= dict_size) {
          Add(prefix + "id", "id " + std::to_string(m.id) + " is not in " + rig.aruco_dictionary +
                                 " (ids 0.." + std::to_string(dict_size - 1) +
                                 "); use a smaller id or a larger rig.aruco_dictionary");
        }
      }
      papers.push_back(square(m.x_mm, m.y_mm, m.yaw_deg, paper));
      if (!(rig.aruco_size_mm > 0) || !(disc_r > 0)) continue;
      double reach = 0;
      for (const auto& p : papers.back()) reach = std::max(reach, std::hypot(p[0], p[1]));
      if (reach > disc_r) {
        Add(prefix + "x_mm",
            "the marker at (" + FormatDouble(m.x_mm) + ", " + FormatDouble(m.y_mm) + ") mm, yaw " +
                FormatDouble(m.yaw_deg) + " deg, with its paper (" + FormatDouble(paper) +
                " mm square) reaches " + FormatDouble(std::round(reach * 10) / 10) +
                " mm from the axis, beyond the disc edge (" + FormatDouble(disc_r) +
                " mm); move it towards the axis or print it smaller (rig.aruco_size_mm)");
        continue;
      }
      for (size_t j = 0; j + 1 < papers.size(); ++j) {
        if (overlap(papers[j], papers.back())) {
          Add(prefix + "x_mm", "the marker's paper overlaps that of " + std::string(kArucoKey) +
                                   "[" + std::to_string(j) + "]; place the markers further apart");
        }
      }
      for (const RigMarker& l : rig.markers) {
        if (overlap(square(l.x_mm, l.y_mm, 0, rig.marker_size_mm), papers.back())) {
          Add(prefix + "x_mm", "the marker's paper covers the " + l.color +
                                   " colour label (rig.markers); move one of them");
        }
      }
    }
    // No rule for sim.aruco_image here: `aggscan calibrate aruco` writes it from
    // this very config; the sim world refuses to start without it and says so.
  }

  // The [calibration] board must be printable with its dictionary and lie
  // flat on the disc (the calibration model puts every corner on the disc
  // top); the sim's charuco scene needs the board image and a pose on the disc.
  void CheckBoard(const Config& c) {
    auto FormatDouble = [](double v) {  // "305", "22.5": no trailing ".0" in messages
      std::string t = aggscan::FormatDouble(v);
      if (t.size() > 2 && t.compare(t.size() - 2, 2, ".0") == 0) t.resize(t.size() - 2);
      return t;
    };
    const CalibrationConfig& b = c.calibration;
    if (b.marker_mm > 0 && b.square_mm > 0 && b.marker_mm >= b.square_mm) {
      Add("calibration.marker_mm", "must be smaller than calibration.square_mm (" +
                                       FormatDouble(b.square_mm) + " mm), got " +
                                       FormatDouble(b.marker_mm));
    }
    const int markers = b.squares_x * b.squares_y / 2;
    for (const auto& [name, size] : BoardDictionaries()) {
      if (name == b.dictionary && markers > size) {
        Add("calibration.dictionary", name + " has " + std::to_string(size) + " markers but a " +
                                          std::to_string(b.squares_x) + "x" +
                                          std::to_string(b.squares_y) + " board needs " +
                                          std::to_string(markers) + "; choose a larger dictionary");
      }
    }
    const double w = b.squares_x * b.square_mm, h = b.squares_y * b.square_mm;
    const double disc = c.rig.turntable_diameter_mm;
    if (b.square_mm > 0 && disc > 0 && std::hypot(w, h) > disc) {
      Add("calibration.square_mm",
          "the board (" + FormatDouble(w) + " x " + FormatDouble(h) + " mm, diagonal " +
              FormatDouble(std::round(std::hypot(w, h))) + " mm) does not fit on the " +
              FormatDouble(disc) + " mm turntable; use fewer or smaller squares");
    }
    if (c.sim.scene != "charuco") return;
    if (c.sim.board_image.empty()) {
      Add("sim.board_image",
          "sim.scene = \"charuco\" needs the board image: write one with `aggscan calibrate "
          "board --out FILE.pgm --margin-mm 0` and name it here");
    }
    // Every corner of the squares area on the disc top.
    const double a = c.sim.board_yaw_deg * M_PI / 180.0;
    double reach = 0;
    for (int sx : {-1, 1}) {
      for (int sy : {-1, 1}) {
        const double x = sx * w / 2, y = sy * h / 2;
        reach = std::max(reach, std::hypot(c.sim.board_x_mm + x * std::cos(a) - y * std::sin(a),
                                           c.sim.board_y_mm + x * std::sin(a) + y * std::cos(a)));
      }
    }
    if (b.square_mm > 0 && disc > 0 && reach > disc / 2) {
      Add("sim.board_x_mm",
          "the board placed at (" + FormatDouble(c.sim.board_x_mm) + ", " +
              FormatDouble(c.sim.board_y_mm) + ") mm, yaw " + FormatDouble(c.sim.board_yaw_deg) +
              " deg reaches " + FormatDouble(std::round(reach)) +
              " mm from the axis, beyond the disc edge (" + FormatDouble(disc / 2) + " mm)");
    }
  }

  const std::string& file_;
  const LineMap* lines_;
  std::vector<ConfigProblem>* problems_;
};

// ---------------------------------------------------------------------------
// Loader: TOML tree -> Config, with every problem and the line of every key.

class Loader {
 public:
  Loader(const std::string& file, std::vector<ConfigProblem>* problems)
      : file_(file), problems_(problems) {}

  void Add(int line, const std::string& key, const std::string& message) {
    problems_->push_back(ConfigProblem{file_, line, key, message});
  }

  void Walk(const toml::table& t, const std::string& prefix, Config* c) {
    for (auto&& [k, v] : t) {
      std::string key = prefix.empty() ? std::string(k.str()) : prefix + "." + std::string(k.str());
      int line = LineOf(v, k);
      if (const auto* f = FindField(Fields(), key)) {
        lines_[key] = line;
        std::string err = Assign(v, f->ref(*c));
        if (!err.empty()) Add(line, key, err);
      } else if (key == kMarkersKey) {
        lines_[key] = line;
        LoadMarkers(v, c);
      } else if (key == kArucoKey) {
        lines_[key] = line;
        c->rig.aruco_markers.clear();
        LoadTables(v, kArucoKey, "{id, x_mm, y_mm, yaw_deg}", ArucoFields(), "id",
                   &c->rig.aruco_markers);
      } else if (IsSection(key)) {
        if (const auto* sub = v.as_table()) {
          Walk(*sub, key, c);
        } else {
          Add(line, key, std::string("expected a table, got ") + TypeName(v));
        }
      } else {
        Add(line, key, "unknown key" + Suggest(key));
      }
    }
  }

  // Profile rule (config.h): a fixed value given with another value is a problem.
  void CheckProfileOverrides(const Config& c) {
    const CaptureConfig& cap = c.capture;
    auto fixed = [&](const char* key, bool differs, const std::string& value) {
      auto it = lines_.find(key);
      if (it == lines_.end() || !differs) return;
      Add(it->second, key,
          "capture.profile \"" + cap.profile + "\" fixes this to " + value +
              "; set capture.profile = \"custom\" " + "to change it");
    };
    if (cap.profile == "paper") {
      fixed("capture.sides", cap.sides != 2, "2");
      fixed("capture.views_per_side", cap.views_per_side != 30, "30");
      fixed("capture.step_deg", cap.step_deg != 30.0, "30");
      fixed("capture.interval", cap.interval != 2 * kNsPerSec, "\"2s\"");
    } else if (cap.profile == "full-turn" && cap.views_per_side >= 1 && cap.views_per_side <= 360) {
      double step = 360.0 / cap.views_per_side;
      fixed("capture.step_deg", std::abs(cap.step_deg - step) > 1e-9,
            "360/views_per_side = " + FormatDouble(step));
    }
  }

  const LineMap& lines() const { return lines_; }

  // An array of tables (`[[key]]` or `key = [{...}, ...]`) into `out`, each
  // table's keys from `fields`; a table without `required` is reported by the
  // validator at the table's line.
  template <class T>
  void LoadTables(const toml::node& v, const char* array_key, const char* shape,
                  const std::vector<Field<T>>& fields, const char* required, std::vector<T>* out) {
    const auto* arr = v.as_array();
    if (!arr) {
      Add(static_cast<int>(v.source().begin.line), array_key,
          std::string("expected an array of tables ([[") + array_key + "]]), got " + TypeName(v));
      return;
    }
    for (size_t i = 0; i < arr->size(); ++i) {
      const toml::node& el = *arr->get(i);
      const int el_line = static_cast<int>(el.source().begin.line);
      const auto* t = el.as_table();
      if (!t) {
        Add(el_line, std::string(array_key) + "[" + std::to_string(i) + "]",
            std::string("expected a table ") + shape + ", got " + TypeName(el));
        continue;
      }
      // Keys use the index in the loaded list, as ValidateConfig sees it.
      const std::string prefix = std::string(array_key) + "[" + std::to_string(out->size()) + "]";
      T item;
      for (auto&& [k, mv] : *t) {
        const std::string key = prefix + "." + std::string(k.str());
        const int line = LineOf(mv, k);
        if (const auto* f = FindField(fields, std::string(k.str()))) {
          lines_[key] = line;
          std::string err = Assign(mv, f->ref(item));
          if (!err.empty()) Add(line, key, err);
        } else {
          std::string hint;
          size_t best = 3;
          for (const auto& f : fields) {
            const size_t d = EditDistance(std::string(k.str()), f.key);
            if (d < best) {
              best = d;
              hint = std::string("; did you mean ") + f.key + "?";
            }
          }
          Add(line, key, "unknown key" + hint);
        }
      }
      if (!t->contains(required)) lines_[prefix + "." + required] = el_line;
      out->push_back(std::move(item));
    }
  }

 private:
  static int LineOf(const toml::node& v, const toml::key& k) {
    int line = static_cast<int>(v.source().begin.line);
    return line > 0 ? line : static_cast<int>(k.source().begin.line);
  }

  void LoadMarkers(const toml::node& v, Config* c) {
    const auto* arr = v.as_array();
    if (!arr) {
      Add(static_cast<int>(v.source().begin.line), kMarkersKey,
          std::string("expected an array of tables ([[rig.markers]]), got ") + TypeName(v));
      return;
    }
    std::vector<RigMarker> markers;
    for (size_t i = 0; i < arr->size(); ++i) {
      const toml::node& el = *arr->get(i);
      int el_line = static_cast<int>(el.source().begin.line);
      const auto* t = el.as_table();
      if (!t) {
        Add(el_line, std::string(kMarkersKey) + "[" + std::to_string(i) + "]",
            std::string("expected a table {color, x_mm, y_mm}, got ") + TypeName(el));
        continue;
      }
      // Keys use the index in the loaded list, as ValidateConfig sees it.
      std::string prefix = std::string(kMarkersKey) + "[" + std::to_string(markers.size()) + "]";
      RigMarker m;
      m.color.clear();
      for (auto&& [k, mv] : *t) {
        std::string key = prefix + "." + std::string(k.str());
        int line = LineOf(mv, k);
        if (const auto* f = FindField(MarkerFields(), std::string(k.str()))) {
          lines_[key] = line;
          std::string err = Assign(mv, f->ref(m));
          if (!err.empty()) Add(line, key, err);
        } else {
          std::string hint;
          size_t best = 3;
          for (const auto& f : MarkerFields()) {
            size_t d = EditDistance(std::string(k.str()), f.key);
            if (d < best) {
              best = d;
              hint = std::string("; did you mean ") + f.key + "?";
            }
          }
          Add(line, key, "unknown key" + hint);
        }
      }
      if (!t->contains("color"))
        lines_[prefix + ".color"] = el_line;  // reported as missing by the validator
      markers.push_back(std::move(m));
    }
    c->rig.markers = std::move(markers);
  }

  // "; did you mean X?" for a close key in the same table, or the same name in
  // another table ("camera.interval" -> "capture.interval").
  static std::string Suggest(const std::string& key) {
    std::vector<std::string> known;
    for (const auto& f : Fields()) known.emplace_back(f.key);
    for (const auto& s : Sections()) known.emplace_back(s.name);
    known.emplace_back(kMarkersKey);
    known.emplace_back(kArucoKey);

    const std::string parent = Parent(key), leaf = Leaf(key);
    size_t limit = leaf.size() <= 3 ? 1 : std::clamp<size_t>(leaf.size() / 3, 2, 3);
    std::string best;
    size_t best_d = limit + 1;
    for (const auto& k : known) {
      if (Parent(k) != parent) continue;
      size_t d = EditDistance(leaf, Leaf(k));
      if (d < best_d) {
        best_d = d;
        best = k;
      }
    }
    if (best.empty()) {
      for (const auto& k : known) {
        if (Leaf(k) == leaf) {
          best = k;
          break;
        }
      }
    }
    return best.empty() ? std::string() : "; did you mean " + best + "?";
  }

  const std::string& file_;
  std::vector<ConfigProblem>* problems_;
  LineMap lines_;
};

Error ProblemsError(const std::string& file, const std::vector<ConfigProblem>& problems,
                    size_t first) {
  size_t n = problems.size() - first;
  std::string detail;
  for (size_t i = first; i < problems.size(); ++i) {
    if (i > first) detail += "\n";
    detail += problems[i].ToString();
  }
  std::string msg = file + ": " + std::to_string(n) +
                    (n == 1 ? " config problem" : " config problems") +
                    ", first: " + problems[first].ToString();
  return MakeError(ErrorClass::kInvalidConfig, std::move(msg), std::move(detail));
}

}  // namespace

bool IsLoopbackAddress(const std::string& address) {
  if (address == "localhost") return true;
  in_addr v4{};
  if (::inet_pton(AF_INET, address.c_str(), &v4) == 1) return (ntohl(v4.s_addr) >> 24) == 127;
  in6_addr v6{};
  if (::inet_pton(AF_INET6, address.c_str(), &v6) == 1) return IN6_IS_ADDR_LOOPBACK(&v6);
  return false;
}

// ---------------------------------------------------------------------------
// Public API

const std::vector<std::string>& KnownBackends(const std::string& kind) {
  // Add a real backend's name here when its driver lands in the factory.
  static const std::map<std::string, std::vector<std::string>> kBackends = {
      {"camera", {"sim", "v4l2", "libcamera"}},
      {"turntable", {"sim", "modbus-tcp", "modbus-rtu", "usb-tic", "manual"}},
      {"button", {"sim", "gpio", "evdev", "modbus"}},
  };
  static const std::vector<std::string> kNone;
  auto it = kBackends.find(kind);
  return it == kBackends.end() ? kNone : it->second;
}

std::string ConfigProblem::ToString() const {
  std::string s = file;
  if (line > 0) s += ":" + std::to_string(line);
  s += ": ";
  if (!key.empty()) s += key + ": ";
  return s + message;
}

Result<Config> LoadConfigString(const std::string& text, const std::string& file,
                                std::vector<ConfigProblem>* problems) {
  std::vector<ConfigProblem> local;
  if (!problems) problems = &local;
  const size_t first = problems->size();

  Config c;
  toml::table root;
  try {
    root = toml::parse(text, file);
  } catch (const toml::parse_error& e) {
    problems->push_back(ConfigProblem{file, static_cast<int>(e.source().begin.line), "",
                                      "TOML syntax error: " + std::string(e.description())});
    return ProblemsError(file, *problems, first);
  }

  Loader loader(file, problems);
  loader.Walk(root, "", &c);
  loader.CheckProfileOverrides(c);
  ApplyProfile(&c);
  Validator(file, &loader.lines(), problems).Run(c);

  // toml++ iterates tables in key order; report in file order (lineless last).
  std::stable_sort(problems->begin() + static_cast<std::ptrdiff_t>(first), problems->end(),
                   [](const ConfigProblem& a, const ConfigProblem& b) {
                     auto key = [](const ConfigProblem& p) {
                       return p.line > 0 ? p.line : std::numeric_limits<int>::max();
                     };
                     return key(a) < key(b);
                   });
  if (problems->size() > first) return ProblemsError(file, *problems, first);
  return c;
}

Result<Config> LoadConfigFile(const std::string& path, std::vector<ConfigProblem>* problems) {
  auto text = ReadFile(path);
  if (!text.ok()) {
    if (problems)
      problems->push_back(ConfigProblem{path, 0, "", "cannot read: " + text.error().ToString()});
    return MakeError(ErrorClass::kInvalidConfig, "cannot read config file " + path,
                     text.error().ToString());
  }
  return LoadConfigString(*text, path, problems);
}

void ValidateConfig(const Config& c, const std::string& file,
                    std::vector<ConfigProblem>* problems) {
  if (!problems) return;
  Validator(file, nullptr, problems).Run(c);
}

std::vector<std::string> SplitCommaList(const std::string& list) {
  std::vector<std::string> out;
  size_t pos = 0;
  while (pos <= list.size()) {
    size_t end = list.find(',', pos);
    if (end == std::string::npos) end = list.size();
    std::string item = list.substr(pos, end - pos);
    const size_t a = item.find_first_not_of(" \t");
    const size_t b = item.find_last_not_of(" \t");
    if (a != std::string::npos) out.push_back(item.substr(a, b - a + 1));
    pos = end + 1;
  }
  return out;
}

void ApplyProfile(Config* c) {
  CaptureConfig& cap = c->capture;
  if (cap.profile == "paper") {
    // The source paper: 30 views a side, ~30 deg apart, one every 2 s, two sides.
    cap.sides = 2;
    cap.views_per_side = 30;
    cap.step_deg = 30.0;
    cap.interval = 2 * kNsPerSec;
  } else if (cap.profile == "full-turn") {
    if (cap.views_per_side >= 1) cap.step_deg = 360.0 / cap.views_per_side;
  }
}

std::string ConfigToToml(const Config& config) {
  Config& c = const_cast<Config&>(config);  // refs are only read here
  std::ostringstream out;
  out << "# aggscan configuration: every field with its effective value.\n"
         "# Durations are strings with a unit: ns us ms s min h (\"500ms\", \"2s\", \"1.5min\").\n";
  for (const auto& section : Sections()) {
    out << "\n[" << section.name << "]\n# " << section.comment << "\n";
    for (const auto& f : Fields()) {
      if (Parent(f.key) != section.name) continue;
      out << "# " << f.comment << "\n";
      if (auto v = ToTomlValue(f.ref(c))) {
        out << Leaf(f.key) << " = " << *v << "\n";
      } else {
        out << "# " << Leaf(f.key) << " =   (not set)\n";
      }
    }
    if (std::string(section.name) == "rig") {
      // Plain keys before the first [[...]] table, which would take them.
      if (c.rig.aruco_markers.empty()) out << "# ArUco scale markers (none)\naruco_markers = []\n";
      if (c.rig.markers.empty()) out << "markers = []\n";
      for (auto& m : c.rig.markers) {
        out << "\n[[" << kMarkersKey << "]]\n";
        for (const auto& f : MarkerFields()) {
          out << "# " << f.comment << "\n" << f.key << " = " << *ToTomlValue(f.ref(m)) << "\n";
        }
      }
      for (auto& m : c.rig.aruco_markers) {
        out << "\n[[" << kArucoKey << "]]\n";
        for (const auto& f : ArucoFields()) {
          out << "# " << f.comment << "\n" << f.key << " = " << *ToTomlValue(f.ref(m)) << "\n";
        }
      }
    }
  }
  return out.str();
}

namespace {

struct Unit {
  const char* name;
  TimeNs ns;
};
constexpr Unit kUnits[] = {
    {"ns", 1},        {"us", 1000},     {"\xC2\xB5s", 1000},  // µs
    {"ms", kNsPerMs}, {"s", kNsPerSec}, {"min", 60 * kNsPerSec}, {"h", 3600 * kNsPerSec}};

}  // namespace

bool ParseDuration(const std::string& s, TimeNs* out) {
  size_t i = 0;
  bool neg = false;
  if (i < s.size() && (s[i] == '-' || s[i] == '+')) neg = s[i++] == '-';
  __int128 whole = 0;
  size_t digits = 0;
  for (; i < s.size() && s[i] >= '0' && s[i] <= '9'; ++i, ++digits) {
    whole = whole * 10 + (s[i] - '0');
    if (whole > std::numeric_limits<int64_t>::max()) return false;
  }
  __int128 frac = 0, frac_scale = 1;
  size_t frac_digits = 0;
  if (i < s.size() && s[i] == '.') {
    ++i;
    for (; i < s.size() && s[i] >= '0' && s[i] <= '9'; ++i, ++frac_digits) {
      if (frac_digits < 18) {  // beyond that the digits are below 1 ns for any unit
        frac = frac * 10 + (s[i] - '0');
        frac_scale *= 10;
      }
    }
    if (frac_digits == 0) return false;
  }
  if (digits == 0) return false;
  while (i < s.size() && s[i] == ' ') ++i;
  std::string unit = s.substr(i);
  const Unit* u = nullptr;
  for (const auto& cand : kUnits) {
    if (unit == cand.name) u = &cand;
  }
  if (!u) return false;
  __int128 ns = whole * u->ns + (frac * u->ns + frac_scale / 2) / frac_scale;
  if (ns > std::numeric_limits<int64_t>::max()) return false;
  *out = static_cast<TimeNs>(neg ? -ns : ns);
  return true;
}

std::string FormatDuration(TimeNs ns) {
  if (ns == 0) return "0s";
  if (ns == std::numeric_limits<TimeNs>::min()) return std::to_string(ns) + "ns";
  std::string sign = ns < 0 ? "-" : "";
  TimeNs a = ns < 0 ? -ns : ns;
  // Whole hours or minutes only; seconds, ms and us with up to three decimals.
  for (const Unit& u : {Unit{"h", 3600 * kNsPerSec}, Unit{"min", 60 * kNsPerSec}}) {
    if (a % u.ns == 0) return sign + std::to_string(a / u.ns) + u.name;
  }
  for (const Unit& u : {Unit{"s", kNsPerSec}, Unit{"ms", kNsPerMs}, Unit{"us", 1000}}) {
    TimeNs milli = u.ns / 1000;
    if (a >= u.ns && a % milli == 0) {
      std::string s = sign + std::to_string(a / u.ns);
      TimeNs rest = (a % u.ns) / milli;  // 0..999
      if (rest) {
        char buf[24];
        std::snprintf(buf, sizeof(buf), ".%03lld", static_cast<long long>(rest));
        std::string f = buf;
        while (f.back() == '0') f.pop_back();
        s += f;
      }
      return s + u.name;
    }
  }
  return sign + std::to_string(a) + "ns";
}

}  // namespace aggscan
