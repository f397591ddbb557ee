// Typed configuration of aggscan: one struct per module, defaults in the
// struct, one comment per field. Loaded from TOML (see config/sim.toml for a
// complete example); every problem found is reported with its file and line.
//
// Units: millimetres, degrees, and durations written with a unit in TOML
// ("500ms", "2s", "1.5min"); durations are held here as nanoseconds (TimeNs).
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "common/clock.h"
#include "common/error.h"

namespace aggscan {

/// True for addresses only this machine can reach: 127.0.0.0/8, ::1, localhost.
bool IsLoopbackAddress(const std::string& address);

struct DaemonConfig {
  std::string state_dir = "/var/lib/aggscan";  // samples/, queue.db, calibration live here
  std::string listen_address = "127.0.0.1";    // HTTP API bind address
  int listen_port = 8470;                      // HTTP API port (0 = pick a free one, tests)
  std::string log_level = "info";              // error|warning|notice|info|debug
  double time_scale =
      1.0;  // sim rig only (> 1 with a real device is refused): clock runs this many times faster
  TimeNs reopen_backoff_min =
      1 * kNsPerSec;  // first retry of a device that failed to open (real time)
  TimeNs reopen_backoff_max =
      30 * kNsPerSec;  // retries double up to this; reset when the device opens
  TimeNs health_probe_interval =
      5 * kNsPerSec;  // turntable status read while no side runs (0 = off)
  // Host names (or addresses, IPv6 in brackets) the API answers to besides localhost,
  // 127.0.0.1, [::1] and listen_address, comma-separated, each with or without ":port"
  std::string allowed_hosts;
  // Origins ("http://host:port", comma-separated) allowed to POST besides the allowed hosts
  std::string allowed_origins;
  // The live camera view for screens (GET /api/v1/preview): a still this often
  // while someone watches and no side runs (0 = no live view)
  TimeNs preview_interval = 250 * kNsPerMs;
  int preview_max_side = 640;  // preview frames' longer side at most this, pixels
  // Accounts the API checks every request against (name:role:crypt hash per
  // line, mode 600); empty = no credentials, allowed on a loopback address only
  std::string credentials_file;
  // PEM certificate (chain) and private key: serve the API over HTTPS
  std::string tls_certificate;
  std::string tls_key;
  // The console's static files; empty = the ones installed beside the
  // binaries (../share/aggscan/web, or ../web in a build tree)
  std::string web_root;

  bool operator==(const DaemonConfig&) const = default;
};

// Capture profiles (ApplyProfile):
//   paper     the source paper's protocol: sides 2, views_per_side 30, step_deg 30,
//             interval 2s. These four are fixed by the profile: a file that gives
//             one of them with another value is a problem ("set capture.profile =
//             \"custom\" to change ..."); giving the same value is allowed.
//   full-turn views_per_side (default 30) evenly over one turn: step_deg =
//             360/views_per_side; sides and interval are free; an explicit step_deg
//             other than 360/views_per_side is a problem.
//   custom    every value as given.
struct CaptureConfig {
  std::string profile = "paper";  // paper | full-turn | custom
  // turntable: the rock turns before a camera on a tripod. moving_camera: the
  // rock lies still among the disc's labels (or ArUco markers) and the
  // operator walks the camera round it, a view at each prompt; the worker
  // poses the views by SfM and scales them by the markers. Needs
  // turntable.backend = "manual" (nothing is driven).
  std::string mode = "turntable";
  int sides = 2;                    // poses of the rock (operator flips between sides)
  int views_per_side = 30;          // photos per side
  double step_deg = 30.0;           // turntable step between views (full-turn: 360/views_per_side)
  TimeNs interval = 2 * kNsPerSec;  // view i of a side is due at t0 + i*interval
  TimeNs settle = 300 * kNsPerMs;   // wait after in-position before the shot (platter oscillation)
  TimeNs home_timeout = 30 * kNsPerSec;  // homing must finish within this
  TimeNs move_timeout = 5 * kNsPerSec;   // one step must reach in-position within this
  TimeNs frame_timeout = 5 * kNsPerSec;  // a still must arrive within this after the trigger
  TimeNs poll_interval = 20 * kNsPerMs;  // turntable status polling period while moving
  TimeNs stall_timeout = 1 * kNsPerSec;  // moving but position unchanged this long = stalled
  int comm_retries = 2;                  // turntable communication retries before a fault

  bool operator==(const CaptureConfig&) const = default;
};

struct ExposureConfig {
  bool manual = true;           // lock exposure so all views of a rock share it
  double exposure_us = 8000.0;  // shutter time, microseconds
  double gain = 1.0;            // analogue gain (1.0 = base ISO)
  double wb_red = 1.0;          // white balance gains, locked like exposure
  double wb_blue = 1.0;

  bool operator==(const ExposureConfig&) const = default;
};

// The V4L2 camera backend (drivers/v4l2/): pixel format, buffers, timeout and
// how the locked settings map onto the device's controls.
struct V4l2CameraConfig {
  std::string pixel_format = "auto";  // auto (MJPEG if offered, else raw) | mjpeg | yuyv | uyvy |
                                      // nv12 | rgb24 | bgr24 | grey
  int buffers = 3;                    // mmap buffers requested from the driver, 2..32
  TimeNs frame_timeout = 2 * kNsPerSec;  // no frame this long after a still request = timeout
  // Gain and red/blue balance controls are unitless on most devices: the device
  // value is round(factor x reference), the reference being the control's own
  // default value unless gain_unit is set (> 0).
  int gain_unit = 0;  // device gain value that means gain 1.0 (0 = the control's default)
  int focus = -1;  // manual focus position in device units (FOCUS_ABSOLUTE); -1 = leave focus alone
  bool strict_controls =
      true;  // refuse to configure when a locked setting has no control on the device

  bool operator==(const V4l2CameraConfig&) const = default;
};

// The libcamera camera backend (drivers/libcamera/): which camera, the stream
// asked of its pipeline, buffers and timeout. Exposure, gain and white balance
// are set through libcamera controls on every request and read back from the
// completed request's metadata.
struct LibcameraCameraConfig {
  std::string camera_id;  // libcamera camera id (`cam -l`); empty = the camera at `index`
  int index = 0;          // position in libcamera's camera list when camera_id is empty
  std::string role =
      "still";  // stream role asked of the pipeline: still | raw | video | viewfinder
  std::string pixel_format = "auto";  // auto (the pipeline's choice, if encodable) | mjpeg | yuyv |
                                      // uyvy | nv12 | rgb888 | bgr888 | r8
  int buffers = 0;  // frame buffers to allocate, 1..32; 0 = the pipeline's default
  TimeNs frame_timeout =
      2 * kNsPerSec;  // no completed frame this long after a still request = timeout
  bool strict_controls =
      true;  // refuse to configure when a locked setting has no libcamera control

  bool operator==(const LibcameraCameraConfig&) const = default;
};

struct CameraConfig {
  std::string backend = "sim";  // sim | v4l2 | libcamera
  std::string id = "sim-cam0";  // camera id recorded in every sidecar
  std::string device;           // device path or udev name for real backends
  int width = 2016;             // still resolution, pixels
  int height = 1512;
  int jpeg_quality = 92;  // 1..100, when the driver encodes JPEG itself
  // The lens's nominal focal length and the sensor's active width (datasheet
  // values; 0 = unknown). Without a rig calibration the SfM path holds
  // lens_focal_mm / sensor_width_mm * width as the focal while it poses the
  // views; with neither, COLMAP starts from its own default.
  double lens_focal_mm = 0.0;
  double sensor_width_mm = 0.0;
  ExposureConfig exposure;
  V4l2CameraConfig v4l2;
  LibcameraCameraConfig libcamera;

  bool operator==(const CameraConfig&) const = default;
};

struct SimTurntableFaults {
  std::optional<double> stall_at_deg;  // motion stops at this absolute angle (stall)
  int timeout_every_n_moves = 0;       // every n-th move the controller stops answering (0 = never)
  std::optional<TimeNs> disconnect_after;  // device disappears this long after open

  bool operator==(const SimTurntableFaults&) const = default;
};

// The Modbus turntable backends (drivers/modbus/): the link, the register map
// (a profile file in config/turntables/) and the drive train's scaling.
struct ModbusTurntableConfig {
  std::string profile = "generic";  // profile name (PROFILE_DIR/NAME.toml) or a path to a .toml
  std::string profile_dir = "/etc/aggscan/turntables";  // where profile names are looked up
  int unit_id = 1;                                      // Modbus unit (slave) id, 1..247
  // modbus-tcp:
  std::string host;  // controller or gateway address
  int port = 502;    // Modbus/TCP port
  // modbus-rtu:
  std::string device;           // serial device, e.g. /dev/ttyUSB0 or /dev/aggscan/turntable
  int baud = 19200;             // line speed, bit/s
  std::string parity = "none";  // none | even | odd
  int data_bits = 8;            // 5..8
  int stop_bits = 1;            // 1 | 2
  bool rs485 = false;           // switch the port to RS-485 mode (TIOCSRS485) where it supports it
  TimeNs response_timeout = 200 * kNsPerMs;  // one request must be answered within this
  int retries = 2;  // a request that got no answer is repeated this many times
  // Scaling: steps per platter revolution = motor_steps_per_rev * microsteps * gear_ratio.
  int motor_steps_per_rev = 200;  // full steps (or encoder counts) per motor revolution
  int microsteps = 16;            // microstepping factor set on the drive
  double gear_ratio = 1.0;        // motor revolutions per platter revolution
  // Motion options:
  bool shortest_path = false;  // go to the target's position modulo 360 the shorter way round
  double backlash_comp_deg =
      0.0;  // approach every target from one side, overshooting by this (0 = off)
  std::string backlash_approach =
      "positive";  // positive | negative: the side targets are approached from
  double in_position_window_deg =
      0.05;  // in-position also needs the measured angle this close to the target

  /// Steps per platter revolution.
  double steps_per_rev() const {
    return motor_steps_per_rev * static_cast<double>(microsteps) * gear_ratio;
  }
  bool operator==(const ModbusTurntableConfig&) const = default;
};

// The USB turntable backend "usb-tic" (drivers/usb/): a Pololu Tic stepper
// controller on its native USB interface, through libusb.
struct UsbTicConfig {
  std::string
      serial_number;  // the Tic's USB serial number ("00123456"); empty = the only Tic attached
  int vendor_id = 0x1FFB;  // USB vendor ID (Pololu's)
  int product_id = 0;      // USB product ID; 0 = any Tic model (T825, T834, T500, N825, T249, 36v4)
  // Scaling: microsteps per platter revolution = motor_steps_per_rev * microsteps * gear_ratio.
  int motor_steps_per_rev = 200;  // full steps per motor revolution
  int microsteps = 8;       // step mode set on open: 1, 2, 4, 8, 16, 32 (36v4 also 64, 128, 256)
  double gear_ratio = 1.0;  // motor revolutions per platter revolution
  std::string home = "reverse";     // reverse | forward: the Tic's homing (limit switch) direction;
                                    // here: the platter's place at StartHome is angle 0
  TimeNs timeout = 500 * kNsPerMs;  // one control transfer must complete within this
  bool shortest_path = false;       // go to the target's position modulo 360 the shorter way round
  double backlash_comp_deg =
      0.0;  // approach every target from one side, overshooting by this (0 = off)
  std::string backlash_approach =
      "positive";  // positive | negative: the side targets are approached from
  double in_position_window_deg =
      0.05;  // in-position also needs the position this close to the target

  /// Microsteps per platter revolution.
  double steps_per_rev() const {
    return motor_steps_per_rev * static_cast<double>(microsteps) * gear_ratio;
  }
  bool operator==(const UsbTicConfig&) const = default;
};

struct TurntableConfig {
  std::string backend = "sim";  // sim | modbus-tcp | modbus-rtu | usb-tic | manual
  // manual (a table turned by hand, the study's own protocol): the prompt to
  // turn ends this long before the next view is due, and the status light
  // goes steady (hands off) so the table is still when the camera shoots.
  TimeNs manual_hands_off = 500 * kNsPerMs;
  double max_speed_deg_s = 60.0;  // trapezoidal profile speed limit
  double accel_deg_s2 = 180.0;    // and acceleration limit
  // Sim model of a real platter:
  double repeatability_deg = 0.05;               // 1-sigma random angle error per move
  double backlash_deg = 0.1;                     // lost motion on direction reversal
  double settle_amplitude_deg = 0.3;             // oscillation amplitude when the move ends
  TimeNs settle_time_constant = 120 * kNsPerMs;  // exponential decay of that oscillation
  double settle_frequency_hz = 6.0;              // its frequency
  TimeNs home_duration = 1500 * kNsPerMs;        // sim homing time
  SimTurntableFaults faults;
  ModbusTurntableConfig modbus;  // modbus-tcp / modbus-rtu only
  UsbTicConfig usb;              // usb-tic only

  bool operator==(const TurntableConfig&) const = default;
};

// A GPIO line through libgpiod (button backend gpio, status light gpio).
struct GpioLineConfig {
  std::string chip = "gpiochip0";  // chip name (gpiochip0), path (/dev/gpiochip0), number or label
  std::string line = "0";          // line offset ("17") or line name ("start")
  bool active_low = false;         // active (pressed / lit) = low level
  std::string bias = "as-is";      // inputs: as-is | pull-up | pull-down | disable

  bool operator==(const GpioLineConfig&) const = default;
};

// An input device key (button backend evdev): USB foot pedal, keypad.
struct EvdevButtonConfig {
  std::string device;          // /dev/input/eventN, or a name in /dev/input/by-id or by-path
  std::string key = "KEY_F1";  // key code name (KEY_*, BTN_*) or its number
  bool grab = false;           // EVIOCGRAB: the key reaches no other reader (console, X)

  bool operator==(const EvdevButtonConfig&) const = default;
};

// A Modbus discrete input or coil polled as a button (backend modbus), on a
// link of its own or the turntable's (link = "turntable": the
// [turntable.modbus] settings of a modbus-tcp turntable, a second connection).
struct ModbusButtonConfig {
  std::string link = "turntable";            // turntable | tcp | rtu
  std::string host;                          // tcp: controller or gateway address
  int port = 502;                            // tcp: port
  std::string device;                        // rtu: serial device
  int baud = 19200;                          // rtu: line speed, bit/s (8 data bits, 1 stop bit)
  std::string parity = "none";               // rtu: none | even | odd
  int unit_id = 1;                           // Modbus unit (slave) id
  TimeNs response_timeout = 200 * kNsPerMs;  // one request must be answered within this
  std::string input = "discrete";            // discrete (function 2) | coil (function 1)
  int address = 0;                           // bit address, 0-based as on the wire
  TimeNs poll_interval = 20 * kNsPerMs;      // read period; a press must last longer than this

  bool operator==(const ModbusButtonConfig&) const = default;
};

struct ButtonConfig {
  std::string backend = "sim";      // sim | gpio | evdev | modbus
  TimeNs debounce = 50 * kNsPerMs;  // presses closer than this are one press
  GpioLineConfig gpio;              // gpio only
  EvdevButtonConfig evdev;          // evdev only
  ModbusButtonConfig modbus;        // modbus only

  bool operator==(const ButtonConfig&) const = default;
};

// The optional status light (drivers/status_light.h has the patterns):
// ready = steady, capturing = slow blink, flip the rock = fast blink,
// fault = double flash, off while aggscand is not running.
struct ModbusLightConfig {
  std::string link =
      "turntable";  // turntable ([turntable.modbus]) | button ([button.modbus]'s link)
  int coil = 0;     // coil address written (function 5), 0-based as on the wire

  bool operator==(const ModbusLightConfig&) const = default;
};

struct LightConfig {
  std::string backend = "none";  // none | gpio | modbus
  GpioLineConfig gpio;           // gpio: the output line (bias unused)
  ModbusLightConfig modbus;      // modbus: the coil

  bool operator==(const LightConfig&) const = default;
};

struct SimConfig {
  uint64_t seed = 1;                   // procedural rock, noise and turntable errors
  std::string rock_mesh;               // PLY/OBJ/STL file; empty = procedural rock from seed
  std::string rock_unit = "mm";        // unit of rock_mesh coordinates: mm | cm | m
  double rock_size_mm = 0.0;           // procedural rock longest dimension; 0 = random 70..200 mm
  double camera_elevation_deg = 35.0;  // camera above the turntable plane, 30..45
  double camera_distance_mm = 650.0;   // from the turntable centre
  double hfov_deg = 40.0;              // horizontal field of view
  double k1 = -0.08;                   // radial distortion (Brown) coefficients
  double k2 = 0.02;
  double noise_sigma = 2.0;  // sensor noise, 8-bit levels
  // A wet or polished stone: the key light's specular highlight (Phong), this
  // strong against the key's diffuse light (0 = a matte stone) ...
  double rock_gloss = 0.0;
  double rock_shininess = 60.0;  // ... and this sharp (Phong exponent)
  bool write_truth = false;      // write ground-truth masks/poses next to the sample (tests)
  // The sim's operator at a hand-turned table (turntable.backend = "manual"):
  // after each prompt the hand waits a reaction time, then turns the table by
  // the plan's step plus a uniform error within +-hand_angle_error_deg over a
  // turn time (a smooth start and stop). Every hand_late_every-th view the hand
  // is late and turns while the camera exposes it: a blurred view.
  double hand_angle_error_deg = 5.0;
  TimeNs hand_reaction_min = 200 * kNsPerMs;
  TimeNs hand_reaction_max = 600 * kNsPerMs;
  TimeNs hand_turn_min = 300 * kNsPerMs;
  TimeNs hand_turn_max = 700 * kNsPerMs;
  int hand_late_every = 0;  // 0 = never late
  // The sim's operator walking the camera round a still rock (capture.mode =
  // "moving_camera"): at each prompt, after a reaction and a walk time (the
  // hand_* ranges), the camera stands at the next position of a rough ring:
  // the plan's angle as azimuth, the elevation alternating by
  // walk_elevation_spread_deg about camera_elevation_deg, with random
  // offsets of azimuth, elevation, distance, aim point and roll.
  // walk_shuffle: the positions are visited in a random order.
  double walk_elevation_spread_deg = 24.0;
  bool walk_shuffle = false;
  // What lies on the turntable: "rock" (the procedural or mesh rock) or
  // "charuco" (the [calibration] board, printed on paper, lying flat on the
  // disc; no rock), for rendering a rig calibration capture.
  std::string scene = "rock";
  std::string board_image;  // charuco: greyscale PGM (P5) of the board area, no margin
                            // (`aggscan calibrate board --out FILE.pgm --margin-mm 0`)
  double board_x_mm = 0.0;  // charuco: board centre on the disc (turntable frame), mm
  double board_y_mm = 0.0;
  double board_yaw_deg = 0.0;  // charuco: board x axis from the turntable x axis, ccw, degrees
  std::string aruco_image;     // rig.aruco_markers: greyscale PGM (P5) of the markers side by
                               // side in list order, each its black square only, no margin
                               // (`aggscan calibrate aruco --out FILE.pgm`); needed by the sim
                               // camera when rig.aruco_markers is not empty

  bool operator==(const SimConfig&) const = default;
};

// The ChArUco board used for the rig calibration (`aggscan calibrate`): printed
// on paper and laid flat on the turntable disc. Board frame (mm): origin at the
// centre of the squares area, x along the printed image's columns, y towards
// its top edge, z up out of the paper; the default 7 x 5 squares of 30 mm
// (210 x 150 mm) fits an A4 sheet and the 305 mm disc.
struct CalibrationConfig {
  std::string dictionary = "DICT_5X5_100";  // ArUco dictionary of the markers (OpenCV name)
  int squares_x = 7;                        // chessboard squares along the board's x axis
  int squares_y = 5;                        // and along its y axis
  double square_mm = 30.0;                  // side of one chessboard square, as printed
  double marker_mm = 22.0;                  // side of one ArUco marker (< square_mm), as printed

  bool operator==(const CalibrationConfig&) const = default;
};

struct RigMarker {
  std::string color;  // red | green | blue | yellow
  double x_mm = 0.0;  // centre in the turntable frame (z up, origin at the axis)
  double y_mm = 0.0;

  bool operator==(const RigMarker&) const = default;
};

// An ArUco marker printed on white paper and laid flat on the disc: the
// alternative scale reference to the colour labels. Marker frame as for the
// [calibration] board: origin at the centre of the black square, x along the
// printed image's columns, y towards its top row; turntable frame p =
// Rz(yaw_deg) * p_marker + (x_mm, y_mm, 0).
struct ArucoMarker {
  int id = -1;        // marker id in rig.aruco_dictionary
  double x_mm = 0.0;  // centre of the black square, turntable frame (z up, origin at the axis)
  double y_mm = 0.0;
  double yaw_deg = 0.0;  // marker x axis from the turntable x axis, counter-clockwise, degrees

  bool operator==(const ArucoMarker&) const = default;
};

// White paper around each ArUco marker's black square, as a fraction of
// rig.aruco_size_mm (the quiet zone a detector needs; the sim draws it).
inline constexpr double kArucoPaperMarginFrac = 0.25;

struct RigConfig {
  double turntable_diameter_mm = 305.0;  // 30.5 cm disc, as in the source study
  double marker_size_mm = 20.0;          // side of each square colour label
  std::vector<RigMarker> markers = {     // the study's four background labels
      {"red", 120.0, 0.0},
      {"green", 0.0, 120.0},
      {"blue", -120.0, 0.0},
      {"yellow", 0.0, -120.0}};
  std::string aruco_dictionary = "DICT_4X4_50";  // ArUco dictionary of aruco_markers (OpenCV name)
  double aruco_size_mm = 30.0;  // side of each ArUco marker's black square, as printed
  std::vector<ArucoMarker>
      aruco_markers;  // ArUco scale markers on the disc; empty = none (default)

  bool operator==(const RigConfig&) const = default;
};

// Foreground masks of the worker (pipeline/masks/mask.h): the classical
// segmentation, or a salient-object network (ONNX, run by OpenCV DNN) whose
// output, resized to the photo and thresholded, seeds the same refinement.
// The network takes one 1x3xHxW float input, RGB, each channel (value/255 -
// mean) / std, and gives one HxW map (1x1xHxW, 1xHxW or HxW).
struct MaskConfig {
  std::string method = "classical";  // classical | onnx
  std::string model;                 // onnx: path of the .onnx file
  int input_width = 320;  // onnx: network input size, pixels (the photo is resized to it)
  int input_height = 320;
  double mean_r = 0.485;  // onnx: per-channel mean subtracted from value/255 (ImageNet's)
  double mean_g = 0.456;
  double mean_b = 0.406;
  double std_r = 0.229;  // onnx: and the standard deviation it is divided by
  double std_g = 0.224;
  double std_b = 0.225;
  std::string output = "probability";  // onnx: probability (sigmoid already applied) | logits
  double threshold = 0.5;              // onnx: probability above which a pixel is rock
  // The empty-turntable photo of a view (store/empty_turntable.h) is the one
  // shot nearest to its measured angle, when within this: farther, the
  // disc's labels and grain would not line up (0.5 deg is 0.9 mm at the rim
  // of a 200 mm disc).
  double empty_turntable_max_angle_deg = 0.5;

  bool operator==(const MaskConfig&) const = default;
};

struct WorkerConfig {
  TimeNs poll_interval = 500 * kNsPerMs;  // queue polling period when idle
  int nice = 10;                          // CPU priority below the capture daemon
  /// Poses: turntable+ba (calibration + measured angles refined by bundle
  /// adjustment, ~2.5 s a side) | turntable (calibration + measured angles as
  /// read) | sfm (COLMAP) | auto (turntable+ba with a rig calibration, sfm
  /// without). Not auto by default: SfM costs minutes a side on the rig's CPU.
  std::string poses = "turntable+ba";
  /// A job whose run fails or crashes this many times is marked failed (the
  /// queue moves on; `aggscan retry ID` puts it back after a fix).
  int max_attempts = 3;
  /// A job found running at start-up this many times in a row (the whole
  /// worker killed or powered off during it each time, e.g. by the OOM
  /// killer) is marked failed.
  int max_interruptions = 10;
  /// The worker reports itself (state, job, stage, progress) in the queue
  /// database this often, and at once when its stage changes (at most twice
  /// a second).
  TimeNs heartbeat_interval = 5 * kNsPerSec;
  /// aggscand calls the worker unhealthy when it has not reported for this
  /// long (0: the daemon does not watch it). Kept in real time, whatever
  /// daemon.time_scale.
  TimeNs silent_after = 60 * kNsPerSec;

  bool operator==(const WorkerConfig&) const = default;
};

// The stone a rig measures, by default: every sample armed without a
// material of its own records this one. Mass = volume x specific gravity x
// the density of water (1 g/cm3), so mass is only as good as the specific
// gravity and its basis: bulk SSD (saturated surface-dry, the one riprap
// gradations by mass use, EN 13383-2 / ASTM C127) or oven-dry.
struct MaterialConfig {
  std::string name;                // e.g. "granite, quarry X"; empty = none given
  double specific_gravity = 0;     // 0 = unknown: no mass is computed until one is given
  std::string basis = "bulk-ssd";  // bulk-ssd | oven-dry

  bool operator==(const MaterialConfig&) const = default;
};

struct Config {
  DaemonConfig daemon;
  CaptureConfig capture;
  CameraConfig camera;
  TurntableConfig turntable;
  ButtonConfig button;
  LightConfig light;
  SimConfig sim;
  RigConfig rig;
  CalibrationConfig calibration;
  MaskConfig mask;
  WorkerConfig worker;
  MaterialConfig material;

  bool operator==(const Config&) const = default;
};

/// One problem found in a config file.
struct ConfigProblem {
  std::string file;
  int line = 0;     // 1-based, 0 when not tied to a line
  std::string key;  // dotted key, e.g. "capture.interval"
  std::string message;
  std::string ToString() const;  // "file:line: key: message"
};

/// Backend names known for a device kind ("camera", "turntable", "button");
/// empty for an unknown kind. The one list the validator and the factory share.
const std::vector<std::string>& KnownBackends(const std::string& kind);

/// Loads and validates a TOML file on top of the defaults, applies the capture
/// profile and runs ValidateConfig. Appends every problem found (syntax error,
/// unknown key with a "did you mean", wrong type, out-of-range value, cross-field
/// rule), not just the first; the result is a kInvalidConfig error iff this call
/// appended any. `problems` may be null.
Result<Config> LoadConfigFile(const std::string& path, std::vector<ConfigProblem>* problems);
/// Same, from a string (file is used in messages).
Result<Config> LoadConfigString(const std::string& toml, const std::string& file,
                                std::vector<ConfigProblem>* problems);
/// Checks every field's range/choices and the cross-field rules (profile vs
/// steps, a step must fit in the interval, unique marker colours, ...); appends
/// problems (line 0: a struct has no lines).
void ValidateConfig(const Config& c, const std::string& file, std::vector<ConfigProblem>* problems);
/// The entries of a comma-separated list (daemon.allowed_hosts), trimmed, empty ones left out.
std::vector<std::string> SplitCommaList(const std::string& list);
/// Applies the capture profile: paper = 2x30x30deg@2s, full-turn = 360/N steps,
/// custom = unchanged (see the rule above CaptureConfig).
void ApplyProfile(Config* c);
/// Effective config as TOML (every field with its comment, durations with
/// units, unset optionals as commented lines). LoadConfigString of it gives c back.
std::string ConfigToToml(const Config& c);
/// "500ms", "2s", "1.5min" -> ns; false if malformed. Units: ns us ms s min h;
/// an optional leading '-'; a decimal fraction is rounded to the nearest ns.
bool ParseDuration(const std::string& s, TimeNs* out);
/// Shortest exact form: "0s", "300ms", "1.5s", "90s", "2min", "1234ns".
std::string FormatDuration(TimeNs ns);

}  // namespace aggscan
