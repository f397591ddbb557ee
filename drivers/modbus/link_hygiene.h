// Keeping a Modbus master in step with its controller.
//
// Modbus cannot cancel a request: an answer that comes after the master's
// response_timeout is still on its way, and whatever request is sent next
// would read it as its own. On TCP libmodbus checks the transaction id and
// refuses such an answer (EMBBADDATA), but the real answer then stays behind
// it, so every later request would again read its predecessor's. On RTU there
// is no id at all: a stale answer of the same shape (a status read's block of
// registers, a single-register write's echo) is taken as the answer. Hence:
//
//  - before every request, whatever already waits on the link is dropped: it
//    cannot be the answer to a request not yet sent (DropStaleInput);
//  - after a time-out or an answer that did not fit, TCP closes the
//    connection (the late answer dies with it; the caller re-opens before the
//    retry), and RTU waits out the late answer: bytes are read and dropped
//    until the line has been quiet for an inter-frame gap, for at most a
//    bounded time (WaitOutLateAnswer).
#pragma once

#include "common/clock.h"

struct _modbus;  // NOLINT(bugprone-reserved-identifier): libmodbus's own tag for modbus_t

namespace aggscan::modbus {

/// Drops input already waiting on the link; returns the number of bytes
/// dropped (0 when there were none or the link has no descriptor).
int DropStaleInput(_modbus* ctx);

/// RTU: reads and drops what arrives until no byte came for `quiet_gap`
/// after the last one, or nothing came within `max_wait` (a frame that began
/// is read to its end, for at most another `max_wait`), then flushes.
/// Returns the number of bytes dropped.
int WaitOutLateAnswer(_modbus* ctx, TimeNs max_wait, TimeNs quiet_gap);

/// The quiet time that ends a frame on a serial line at `baud`: Modbus RTU's
/// 3.5 character times (11 bits each), but at least 50 ms, since USB serial
/// adapters hand bytes over in bursts (an FTDI's latency timer is 16 ms).
TimeNs RtuQuietGap(int baud);

}  // namespace aggscan::modbus
