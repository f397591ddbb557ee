#!/usr/bin/env python3
"""A turntable controller speaking aggscan's generic register map
(config/turntables/generic.toml) over Modbus/TCP, built on pymodbus: an
implementation independent of libmodbus, for the interoperability test
(tests/drivers/modbus_pymodbus_test.cpp starts it on a free port).

Holding registers, 0-based: 0-1 target (int32 steps, high word first),
2 command (1 move, 2 home, 3 stop, 4 reset alarm), 3 status (bit 0 enabled,
1 moving, 2 in position, 3 homed, 4 alarm), 4-5 actual position, 6 alarm
code, 7 speed (0.1 deg/s), 8 acceleration (0.1 deg/s^2).

Test control, registers a client of the test writes or reads: 10 answers the
next write to the command register this many ms late, 11 the next read of the
status register (both executed at once, answered late, nothing else served
meanwhile: a controller slower than the master's response_timeout); 12 counts
stop commands, 13 every command written.

The platter moves at constant speed (a move takes |distance| / speed; the
acceleration register is only kept), computed from time.monotonic() whenever
the registers are read, so what a client reads is where the platter is.
"""
import argparse
import asyncio
import threading
import time

from pymodbus.datastore import (ModbusSequentialDataBlock, ModbusServerContext,
                                ModbusSlaveContext)
from pymodbus.server import StartAsyncTcpServer

TARGET, COMMAND, STATUS, ACTUAL, ALARM, SPEED, ACCEL = 0, 2, 3, 4, 6, 7, 8
LATE_COMMAND_MS, LATE_STATUS_MS, STOPS, COMMANDS = 10, 11, 12, 13


class Platter:
    """Constant-speed motion in steps, homing as a fixed-time run to 0."""

    def __init__(self, steps_per_rev, home_seconds):
        self.steps_per_deg = steps_per_rev / 360.0
        self.home_seconds = home_seconds
        self.pos = 0.0
        self.start = 0.0
        self.goal = 0.0
        self.t0 = 0.0
        self.duration = 0.0
        self.moving = False
        self.homing = False
        self.homed = False
        self.in_position = False

    def advance(self, now):
        if not (self.moving or self.homing):
            return
        f = 1.0 if self.duration <= 0 else (now - self.t0) / self.duration
        if f >= 1.0:
            self.pos = self.goal
            self.homed = self.homed or self.homing
            self.moving = self.homing = False
            self.in_position = True
        else:
            self.pos = self.start + (self.goal - self.start) * f

    def run(self, now, goal, duration, homing):
        self.advance(now)
        self.start, self.goal, self.t0, self.duration = self.pos, goal, now, duration
        self.moving, self.homing, self.in_position = not homing, homing, False
        if homing:
            self.homed = False


class Registers(ModbusSequentialDataBlock):
    """The register block: reads see the platter now, writes to the
    command register act at once."""

    def __init__(self, platter):
        super().__init__(0, [0] * 16)
        self.platter = platter
        self.lock = threading.Lock()

    def _refresh(self):
        p = self.platter
        p.advance(time.monotonic())
        steps = int(round(p.pos)) & 0xFFFFFFFF
        status = 1 | (2 if p.moving or p.homing else 0) | (4 if p.in_position else 0) | (
            8 if p.homed else 0)
        super().setValues(STATUS, [status])
        super().setValues(ACTUAL, [steps >> 16, steps & 0xFFFF])
        super().setValues(ALARM, [0])

    def _late(self, register):
        """The delay armed in `register` (ms), disarmed; 0 when none."""
        ms = super().getValues(register, 1)[0]
        if ms:
            super().setValues(register, [0])
        return ms / 1000.0

    def getValues(self, address, count=1):
        with self.lock:
            self._refresh()
            values = super().getValues(address, count)
            delay = self._late(LATE_STATUS_MS) if address <= STATUS < address + count else 0
        if delay:
            time.sleep(delay)  # blocks the server's loop: the answer is late
        return values

    def setValues(self, address, values):
        delay = 0
        with self.lock:
            if not isinstance(values, list):
                values = [values]
            super().setValues(address, values)
            if address <= COMMAND < address + len(values):
                cmd = values[COMMAND - address]
                self._command(cmd)
                super().setValues(COMMANDS, [super().getValues(COMMANDS, 1)[0] + 1])
                if cmd == 3:
                    super().setValues(STOPS, [super().getValues(STOPS, 1)[0] + 1])
                delay = self._late(LATE_COMMAND_MS)
            self._refresh()
        if delay:
            time.sleep(delay)

    def _command(self, cmd):
        p = self.platter
        now = time.monotonic()
        if cmd == 1:
            hi, lo = super().getValues(TARGET, 2)
            target = (hi << 16) | lo
            if target >= 1 << 31:
                target -= 1 << 32
            speed = super().getValues(SPEED, 1)[0] * 0.1 * p.steps_per_deg
            if speed > 0:
                p.advance(now)
                p.run(now, float(target), abs(target - p.pos) / speed, homing=False)
        elif cmd == 2:
            p.run(now, 0.0, p.home_seconds, homing=True)
        elif cmd == 3:
            p.advance(now)
            p.moving = p.homing = p.in_position = False


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--unit", type=int, default=1)
    parser.add_argument("--steps-per-rev", type=float, default=32000)
    parser.add_argument("--home-seconds", type=float, default=0.3)
    args = parser.parse_args()
    block = Registers(Platter(args.steps_per_rev, args.home_seconds))
    slave = ModbusSlaveContext(hr=block, zero_mode=True)
    context = ModbusServerContext(slaves={args.unit: slave}, single=False)
    asyncio.run(StartAsyncTcpServer(context=context, address=("127.0.0.1", args.port)))


if __name__ == "__main__":
    main()
