#include "drivers/modbus/link_hygiene.h"

#include <modbus/modbus.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>

namespace aggscan::modbus {

int DropStaleInput(modbus_t* ctx) {
  const int fd = modbus_get_socket(ctx);
  if (fd < 0) return 0;
  int pending = 0;
  if (ioctl(fd, FIONREAD, &pending) != 0 || pending <= 0) return 0;
  modbus_flush(ctx);
  return pending;
}

int WaitOutLateAnswer(modbus_t* ctx, TimeNs max_wait, TimeNs quiet_gap) {
  const int fd = modbus_get_socket(ctx);
  if (fd < 0) return 0;
  TimeNs deadline = MonotonicNs() + max_wait;
  int dropped = 0;
  bool extended = false;
  while (true) {
    const TimeNs now = MonotonicNs();
    if (dropped > 0 && !extended && now + quiet_gap > deadline) {
      deadline = now + max_wait;  // a frame that began is read to its end
      extended = true;
    }
    const TimeNs wait = dropped > 0 ? std::min(quiet_gap, deadline - now) : deadline - now;
    if (wait <= 0) break;
    pollfd p{fd, POLLIN, 0};
    const int rc = poll(&p, 1, static_cast<int>((wait + kNsPerMs - 1) / kNsPerMs));
    if (rc < 0 && errno == EINTR) continue;
    if (rc <= 0) break;  // quiet (or the line failed: the next request tells)
    if (!(p.revents & POLLIN)) break;
    char buf[256];
    const ssize_t n = read(fd, buf, sizeof(buf));
    if (n <= 0) break;
    dropped += static_cast<int>(n);
  }
  modbus_flush(ctx);
  return dropped;
}

TimeNs RtuQuietGap(int baud) {
  const TimeNs chars = baud > 0 ? static_cast<TimeNs>(3.5 * 11 * 1e9 / baud) : 0;
  return std::max<TimeNs>(chars, 50 * kNsPerMs);
}

}  // namespace aggscan::modbus
