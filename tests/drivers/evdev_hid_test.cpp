// The evdev button against a real input device: a USB HID keyboard gadget
// (dummy_hcd + libcomposite + usb_f_hid, all in Debian's kernel) that the
// kernel's own usbhid / hid-generic turn into /dev/input/eventN. Meant to
// run inside the throwaway VM of tests/vm/run-in-vm.sh; exits 77 (skipped)
// where the gadget cannot be made (modules missing, no configfs).
//
// The gadget is set up here by writing configfs files (no helper programs:
// each costs ~0.3 s under TCG). The test plays the pedal by writing 8-byte
// boot-keyboard reports to /dev/hidg0; unplugging is unbinding the UDC.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <libevdev/libevdev.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>

#include "common/clock.h"
#include "config/config.h"
#include "drivers/evdev/evdev_button.h"
#include "tests/util/eventually.h"

namespace aggscan::evdev {
namespace {

using test::Eventually;
using test::WriteFile;

const std::string kGadget = "/sys/kernel/config/usb_gadget/aggscan-pedal";
const char* kProduct = "aggscan test pedal";
std::string g_udc;    // the dummy UDC the gadget is bound to
std::string g_event;  // /dev/input/eventN of the gadget, seen from the host side

// The boot keyboard report descriptor (HID 1.11, appendix B.1): 8-byte
// input reports [modifiers, reserved, 6 key usages], 1-byte LED output.
const unsigned char kKeyboardDesc[] = {
    0x05, 0x01, 0x09, 0x06, 0xa1, 0x01, 0x05, 0x07, 0x19, 0xe0, 0x29, 0xe7, 0x15, 0x00, 0x25, 0x01,
    0x75, 0x01, 0x95, 0x08, 0x81, 0x02, 0x95, 0x01, 0x75, 0x08, 0x81, 0x03, 0x95, 0x05, 0x75, 0x01,
    0x05, 0x08, 0x19, 0x01, 0x29, 0x05, 0x91, 0x02, 0x95, 0x01, 0x75, 0x03, 0x91, 0x03, 0x95, 0x06,
    0x75, 0x08, 0x15, 0x00, 0x25, 0x65, 0x05, 0x07, 0x19, 0x00, 0x29, 0x65, 0x81, 0x00, 0xc0};

// Binds the gadget to the UDC (plugs it in) and finds its event device.
std::string Plug() {
  if (!WriteFile(kGadget + "/UDC", g_udc)) return "bind UDC " + g_udc;
  g_event.clear();
  const bool found = Eventually([] {
    for (int i = 0; i < 32; ++i) {
      const std::string p = "/dev/input/event" + std::to_string(i);
      const int fd = ::open(p.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC);
      if (fd < 0) continue;
      libevdev* d = nullptr;
      bool ours = false;
      if (libevdev_new_from_fd(fd, &d) == 0) {
        const char* n = libevdev_get_name(d);
        ours = n && std::strstr(n, kProduct);
        libevdev_free(d);
      }
      ::close(fd);
      if (ours) {
        g_event = p;
        return true;
      }
    }
    return false;
  });
  return found ? "" : "no input device for the gadget";
}

std::string MakeGadget() {
  for (const char* d : {"", "/strings", "/strings/0x409", "/configs/c.1", "/configs/c.1/strings",
                        "/configs/c.1/strings/0x409", "/functions", "/functions/hid.usb0"}) {
    const std::string p = kGadget + d;
    if (::mkdir(p.c_str(), 0755) != 0 && errno != EEXIST) return "mkdir " + p;
  }
  const std::string f = kGadget + "/functions/hid.usb0";
  if (!WriteFile(kGadget + "/idVendor", "0x1d6b") || !WriteFile(kGadget + "/idProduct", "0x0104") ||
      !WriteFile(kGadget + "/strings/0x409/manufacturer", "aggscan") ||
      !WriteFile(kGadget + "/strings/0x409/product", kProduct) ||
      !WriteFile(kGadget + "/strings/0x409/serialnumber", "0001") ||
      !WriteFile(kGadget + "/configs/c.1/strings/0x409/configuration", "pedal") ||
      !WriteFile(f + "/protocol", "1") || !WriteFile(f + "/subclass", "1") ||
      !WriteFile(f + "/report_length", "8") ||
      !WriteFile(f + "/report_desc",
                 std::string(reinterpret_cast<const char*>(kKeyboardDesc), sizeof kKeyboardDesc))) {
    return "gadget attributes";
  }
  if (::symlink(f.c_str(), (kGadget + "/configs/c.1/hid.usb0").c_str()) != 0) return "config link";
  for (const auto& e : std::filesystem::directory_iterator("/sys/class/udc")) {
    g_udc = e.path().filename();
    break;
  }
  if (g_udc.empty()) return "no UDC (dummy_hcd)";
  return Plug();
}

// The pedal: one boot-keyboard report per call (usage 0 = nothing down).
class Pedal {
 public:
  Pedal() : fd_(::open("/dev/hidg0", O_RDWR | O_CLOEXEC)) {}
  ~Pedal() {
    if (fd_ >= 0) ::close(fd_);
  }
  bool ok() const { return fd_ >= 0; }
  void Report(unsigned char usage) {
    const unsigned char r[8] = {0, 0, usage, 0, 0, 0, 0, 0};
    ASSERT_EQ(::write(fd_, r, sizeof r), 8) << std::strerror(errno);
  }

 private:
  int fd_;
};

constexpr unsigned char kUsageF1 = 0x3a, kUsageA = 0x04, kUsageNone = 0;

ButtonConfig Config(const std::string& device, const std::string& key) {
  ButtonConfig c;
  c.backend = "evdev";
  c.debounce = 0;
  c.evdev.device = device;
  c.evdev.key = key;
  c.evdev.grab = true;
  return c;
}

TEST(EvdevHid, KeyDownIsAPressOtherKeysAreIgnored) {
  RealClock clock;
  EvdevButton b(clock, Config(g_event, "KEY_F1"));
  std::atomic<int> presses{0};
  std::string source;
  ASSERT_TRUE(b.Start([&](const ButtonPress& p) {
                 source = p.source;
                 ++presses;
               }).ok());
  Pedal pedal;
  ASSERT_TRUE(pedal.ok()) << std::strerror(errno);
  pedal.Report(kUsageF1);
  ASSERT_TRUE(Eventually([&] { return presses == 1; })) << "F1 down not seen";
  EXPECT_EQ(source, "evdev");
  pedal.Report(kUsageNone);  // release: no press
  pedal.Report(kUsageA);     // another key: ignored
  ASSERT_TRUE(Eventually([&] { return b.other_keys() == 1; }));
  pedal.Report(kUsageNone);
  EXPECT_EQ(presses, 1);
  pedal.Report(kUsageF1);
  EXPECT_TRUE(Eventually([&] { return presses == 2; }));
  pedal.Report(kUsageNone);
  EXPECT_TRUE(b.Health().ok());
  b.Stop();
}

TEST(EvdevHid, MissingDeviceAndKeyAreClassified) {
  RealClock clock;
  EvdevButton nodev(clock, Config("usb-nobody-event-kbd", "KEY_F1"));
  Status s = nodev.Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kDeviceMissing);
  EXPECT_NE(s.error().message.find("/dev/input/by-id/usb-nobody-event-kbd"), std::string::npos)
      << s.error().ToString();

  EvdevButton nokey(clock, Config(g_event, "BTN_TRIGGER_HAPPY40"));  // not on a keyboard
  s = nokey.Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidConfig);
  EXPECT_NE(s.error().message.find("has no key BTN_TRIGGER_HAPPY40"), std::string::npos)
      << s.error().ToString();
  EXPECT_NE(s.error().message.find(kProduct), std::string::npos) << s.error().ToString();

  EvdevButton badname(clock, Config(g_event, "KEY_FOOT"));
  s = badname.Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kInvalidConfig);

  // Grabbed by another reader: a conflict.
  EvdevButton first(clock, Config(g_event, "KEY_F1"));
  ASSERT_TRUE(first.Start([](const ButtonPress&) {}).ok());
  EvdevButton second(clock, Config(g_event, "KEY_F1"));
  s = second.Start([](const ButtonPress&) {});
  ASSERT_FALSE(s.ok());
  EXPECT_EQ(s.error().cls, ErrorClass::kConflict) << s.error().ToString();
  first.Stop();
}

// Last: unplugs the gadget.
TEST(EvdevHid, UnplugIsADisconnect) {
  RealClock clock;
  EvdevButton b(clock, Config(g_event, "KEY_F1"));
  ASSERT_TRUE(b.Start([](const ButtonPress&) {}).ok());
  ASSERT_TRUE(WriteFile(kGadget + "/UDC", "\n"));  // unbind: the pedal's cable is pulled
  ASSERT_TRUE(Eventually([&] { return !b.Health().ok(); })) << "unplug not noticed";
  EXPECT_EQ(b.Health().error().cls, ErrorClass::kDisconnected) << b.Health().error().ToString();
  EXPECT_NE(b.Health().error().message.find("went away"), std::string::npos);
  b.Stop();
  // Plugged in again: a new Start() works (what the daemon's reopen does).
  ASSERT_EQ(Plug(), "");
  EvdevButton again(clock, Config(g_event, "KEY_F1"));
  EXPECT_TRUE(again.Start([](const ButtonPress&) {}).ok());
  again.Stop();
}

}  // namespace
}  // namespace aggscan::evdev

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  if (::access("/sys/kernel/config/usb_gadget", F_OK) != 0 ||
      ::access("/sys/class/udc", F_OK) != 0) {
    std::fprintf(stderr,
                 "evdev_hid_test: SKIP: no USB gadget configfs or UDC (modprobe dummy_hcd "
                 "libcomposite usb_f_hid usbhid hid-generic evdev; tests/vm/run-in-vm.sh does it "
                 "in a VM)\n");
    return 77;
  }
  const std::string err = aggscan::evdev::MakeGadget();
  if (!err.empty()) {
    std::fprintf(stderr, "evdev_hid_test: cannot make the HID gadget: %s\n", err.c_str());
    return 1;
  }
  std::fprintf(stderr, "evdev_hid_test: gadget on %s is %s\n", aggscan::evdev::g_udc.c_str(),
               aggscan::evdev::g_event.c_str());
  return RUN_ALL_TESTS();
}
