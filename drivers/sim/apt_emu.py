"""Emulated Thorlabs APT controller: a KDC101 K-cube (Z8 DC servo stages) or a K10CR1.

Byte-level firmware model with its own framing and packing (deliberately not the driver's
codec, so a shared misreading of the protocol cannot make both sides agree). It answers
what vendor software and third-party libraries send on connect (HW_REQ_INFO with a real
84-byte HW_GET_INFO, channel enable state, velocity/jog/home parameters, position counter,
status bits, status updates) and runs moves on a ``SimAxis`` whose clock is injected.

Behaviour modelled on the real units:
- The position counter reads 0 at power-up wherever the stage is; homing makes it 0 at
  the home switch. Moves are accepted before homing (the KDC101 and K10CR1 allow that;
  positions are then relative to power-up), but never while the channel is disabled:
  a disabled channel ignores motion commands silently.
- MOVE_HOME ends with a header-only MOVE_HOMED; MOVE_ABSOLUTE/RELATIVE end with
  MOVE_COMPLETED, or MOVE_STOPPED when a limit switch ended the move; MOVE_STOP answers
  MOVE_STOPPED. These carry a status block (DC layout on the KDC101, 0x0481 layout on the
  K10CR1) and may arrive between any request and its reply.
- After HW_START_UPDATEMSGS, a status update every 100 ms of controller time, which stop
  when the host has not acknowledged (MOT_ACK_DCSTATUSUPDATE) for 50 updates.
- A stalled servo reports the motion-error bit (excessive position error).
"""

from __future__ import annotations

import logging
import struct
from dataclasses import dataclass

from drivers.config import AxisConfig
from drivers.sim.clock import Clock
from drivers.sim.emulator import Emulator
from drivers.sim.kinematics import AxisPhysics, SimAxis

log = logging.getLogger(__name__)

_ME = 0x50  # USB stand-alone controller address
_ADDRESSES = {0x01, 0x11, 0x50, *range(0x21, 0x2B)}  # host, rack, USB unit, bays
_UPDATE_PERIOD_S = 0.1
_UPDATES_WITHOUT_ACK = 50

# status bits as the hardware sets them (0x01/0x10: reverse side, 0x02/0x20: forward side)
_LIM_REV, _LIM_FWD = 0x1, 0x2
_MOV_REV, _MOV_FWD = 0x10, 0x20
_CONNECTED, _HOMING, _HOMED = 0x100, 0x200, 0x400
_TRACKING, _SETTLED, _MOTION_ERR = 0x1000, 0x2000, 0x4000
_POWER_OK, _ACTIVE, _ENABLED = 0x10000000, 0x20000000, 0x80000000


@dataclass(frozen=True)
class _Stage:
    units: str
    counts_per_unit: float
    travel: tuple[float, float]
    max_speed: float
    max_accel: float
    home_speed: float
    stage_id: int  # what a KDC101 reports for it in HW_GET_INFO


# Independent of the driver's table on purpose (see the module docstring).
_STAGES = {
    "MTS25-Z8": _Stage("mm", 512 * 67.0, (0.0, 25.0), 2.4, 4.5, 1.0, 7),
    "MTS50-Z8": _Stage("mm", 512 * 67.0, (0.0, 50.0), 2.4, 4.5, 1.0, 8),
    "PRM1-Z8": _Stage("deg", 1919.6418578623391, (-1.0e4, 1.0e4), 25.0, 25.0, 10.0, 6),
    "K10CR1": _Stage("deg", 200 * 2048 * 120 / 360, (-1.0e4, 1.0e4), 10.0, 20.0, 10.0, 0),
}


def physics_for(axis: AxisConfig) -> AxisPhysics:
    """Mechanics of the stage an APT axis config names (MTS25-Z8 unless it says otherwise).

    Speed and acceleration are the stage's catalogue maxima (what the controller allows);
    the driver writes its own trapezoid with MOT_SET_VELPARAMS on connect.
    """
    name = (axis.stage or ("K10CR1" if axis.units == "deg" else "MTS25-Z8")).upper()
    stage = _STAGES.get(name.replace("/M", ""))
    if stage is None:
        raise ValueError(f"no APT emulation for stage {axis.stage!r} (axis {axis.role}); "
                         f"known: {', '.join(_STAGES)}")
    return AxisPhysics(travel_min=stage.travel[0], travel_max=stage.travel[1],
                       speed=stage.max_speed, accel=stage.max_accel,
                       counts_per_unit=stage.counts_per_unit, backlash=0.0,
                       repeatability=0.0, settle_s=0.05, home_position=stage.travel[0]
                       if stage.units == "mm" else 0.0, home_speed=stage.home_speed,
                       requires_homing=True)


def _stage_of(phys: AxisPhysics) -> str:
    """Which stage a simulated axis is (the rig builds emulators from physics alone)."""
    for name, st in _STAGES.items():
        if abs(st.counts_per_unit - phys.counts_per_unit) < 1e-6 and \
                abs((st.travel[1] - st.travel[0]) - (phys.travel_max - phys.travel_min)) < 1.0:
            return name
    for name, st in _STAGES.items():
        if abs(st.counts_per_unit - phys.counts_per_unit) < 1e-6:
            return name
    return "MTS25-Z8"


@dataclass
class _Channel:
    """Firmware state of one motor channel."""

    axis: SimAxis
    enabled: bool = True
    offset: int = 0  # encoder counts at position counter 0
    min_vel: int = 0
    accel: int = 0
    max_vel: int = 0
    home_dir: int = 2  # reverse
    home_limit: int = 1  # reverse hardware switch
    home_vel: int = 0
    home_offset: int = 0
    jog: bytes = b""  # jog parameters block after the channel word (20 bytes)
    rel_dist: int = 0
    abs_pos: int = 0
    pending: str | None = None  # "move" | "home" while a motion command runs
    forward: bool = True  # direction of the current/last motion
    stop_reply: bool = False  # MOVE_STOP received: answer MOVE_STOPPED once stopped


@dataclass
class _Updates:
    on: bool = False
    next_t: float = 0.0
    unacked: int = 0


@dataclass
class _Identity:
    model: str
    serial: int
    hw_type: int
    firmware: tuple[int, int, int]  # major, interim, minor
    notes: str
    stage_id: int
    hw_version: int = 1
    mod_state: int = 0


class AptEmulator(Emulator):
    """A KDC101 (default) or K10CR1 on one USB serial port; ``axes`` maps channel -> axis."""

    protocol = "apt"
    baudrate = 115200  # the real controller's line: 8N1 RTS/CTS

    def __init__(self, name: str, axes: dict[int, SimAxis], clock: Clock, *,
                 model: str | None = None, stage: str | None = None,
                 serial: int | None = None) -> None:
        super().__init__(name, axes, clock)
        if not axes:
            raise ValueError("an APT controller drives at least one channel")
        first = axes[min(axes)]
        self.stage = (stage or _stage_of(first.p)).upper()
        if self.stage not in _STAGES:
            raise ValueError(f"no APT emulation for stage {self.stage!r}")
        self.model = model or ("K10CR1" if self.stage == "K10CR1" else "KDC101")
        if self.model not in ("KDC101", "K10CR1"):
            raise ValueError(f"APT emulator models are KDC101 and K10CR1, not {self.model!r}")
        st = _STAGES[self.stage]
        if self.model == "KDC101":
            self.ident = _Identity("KDC101", serial or 27250101, 16, (3, 0, 10),
                                   "KDC101 DC Servo Drive", st.stage_id)
        else:
            self.ident = _Identity("K10CR1", serial or 55250101, 16, (3, 0, 6),
                                   "K10CR1 Rotation Mount", 0)
        self.ch: dict[int, _Channel] = {}
        for chan, ax in axes.items():
            c = _Channel(ax)
            # power-up: the counter reads 0 wherever the stage stands (unless no homing
            # is needed at all, then it is absolute)
            c.offset = 0 if ax.homed else ax.encoder_counts()
            c.max_vel = self._vel_reg(ax.p.speed, ax)
            c.accel = self._acc_reg(ax.p.accel, ax)
            c.home_vel = self._vel_reg(ax.p.home_speed or ax.p.speed, ax)
            c.jog = struct.pack("<HiiiiH", 2, round(0.1 * ax.p.counts_per_unit), 0,
                                c.accel, c.max_vel, 2)
            self.ch[chan] = c
        self.updates = _Updates()
        self.identify_count = 0
        self.no_flash = False
        self._buf = bytearray()
        self.unknown: list[int] = []  # ids of messages this firmware ignored

    # ---- units of the registers ------------------------------------------------------
    def _vel_reg(self, v: float, ax: SimAxis) -> int:
        c = v * ax.p.counts_per_unit
        return round(c * 2048 / 6e6 * 65536) if self.model == "KDC101" else round(c * 53.68)

    def _acc_reg(self, a: float, ax: SimAxis) -> int:
        c = a * ax.p.counts_per_unit
        if self.model == "KDC101":
            return round(c * (2048 / 6e6) ** 2 * 65536)
        return round(c * 53.68 * 204.94e-6)

    def _vel_units(self, reg: int, ax: SimAxis) -> float:
        per = 2048 / 6e6 * 65536 if self.model == "KDC101" else 53.68
        return reg / per / ax.p.counts_per_unit

    def _acc_units(self, reg: int, ax: SimAxis) -> float:
        per = (2048 / 6e6) ** 2 * 65536 if self.model == "KDC101" else 53.68 * 204.94e-6
        return reg / per / ax.p.counts_per_unit

    # ---- framing -----------------------------------------------------------------------
    def handle(self, data: bytes) -> bytes:
        """Parse whatever complete messages ``data`` completes; replies in stream order."""
        out = bytearray(self.poll())  # completions due before these commands were read
        self._buf += data
        while len(self._buf) >= 6:
            mid = self._buf[0] | self._buf[1] << 8
            dest, src = self._buf[4], self._buf[5]
            long_form = bool(dest & 0x80)
            length = (self._buf[2] | self._buf[3] << 8) if long_form else 0
            if (dest & 0x7F) not in _ADDRESSES or src not in _ADDRESSES or length > 255:
                # not a header: the firmware slides one byte and tries again
                del self._buf[0]
                continue
            if len(self._buf) < 6 + length:
                break
            p1, p2 = self._buf[2], self._buf[3]
            payload = bytes(self._buf[6:6 + length]) if long_form else None
            del self._buf[:6 + length]
            self.note_command(f"0x{mid:04X}")
            if (dest & 0x7F) != _ME:
                continue  # for another unit on the bus
            out += self._dispatch(mid, p1, p2, payload, src)
        return bytes(out)

    def _short(self, mid: int, p1: int, p2: int, to: int) -> bytes:
        return bytes((mid & 0xFF, mid >> 8, p1, p2, to, _ME))

    def _long(self, mid: int, payload: bytes, to: int) -> bytes:
        n = len(payload)
        return bytes((mid & 0xFF, mid >> 8, n & 0xFF, n >> 8, to | 0x80, _ME)) + payload

    # ---- state -------------------------------------------------------------------------
    def _chan(self, raw: int) -> _Channel | None:
        return self.ch.get(raw)

    def _counter(self, c: _Channel) -> int:
        return c.axis.encoder_counts() - c.offset

    def _bits(self, c: _Channel) -> int:
        ax = c.axis
        ax.motor_position()  # advances homing -> homed and arrival limit flags
        moving = ax.moving
        bits = _CONNECTED | _POWER_OK
        if c.enabled:
            bits |= _ENABLED
        if ax.homed:
            bits |= _HOMED
        if ax.homing:
            bits |= _HOMING
        if moving:
            bits |= _ACTIVE
            bits |= _MOV_FWD if c.forward else _MOV_REV
        elif c.enabled:
            bits |= _TRACKING
            if ax.settled:
                bits |= _SETTLED
        if ax.limit_low:
            bits |= _LIM_REV
        if ax.limit_high:
            bits |= _LIM_FWD
        if ax.stalled:
            bits |= _MOTION_ERR
        return bits

    def _status_block(self, chan: int, c: _Channel) -> bytes:
        """Status carried by 0x0491/0x0481 and by MOVE_COMPLETED/MOVE_STOPPED."""
        bits = self._bits(c)  # before the position: a block never says "stopped" over a
        pos = self._counter(c)  # position read before the stop (a later read is harmless)
        if self.model == "KDC101":
            vel = round(self._vel_units(c.max_vel, c.axis) * c.axis.p.counts_per_unit
                        * 2048 / 6e6) if c.axis.moving else 0
            return struct.pack("<HiHHI", chan, pos, min(vel, 0xFFFF), 0, bits)
        return struct.pack("<HiiI", chan, pos, 0, bits)  # open-loop stepper: no encoder

    def _status_msg_id(self) -> int:
        return 0x0491 if self.model == "KDC101" else 0x0481

    def _start(self, c: _Channel, counts: int) -> None:
        ax = c.axis
        if not ax.moving:  # a new trapezoid takes the current acceleration register
            ax.p.accel = self._acc_units(c.accel, ax)
        target = (counts + c.offset) / ax.p.counts_per_unit
        self.log_target(ax, counts / ax.p.counts_per_unit)
        c.forward = target >= ax.motor_position()
        ax.move_to(target, speed=self._vel_units(c.max_vel, ax))
        c.pending = "move"
        c.stop_reply = False

    # ---- commands ----------------------------------------------------------------------
    def _dispatch(self, mid: int, p1: int, p2: int, data: bytes | None, host: int) -> bytes:
        to = host
        if mid == 0x0005:  # HW_REQ_INFO
            i = self.ident
            major, interim, minor = i.firmware
            info = struct.pack("<I8sH4B48s10sHHHH", i.serial, i.model.encode(), i.hw_type,
                               minor, interim, major, 0, i.notes.encode(), b"", i.stage_id,
                               i.hw_version, i.mod_state, len(self.ch))
            return self._long(0x0006, info, to)
        if mid == 0x0223:  # MOD_IDENTIFY: blink
            self.identify_count += 1
            return b""
        if mid == 0x0018:  # HW_NO_FLASH_PROGRAMMING
            self.no_flash = True
            return b""
        if mid == 0x0011:  # HW_START_UPDATEMSGS
            self.updates = _Updates(True, self.clock.now(), 0)
            return b""
        if mid in (0x0012, 0x0002):  # HW_STOP_UPDATEMSGS, HW_DISCONNECT
            self.updates.on = False
            return b""
        if mid == 0x0492:  # MOT_ACK_DCSTATUSUPDATE
            self.updates.unacked = 0
            return b""
        if mid in (0x0210, 0x0211):  # MOD_SET/REQ_CHANENABLESTATE (channel as bit mask)
            chan = {1: 1, 2: 2, 4: 3, 8: 4}.get(p1, 0)
            c = self._chan(chan)
            if c is None:
                return b""
            if mid == 0x0210:
                if p2 in (1, 2):
                    c.enabled = p2 == 1
                    if not c.enabled and c.axis.moving:
                        c.axis.stop()  # motor unpowered: it coasts to a stop
                        c.pending = None
                return b""
            return self._short(0x0212, p1, 1 if c.enabled else 2, to)
        if data is not None:
            return self._dispatch_long(mid, data, to)
        return self._dispatch_short(mid, p1, p2, to)

    def _dispatch_short(self, mid: int, p1: int, p2: int, to: int) -> bytes:
        c = self._chan(p1)
        if c is None:
            self.unknown.append(mid)
            return b""
        ax = c.axis
        if mid == 0x0411:  # REQ_POSCOUNTER
            return self._long(0x0412, struct.pack("<Hi", p1, self._counter(c)), to)
        if mid == 0x040A:  # REQ_ENCCOUNTER
            return self._long(0x040B, struct.pack("<Hi", p1, self._counter(c)), to)
        if mid == 0x0414:  # REQ_VELPARAMS
            return self._long(0x0415, struct.pack("<Hiii", p1, c.min_vel, c.accel, c.max_vel),
                              to)
        if mid == 0x0417:  # REQ_JOGPARAMS
            return self._long(0x0418, struct.pack("<H", p1) + c.jog, to)
        if mid == 0x0441:  # REQ_HOMEPARAMS
            return self._long(0x0442, struct.pack("<HHHii", p1, c.home_dir, c.home_limit,
                                                  c.home_vel, c.home_offset), to)
        if mid == 0x0446:  # REQ_MOVERELPARAMS
            return self._long(0x0447, struct.pack("<Hi", p1, c.rel_dist), to)
        if mid == 0x0451:  # REQ_MOVEABSPARAMS
            return self._long(0x0452, struct.pack("<Hi", p1, c.abs_pos), to)
        if mid == 0x0429:  # REQ_STATUSBITS
            return self._long(0x042A, struct.pack("<HI", p1, self._bits(c)), to)
        if mid == self._status_msg_id() - 1:  # REQ_DCSTATUSUPDATE / REQ_STATUSUPDATE
            return self._long(self._status_msg_id(), self._status_block(p1, c), to)
        if mid == 0x0443:  # MOVE_HOME
            if c.enabled:
                c.forward = ax.p.home_position >= ax.motor_position()
                ax.home()
                c.offset = 0  # the counter is zeroed at the home position
                c.pending = "home"
                c.stop_reply = False
            return b""
        if mid == 0x0448:  # MOVE_RELATIVE with the stored distance
            if c.enabled:
                self._start(c, self._counter(c) + c.rel_dist)
            return b""
        if mid == 0x0453:  # MOVE_ABSOLUTE to the stored position
            if c.enabled:
                self._start(c, c.abs_pos)
            return b""
        if mid == 0x0457:  # MOVE_VELOCITY: run towards a travel end
            if c.enabled:
                end = ax.p.travel_max + 1.0 if p2 == 1 else ax.p.travel_min - 1.0
                self._start(c, round(end * ax.p.counts_per_unit) - c.offset)
            return b""
        if mid == 0x0465:  # MOVE_STOP (immediate or profiled: both end at once here)
            self.log_stop(ax)
            ax.stop()
            c.pending = None
            c.stop_reply = True
            return b""
        self.unknown.append(mid)
        log.debug("%s: ignoring message 0x%04X", self.name, mid)
        return b""

    def _dispatch_long(self, mid: int, data: bytes, to: int) -> bytes:
        if len(data) < 2:
            return b""
        chan = data[0] | data[1] << 8
        c = self._chan(chan)
        if c is None:
            self.unknown.append(mid)
            return b""
        if mid in (0x0448, 0x0453, 0x0410, 0x0409, 0x0445, 0x0450) and len(data) == 6:
            (value,) = struct.unpack_from("<i", data, 2)
            if mid == 0x0453 and c.enabled:  # MOVE_ABSOLUTE
                self._start(c, value)
            elif mid == 0x0448 and c.enabled:  # MOVE_RELATIVE
                self._start(c, self._counter(c) + value)
            elif mid in (0x0410, 0x0409):  # SET_POSCOUNTER / SET_ENCCOUNTER
                c.offset = c.axis.encoder_counts() - value
            elif mid == 0x0445:
                c.rel_dist = value
            elif mid == 0x0450:
                c.abs_pos = value
            return b""
        if mid == 0x0413 and len(data) == 14:  # SET_VELPARAMS
            _, c.min_vel, c.accel, c.max_vel = struct.unpack("<Hiii", data)
            return b""
        if mid == 0x0416 and len(data) == 22:  # SET_JOGPARAMS
            c.jog = data[2:]
            return b""
        if mid == 0x0440 and len(data) == 14:  # SET_HOMEPARAMS
            _, c.home_dir, c.home_limit, c.home_vel, c.home_offset = \
                struct.unpack("<HHHii", data)
            c.axis.p.home_speed = self._vel_units(c.home_vel, c.axis)
            return b""
        self.unknown.append(mid)
        log.debug("%s: ignoring data message 0x%04X (%d bytes)", self.name, mid, len(data))
        return b""

    # ---- unsolicited ---------------------------------------------------------------------
    def poll(self) -> bytes:
        """Completion messages and periodic status updates due now."""
        out = bytearray()
        host = 0x01
        for chan, c in self.ch.items():
            ax = c.axis
            ax.motor_position()  # advances homing -> homed and arrival limit flags
            if c.stop_reply and not ax.moving:
                c.stop_reply = False
                out += self._long(0x0466, self._status_block(chan, c), host)
            if c.pending is None or ax.moving:
                continue
            what, c.pending = c.pending, None
            if what == "home":
                if ax.homed:
                    out += self._short(0x0444, chan, 0, host)
            elif ax.limit_low or ax.limit_high:
                out += self._long(0x0466, self._status_block(chan, c), host)
            else:
                out += self._long(0x0464, self._status_block(chan, c), host)
        up = self.updates
        now = self.clock.now()
        if up.on and now >= up.next_t:
            up.next_t = now + _UPDATE_PERIOD_S  # no backlog if nobody polled for a while
            up.unacked += 1
            if up.unacked > _UPDATES_WITHOUT_ACK:
                up.on = False
                log.info("%s: status updates stopped: host did not acknowledge", self.name)
            else:
                for chan, c in self.ch.items():
                    out += self._long(self._status_msg_id(), self._status_block(chan, c),
                                      host)
        return bytes(out)
