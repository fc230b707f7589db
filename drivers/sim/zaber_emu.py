"""Emulated daisy chain of Zaber X-LSM stages speaking the Zaber ASCII protocol.

A byte-level state machine with its own parser (it shares no code with
``drivers.zaber_ascii``): commands ``/[device] [axis] [id] command [args][:CK]`` terminated by
CR and/or LF; every device whose address matches (0 = all) answers ``@NN A [ID] OK|RJ
IDLE|BUSY WW data``, with a checksum when its ``comm.checksum`` is 1, and alerts ``!NN A
IDLE WW`` when its ``comm.alert`` is 1 and a motion ends.

Behaviour follows Zaber's ASCII Protocol Manual (firmware 6/7): positions in microsteps,
``maxspeed`` in microsteps/s x 1.6384, ``accel`` in microsteps/s^2 x 1.6384 / 10000 (at most
32767; data outside a setting's range is rejected with ``BADDATA``); at
power-up the position reads 0 and the axis carries ``WR`` (no reference position) until it
is homed (``set pos`` gives a reference but not a home: ``WH``); absolute moves without a
reference are rejected (``RJ ... BADDATA``; the manual warns that motion commands "may respond
with a rejection reply" before homing, and the emulator takes the strict reading); moves
outside ``limit.min``..``limit.max`` are rejected with ``BADDATA``; a stall stops the axis
and latches ``FS``, an unexpected limit switch latches ``WL``, both until ``warnings
clear``; a move that interrupts another sets ``NI``. A command whose checksum fails is
rejected with ``BADDATA`` by every device on the chain (the manual's checksum section).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field

from drivers.config import AxisConfig
from drivers.sim.clock import Clock
from drivers.sim.emulator import Emulator
from drivers.sim.kinematics import AxisPhysics, SimAxis

log = logging.getLogger(__name__)

# X-LSM: 0.6096 mm lead screw, 200 full steps/turn, 64 microsteps/step -> 0.047625 um.
XLSM_MICROSTEP_MM = 0.6096 / 200 / 64
# "Set Acceleration" (A-/X-series, firmware 6+): actual acceleration =
# 10000 x data / 1.6384 microsteps/s^2, the maximum data value is 32767.
SPEED_FACTOR = 1.6384  # maxspeed data per microstep/s
ACCEL_FACTOR = 1.6384e-4  # accel data per microstep/s^2
ACCEL_MAX = 32767

# Travel (mm) of the X-LSM sizes: inch-based lead screws, e.g. X-LSM050A = 2 in.
XLSM_TRAVEL_MM = {"X-LSM025A": 25.4, "X-LSM050A": 50.8, "X-LSM100A": 101.6,
                  "X-LSM150A": 152.4, "X-LSM200A": 203.2}
# Device ids reported by `get deviceid` (not verified against Zaber's device database).
XLSM_DEVICE_IDS = {"X-LSM025A": 50079, "X-LSM050A": 50081, "X-LSM100A": 50082,
                   "X-LSM150A": 50083, "X-LSM200A": 50084}
FIRMWARE_VERSION = "7.38"
FIRMWARE_BUILD = 17425
PACKET_SIZE_MAX = 80

# Highest priority first (FW7 ordering: faults, warnings, notices).
FLAG_PRIORITY = ("FD", "FQ", "FS", "FT", "FE", "WL", "WV", "WT", "WM", "WH", "WR", "NC", "NI",
                 "NU")
CLEARABLE = frozenset({"FS", "FE", "WL", "NI"})

_NUMBER = re.compile(r"[+-]?(?:\d+|0[xX][0-9a-fA-F]+)")


def physics_for(axis: AxisConfig, *, backlash: float = 0.0,
                repeatability: float = 0.0) -> AxisPhysics:
    """Mechanics of the X-LSM stage named by ``axis.stage``, moving at the config's speed."""
    stage = axis.stage.upper()
    for model in XLSM_TRAVEL_MM:
        if stage.startswith(model):
            break
    else:
        raise ValueError(f"unknown Zaber stage {axis.stage!r} for axis {axis.role!r} "
                         f"(known: {', '.join(XLSM_TRAVEL_MM)})")
    travel = XLSM_TRAVEL_MM[model]
    return AxisPhysics(travel_min=0.0, travel_max=travel, speed=axis.speed, accel=axis.accel,
                       counts_per_unit=1.0 / XLSM_MICROSTEP_MM, backlash=backlash,
                       repeatability=repeatability, settle_s=0.02, home_position=0.0,
                       home_speed=axis.speed, requires_homing=True)


def _int(token: str) -> int:
    """A decimal (leading zeros allowed, e.g. message id ``07``) or ``0x`` hex number."""
    sign = -1 if token.startswith("-") else 1
    digits = token.lstrip("+-")
    return sign * (int(digits, 16) if digits[:2].lower() == "0x" else int(digits, 10))


def _checksum(body: str) -> int:
    """LRC: the byte that makes the 8-bit sum of body + checksum zero."""
    return -sum(body.encode("ascii")) & 0xFF


def _model_for_travel(travel: float) -> str:
    best = min(XLSM_TRAVEL_MM, key=lambda m: abs(XLSM_TRAVEL_MM[m] - travel))
    return best


@dataclass
class _Device:
    """One X-LSM device on the chain (integrated controller, one axis)."""

    number: int
    axis: SimAxis
    model: str
    serial: int
    steps_per_mm_base: float
    resolution: int = 64
    maxspeed: float = 0.0  # mm/s
    accel: float = 0.0  # mm/s^2
    limit_min: float = 0.0  # mm, device coordinates
    limit_max: float = 0.0
    offset: float = 0.0  # physical mm at device position 0
    reference: str = "none"  # none -> WR, set -> WH, homed
    homing: bool = False
    latched: set[str] = field(default_factory=set)
    comm_checksum: int = 0
    comm_alert: int = 0
    was_busy: bool = False
    busy: bool = False  # what the reply to the command being handled says (BUSY/IDLE)
    limit_seen: tuple[bool, bool] = (False, False)

    @property
    def steps_per_mm(self) -> float:
        return self.steps_per_mm_base * self.resolution / 64.0


class ZaberEmulator(Emulator):
    """A chain of X-LSM devices; ``axes`` maps device number -> the stage it drives."""

    protocol = "zaber"
    baudrate = 115200  # the real controller's line: 8N1

    def __init__(self, name: str, axes: dict[int, SimAxis], clock: Clock, *,
                 models: dict[int, str] | None = None, serial_base: int = 91301) -> None:
        super().__init__(name, axes, clock)
        for number in axes:
            if not 1 <= number <= 99:
                raise ValueError(f"Zaber device number {number} outside 1..99")
        self._buf = b""
        self._alerts = b""  # alerts due, sent by poll()
        self.devices: dict[int, _Device] = {}
        for number in sorted(axes):
            ax = axes[number]
            model = (models or {}).get(number) or _model_for_travel(ax.p.travel_max)
            dev = _Device(number=number, axis=ax, model=model, serial=serial_base + number,
                          steps_per_mm_base=ax.p.counts_per_unit, maxspeed=ax.p.speed,
                          accel=ax.p.accel, limit_min=0.0,
                          limit_max=ax.p.travel_max - ax.p.travel_min)
            # Power-up: wherever the carriage is, the position reads 0 (no reference).
            dev.offset = ax.motor_position()
            dev.was_busy = ax.moving
            self.devices[number] = dev

    # ---- device state -----------------------------------------------------------
    def _pos_steps(self, dev: _Device) -> int:
        return round((dev.axis.motor_position() - dev.offset) * dev.steps_per_mm)

    def _update(self, dev: _Device) -> bool:
        """Advance the device's view of its axis; return whether it is busy."""
        ax = dev.axis
        moving = ax.moving
        if ax.stalled:  # the stepper lost sync: the firmware stops the axis and latches FS
            log.info("%s: device %d stalled", self.name, dev.number)
            ax.stop()
            dev.latched.add("FS")
            dev.homing = False
            moving = False
        limits = (ax.limit_low, ax.limit_high)
        if any(limits) and limits != dev.limit_seen:
            dev.latched.add("WL")
        dev.limit_seen = limits
        if dev.homing and not moving:  # reached the home sensor: position := 0
            dev.homing = False
            dev.offset = ax.motor_position()
            dev.reference = "homed"
        busy = moving or dev.homing
        if dev.was_busy and not busy and dev.comm_alert:  # motion complete: alert
            self._alerts += self._line(dev, "!", f"{dev.number:02d} 1 IDLE {self._warn(dev)}")
        dev.was_busy = dev.busy = busy
        return busy

    def _flags(self, dev: _Device) -> list[str]:
        flags = set(dev.latched)
        if dev.reference == "none":
            flags.add("WR")
        elif dev.reference == "set":
            flags.add("WH")
        return [f for f in FLAG_PRIORITY if f in flags]

    def _warn(self, dev: _Device) -> str:
        flags = self._flags(dev)
        return flags[0] if flags else "--"

    # ---- wire -------------------------------------------------------------------
    def _line(self, dev: _Device, kind: str, body: str) -> bytes:
        text = kind + body
        if dev.comm_checksum:
            text += f":{_checksum(body):02X}"
        return (text + "\r\n").encode("ascii")

    def _reply(self, dev: _Device, axis: int, mid: int | None, ok: bool, data: str) -> bytes:
        """The reply's status and flags describe the instant of the command's ``_update``
        (plus what the command itself started or stopped), as its data does: reading the
        clock again here let a homing end between the data (``WR``) and the status
        (``IDLE``), a reply no real device sends."""
        busy = dev.busy
        head = f"{dev.number:02d} {axis}" + (f" {mid:02d}" if mid is not None else "")
        body = f"{head} {'OK' if ok else 'RJ'} {'BUSY' if busy else 'IDLE'} {self._warn(dev)} "
        return self._line(dev, "@", body + data)

    def handle(self, data: bytes) -> bytes:
        self._buf += data
        out = b""
        while True:
            cut = [i for i in (self._buf.find(b"\r"), self._buf.find(b"\n")) if i >= 0]
            if not cut:
                break
            i = min(cut)
            line, self._buf = self._buf[:i], self._buf[i + 1:]
            start = line.find(b"/")
            if start < 0:
                continue  # a bare footer, or noise without a message type
            out += self._command(line[start + 1:])
        if len(self._buf) > 1024:  # no footer in sight: drop, as the firmware's buffer would
            self._buf = b""
        return out

    def poll(self) -> bytes:
        for dev in self.devices.values():
            self._update(dev)
        out, self._alerts = self._alerts, b""
        return out

    def corrupt_checksum(self, reply: bytes) -> bytes:
        """Spoil the first checksum in ``reply`` (or a byte, if the devices send none)."""
        m = re.search(rb":([0-9A-F]{2})\r\n", reply)
        if m is None:
            return super().corrupt_checksum(reply)
        wrong = b"%02X" % ((int(m[1], 16) + 0x11) & 0xFF)
        return reply[:m.start(1)] + wrong + reply[m.end(1):]

    # ---- parsing ----------------------------------------------------------------
    def _command(self, raw: bytes) -> bytes:
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            self.note_command("?")
            return b""  # unsupported characters: the firmware discards the message
        checksum_ok = True
        if len(text) >= 3 and text[-3] == ":":
            try:
                checksum_ok = (sum(text[:-3].encode("ascii")) + int(text[-2:], 16)) & 0xFF == 0
            except ValueError:
                checksum_ok = False
            text = text[:-3]
        tokens = text.split()
        header: list[int] = []
        while tokens and len(header) < 3 and _NUMBER.fullmatch(tokens[0]):
            header.append(_int(tokens.pop(0)))
        address = header[0] if header else 0
        axis = header[1] if len(header) > 1 else 0
        mid = header[2] if len(header) > 2 else None
        self.note_command(" ".join(tokens).lower())
        for dev in self.devices.values():
            self._update(dev)  # one instant per message: data and status agree
        if not checksum_ok:  # every device rejects it, whatever the address
            return b"".join(self._reply(d, axis, mid if mid is not None and 0 <= mid <= 99
                                        else None, False, "BADDATA")
                            for d in self.devices.values())
        if address == 0:
            targets = list(self.devices.values())
        elif address in self.devices:
            targets = [self.devices[address]]
        else:
            return b""  # nobody with that address on the chain
        if mid is not None and not 0 <= mid <= 99:
            return b"".join(self._reply(d, axis, None, False, "BADMESSAGEID") for d in targets)
        out = b""
        for dev in targets:
            if not 0 <= axis <= 1:
                out += self._reply(dev, axis, mid, False, "BADAXIS")
                continue
            ok, data = self._execute(dev, axis, tokens)
            out += self._reply(dev, axis, mid, ok, data)
        return out

    # ---- commands -----------------------------------------------------------------
    def _execute(self, dev: _Device, axis: int, words: list[str]) -> tuple[bool, str]:
        if not words:
            return True, "0"
        cmd, args = words[0], words[1:]
        if cmd == "get" and len(args) == 1:
            return self._get(dev, axis, args[0])
        if cmd == "set" and len(args) == 2:
            return self._set(dev, axis, args[0], args[1])
        if cmd in ("get", "set"):
            return False, "BADDATA" if args else "BADCOMMAND"
        if cmd == "home" and not args:
            self._start_motion(dev)
            dev.axis.home()
            dev.homing = True
            return True, "0"
        if cmd == "move" and args:
            return self._move(dev, args)
        if cmd in ("stop", "estop") and not args:
            self.log_stop(dev.axis)
            if dev.axis.moving or dev.homing:
                dev.latched.add("NI")
            dev.axis.stop()
            dev.homing = dev.busy = False
            return True, "0"
        if cmd == "warnings" and args in ([], ["clear"]):
            flags = self._flags(dev)
            if args:
                dev.latched -= CLEARABLE
            return True, " ".join([f"{len(flags):02d}", *flags])
        return False, "BADCOMMAND"

    def _start_motion(self, dev: _Device) -> None:
        """A movement command: NI if it interrupts one, cleared if the axis was idle."""
        if dev.axis.moving or dev.homing:
            dev.latched.add("NI")
        else:
            dev.latched.discard("NI")
        dev.was_busy = True  # even a motion that ends at once is followed by an alert
        dev.busy = True

    def _move(self, dev: _Device, args: list[str]) -> tuple[bool, str]:
        kind, rest = args[0], args[1:]
        if kind in ("min", "max") and not rest:
            target = dev.limit_min if kind == "min" else dev.limit_max
            absolute = True
        elif kind in ("abs", "rel") and len(rest) == 1:
            if not _NUMBER.fullmatch(rest[0]):
                return False, "BADDATA"
            steps = _int(rest[0])
            if kind == "rel":
                steps += self._pos_steps(dev)
            target = steps / dev.steps_per_mm
            absolute = kind == "abs"
        else:
            return False, "BADCOMMAND"
        lo, hi = dev.limit_min, dev.limit_max
        eps = 0.5 / dev.steps_per_mm
        ok = not (absolute and dev.reference == "none") and lo - eps <= target <= hi + eps
        self.log_target(dev.axis, target, accepted=ok, command=f"move {kind}")
        if not ok:
            return False, "BADDATA"
        self._start_motion(dev)
        dev.homing = False
        dev.axis.move_to(target + dev.offset, speed=dev.maxspeed)
        return True, "0"

    def _device_settings(self, dev: _Device) -> dict[str, str]:
        return {
            "deviceid": str(XLSM_DEVICE_IDS.get(dev.model, 50081)),
            "system.serial": str(dev.serial),
            "version": FIRMWARE_VERSION,
            "version.build": str(FIRMWARE_BUILD),
            "system.axiscount": "1",
            "comm.packet.size.max": str(PACKET_SIZE_MAX),
            "comm.checksum": str(dev.comm_checksum),
            "comm.alert": str(dev.comm_alert),
            "comm.address": str(dev.number),
        }

    def _axis_settings(self, dev: _Device) -> dict[str, str]:
        spm = dev.steps_per_mm
        return {
            "pos": str(self._pos_steps(dev)),
            "limit.min": str(round(dev.limit_min * spm)),
            "limit.max": str(round(dev.limit_max * spm)),
            "maxspeed": str(round(dev.maxspeed * spm * SPEED_FACTOR)),
            "accel": str(round(dev.accel * spm * ACCEL_FACTOR)),
            "resolution": str(dev.resolution),
            "peripheralid": "0",  # integrated stage: no peripheral
            "peripheral.id": "0",
        }

    def _get(self, dev: _Device, axis: int, setting: str) -> tuple[bool, str]:
        device_settings = self._device_settings(dev)
        if setting in device_settings:
            return (True, device_settings[setting]) if axis == 0 else (False, "DEVICEONLY")
        axis_settings = self._axis_settings(dev)
        if setting in axis_settings:
            return True, axis_settings[setting]  # axis 0: one value per axis (one axis)
        return False, "BADCOMMAND"

    def _set(self, dev: _Device, axis: int, setting: str, value: str) -> tuple[bool, str]:
        writable_device = {"comm.checksum", "comm.alert"}
        writable_axis = {"pos", "limit.min", "limit.max", "maxspeed", "accel", "resolution"}
        if setting in writable_device:
            if axis != 0:
                return False, "DEVICEONLY"
        elif setting not in writable_axis:
            known = setting in self._device_settings(dev) or setting in self._axis_settings(dev)
            return False, "BADDATA" if known else "BADCOMMAND"  # read-only vs unknown
        if not _NUMBER.fullmatch(value):
            return False, "BADDATA"
        n = _int(value)
        spm = dev.steps_per_mm
        travel = dev.axis.p.travel_max - dev.axis.p.travel_min
        if setting in ("comm.checksum", "comm.alert"):
            if n not in (0, 1):
                return False, "BADDATA"
            setattr(dev, setting.replace(".", "_"), n)
        elif setting == "pos":
            if dev.axis.moving or dev.homing:
                return False, "BADDATA"
            dev.offset = dev.axis.motor_position() - n / spm
            if dev.reference != "homed":
                dev.reference = "set"
        elif setting == "limit.min":
            if not -travel <= n / spm <= dev.limit_max:
                return False, "BADDATA"
            dev.limit_min = n / spm
        elif setting == "limit.max":
            if not dev.limit_min <= n / spm <= 2 * travel:
                return False, "BADDATA"
            dev.limit_max = n / spm
        elif setting == "maxspeed":
            if n <= 0:
                return False, "BADDATA"
            dev.maxspeed = n / SPEED_FACTOR / spm
        elif setting == "accel":
            if not 1 <= n <= ACCEL_MAX:
                return False, "BADDATA"
            dev.accel = n / ACCEL_FACTOR / spm
            dev.axis.p.accel = dev.accel
        elif setting == "resolution":
            if n not in (1, 2, 4, 8, 16, 32, 64, 128) or dev.axis.moving:
                return False, "BADDATA"
            dev.resolution = n
        return True, "0"
