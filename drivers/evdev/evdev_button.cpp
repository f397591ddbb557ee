#include "drivers/evdev/evdev_button.h"

#include <fcntl.h>
#include <libevdev/libevdev.h>
#include <poll.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

namespace aggscan::evdev {
namespace {

// A path as given, or the first existing stable name for it.
std::string ResolveDevice(const std::string& device) {
  if (device.find('/') != std::string::npos) return device;
  for (const char* dir : {"/dev/input/by-id/", "/dev/input/by-path/", "/dev/input/"}) {
    std::string p = dir + device;
    if (::access(p.c_str(), F_OK) == 0) return p;
  }
  return "/dev/input/by-id/" + device;
}

// KEY_F1, BTN_0, ... or a decimal code.
int KeyCode(const std::string& key) {
  if (!key.empty() && key.find_first_not_of("0123456789") == std::string::npos) {
    const int c = std::stoi(key);
    return c <= KEY_MAX ? c : -1;
  }
  return libevdev_event_code_from_name(EV_KEY, key.c_str());
}

}  // namespace

EvdevButton::EvdevButton(Clock& clock, const ButtonConfig& config)
    : Button(clock, config.debounce), config_(config.evdev) {}

EvdevButton::~EvdevButton() { Stop(); }

std::string EvdevButton::Describe() const {
  return "input-device button, " + config_.key + " of " + config_.device;
}

void EvdevButton::CloseDevice() {
  if (dev_) libevdev_free(dev_);
  dev_ = nullptr;
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

Status EvdevButton::DoStart() {
  code_ = KeyCode(config_.key);
  if (code_ < 0) {
    return MakeError(ErrorClass::kInvalidConfig,
                     "'" + config_.key +
                         "' is no key name; set [button.evdev] key to a KEY_* or BTN_* "
                         "name (evtest shows the device's keys)");
  }
  path_ = ResolveDevice(config_.device);
  fd_ = ::open(path_.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC);
  if (fd_ < 0) {
    const int err = errno;
    if (err == EACCES || err == EPERM) {
      return MakeError(ErrorClass::kDeviceMissing,
                       "no permission to read " + path_ +
                           "; add the service user to the input group "
                           "(or fix the udev rule)",
                       std::strerror(err));
    }
    return MakeError(ErrorClass::kDeviceMissing,
                     "no input device " + path_ +
                         "; check that the pedal is plugged in and "
                         "[button.evdev] device (ls /dev/input/by-id)",
                     std::strerror(err));
  }
  if (const int rc = libevdev_new_from_fd(fd_, &dev_); rc < 0) {
    CloseDevice();
    return MakeError(ErrorClass::kDeviceMissing,
                     path_ + " is not an input event device; check [button.evdev] device",
                     std::strerror(-rc));
  }
  const char* n = libevdev_get_name(dev_);
  name_ = "'" + std::string(n ? n : "?") + "' (" + path_ + ")";
  if (!libevdev_has_event_code(dev_, EV_KEY, static_cast<unsigned>(code_))) {
    CloseDevice();
    return MakeError(ErrorClass::kInvalidConfig,
                     "input device " + name_ + " has no key " + config_.key +
                         "; check [button.evdev] key and device (evtest lists its keys)");
  }
  if (config_.grab) {
    if (const int rc = libevdev_grab(dev_, LIBEVDEV_GRAB); rc < 0) {
      CloseDevice();
      return MakeError(ErrorClass::kConflict,
                       "input device " + name_ +
                           " is grabbed by another program; stop it or set "
                           "[button.evdev] grab = false",
                       std::strerror(-rc));
    }
  }
  stop_ = false;
  other_keys_ = 0;
  thread_ = std::thread([this] { Run(); });
  return OkStatus();
}

void EvdevButton::DoStop() {
  stop_ = true;
  if (thread_.joinable()) thread_.join();
  CloseDevice();  // closing the fd also releases a grab
}

void EvdevButton::Run() {
  while (!stop_) {
    pollfd p{fd_, POLLIN, 0};
    if (::poll(&p, 1, 100) == 0) continue;
    input_event ev{};
    int rc = libevdev_next_event(dev_, LIBEVDEV_READ_FLAG_NORMAL, &ev);
    while (rc == LIBEVDEV_READ_STATUS_SUCCESS || rc == LIBEVDEV_READ_STATUS_SYNC) {
      if (rc == LIBEVDEV_READ_STATUS_SYNC) {
        // Events were dropped (SYN_DROPPED): resynchronise; a key that went
        // down meanwhile is not taken as a press.
        while (libevdev_next_event(dev_, LIBEVDEV_READ_FLAG_SYNC, &ev) ==
               LIBEVDEV_READ_STATUS_SYNC) {
        }
      } else if (ev.type == EV_KEY && ev.value == 1) {
        if (ev.code == code_) {
          DeliverPress("evdev");
        } else {
          ++other_keys_;
        }
      }
      rc = libevdev_next_event(dev_, LIBEVDEV_READ_FLAG_NORMAL, &ev);
    }
    if (rc != -EAGAIN && rc != -EINTR) {
      ReportFault(MakeError(rc == -ENODEV ? ErrorClass::kDisconnected : ErrorClass::kIo,
                            "input device " + name_ +
                                " went away; check the pedal's cable and "
                                "[button.evdev] device",
                            std::strerror(-rc)));
      return;
    }
  }
}

}  // namespace aggscan::evdev
