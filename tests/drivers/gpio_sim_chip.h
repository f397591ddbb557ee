// A gpio-sim chip for the VM tests (gpio_sim_test, full_rig_test): made by
// writing configfs files (no helper programs: each costs ~0.3 s under TCG),
// bank0 with 4 lines, line 0 named "start" (the button) and line 1 "lamp"
// (the light). A press is gpio-sim's simulated pull: `pull-up` drives the
// input high, `pull-down` low; an output's level is read back from
// sim_gpioN/value. Also brings up the loopback interface, which the VM boots
// with down and aggscand's API (and a loopback Modbus peer) need.
#pragma once

#include <net/if.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstdio>
#include <cstring>
#include <fstream>
#include <string>

#include "tests/util/eventually.h"

namespace aggscan::test::gpiosim {

inline const char* kConfigfs = "/sys/kernel/config/gpio-sim";
inline const char* kChipDir = "/sys/kernel/config/gpio-sim/aggscan";

/// True where gpio-sim is loaded and configfs is mounted.
inline bool Available() {
  struct stat st {};
  return ::stat(kConfigfs, &st) == 0;
}

inline std::string ReadLine(const std::string& path) {
  std::ifstream f(path);
  std::string s;
  std::getline(f, s);
  return s;
}

/// The VM boots with the loopback interface down; sets it up (errors to stderr).
inline void BringUpLoopback() {
  const int fd = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  if (fd < 0) return;
  ifreq ifr{};
  std::strncpy(ifr.ifr_name, "lo", IFNAMSIZ - 1);
  if (::ioctl(fd, SIOCGIFFLAGS, &ifr) == 0 && !(ifr.ifr_flags & IFF_UP)) {
    ifr.ifr_flags |= IFF_UP;
    if (::ioctl(fd, SIOCSIFFLAGS, &ifr) != 0) std::perror("bring up lo");
  }
  ::close(fd);
}

/// The simulated chip, once made.
struct Chip {
  std::string name;   // "gpiochipN"
  std::string sysfs;  // /sys/devices/platform/gpio-sim.K/gpiochipN
};

/// Creates the chip into `out`; an empty string on success, else what failed.
inline std::string MakeChip(Chip* out) {
  const std::string dev = kChipDir;
  const std::string bank = dev + "/bank0";
  if (::mkdir(dev.c_str(), 0755) != 0 || ::mkdir(bank.c_str(), 0755) != 0) return "mkdir " + bank;
  if (!WriteFile(bank + "/num_lines", "4")) return "num_lines";
  if (!WriteFile(bank + "/label", "aggscan-sim")) return "label";
  const char* names[] = {"start", "lamp"};
  for (int i = 0; i < 2; ++i) {
    const std::string line = bank + "/line" + std::to_string(i);
    if (::mkdir(line.c_str(), 0755) != 0 || !WriteFile(line + "/name", names[i])) return line;
  }
  if (!WriteFile(dev + "/live", "1")) return "live";
  out->name = ReadLine(bank + "/chip_name");
  out->sysfs = "/sys/devices/platform/" + ReadLine(dev + "/dev_name") + "/" + out->name;
  return out->name.empty() ? "chip_name" : "";
}

/// Sets the simulated level of a line's input (what a switch would do to it).
inline bool SetPull(const Chip& c, int offset, bool high) {
  return WriteFile(c.sysfs + "/sim_gpio" + std::to_string(offset) + "/pull",
                   high ? "pull-up" : "pull-down");
}

/// The line's level as the chip sees it.
inline int Value(const Chip& c, int offset) {
  return std::stoi(ReadLine(c.sysfs + "/sim_gpio" + std::to_string(offset) + "/value"));
}

}  // namespace aggscan::test::gpiosim
