"""Emulated Newport SMC100CC controllers (one or more on an RS-485 chain) with rotation stages.

Byte-faithful to the published ASCII protocol: ``[address][two letters][value | ?]`` ended
by CR LF, case-insensitive; set commands are silent; a command that cannot run stores an
error letter that ``TE`` returns (and clears); replies echo address and command
(``1TP`` -> ``1TP12.345``). Each address runs the controller state machine of the manual:
NOT REFERENCED (0A from reset, 0B from HOMING, 0D from DISABLE ...), HOMING (1E),
MOVING (28), READY (32 from HOMING, 33 from MOVING, 34 from DISABLE) and DISABLE
(3C from READY, 3D from MOVING). The mechanics are a ``SimAxis`` (trapezoidal profile,
encoder quantisation, backlash, limits, stall) on the injected clock.

This parser is deliberately independent of ``drivers.newport_smc100``: a bug shared by
driver and emulator would make both agree and hide it.

Choices where the manual leaves room (documented so tests and readers know):
- a PA/PR target outside SL..SR stores ``G`` (displacement out of limits) and does not move;
- a following error (the simulated stall) latches bit 0x0020 and drops the controller to
  DISABLE from MOVING (3D), as the real servo loop does; ``MM1``, ``OR`` or ``RS`` clear it;
- a tripped end-of-run switch stops the motion, reports bit 0x0001 / 0x0002 while the
  switch is pressed and leaves the controller in READY from MOVING (33);
- query-only commands (TS, TE, TP, TH, VE) also accept a trailing ``?``, as the hardware
  does and as several third-party drivers send them.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass

from drivers.config import AxisConfig
from drivers.sim.clock import Clock
from drivers.sim.emulator import Emulator
from drivers.sim.kinematics import AxisPhysics, SimAxis

log = logging.getLogger(__name__)

# ---- controller states (hex codes of the SMC100 manual) ------------------------------
NOT_REF_RESET = 0x0A
NOT_REF_HOMING = 0x0B
NOT_REF_CONFIGURATION = 0x0C
NOT_REF_DISABLE = 0x0D
NOT_REF_READY = 0x0E
NOT_REF_MOVING = 0x0F
NOT_REF_ESP_ERROR = 0x10
NOT_REF_JOGGING = 0x11
CONFIGURATION = 0x14
HOMING_RS232 = 0x1E
HOMING_KEYPAD = 0x1F
MOVING = 0x28
READY_HOMING = 0x32
READY_MOVING = 0x33
READY_DISABLE = 0x34
READY_JOGGING = 0x35
DISABLE_READY = 0x3C
DISABLE_MOVING = 0x3D
DISABLE_JOGGING = 0x3E
JOGGING_READY = 0x46
JOGGING_DISABLE = 0x47

NOT_REFERENCED_STATES = frozenset(range(0x0A, 0x12))
READY_STATES = frozenset({READY_HOMING, READY_MOVING, READY_DISABLE, READY_JOGGING})
DISABLE_STATES = frozenset({DISABLE_READY, DISABLE_MOVING, DISABLE_JOGGING})
HOMING_STATES = frozenset({HOMING_RS232, HOMING_KEYPAD})
JOGGING_STATES = frozenset({JOGGING_READY, JOGGING_DISABLE})

# ---- positioner error bits (TS, first four hex digits) -------------------------------
ERR_NEG_END_OF_RUN = 0x0001
ERR_POS_END_OF_RUN = 0x0002
ERR_FOLLOWING = 0x0020
ERR_HOMING_TIMEOUT = 0x0040

# ---- TE error letters, and the TB texts the controller answers with --------------------
ERROR_TEXT = {
    "@": "No error",
    "A": "Unknown message code or floating point controller address",
    "B": "Controller address not correct",
    "C": "Parameter missing or out of range",
    "D": "Execution not allowed",
    "E": "Home sequence already started",
    "F": "ESP stage name unknown",
    "G": "Displacement out of limits",
    "H": "Execution not allowed in NOT REFERENCED state",
    "I": "Execution not allowed in CONFIGURATION state",
    "J": "Execution not allowed in DISABLE state",
    "K": "Execution not allowed in READY state",
    "L": "Execution not allowed in HOMING state",
    "M": "Execution not allowed in MOVING state",
    "N": "Current position out of software limit",
    "S": "Communication Time Out",
    "U": "Error during EEPROM access",
    "V": "Error during command execution",
    "W": "Command not allowed for PP version",
    "X": "Command not allowed for CC version",
}

# the firmware string a real SMC100CC answers to VE (from a unit's transcript)
FIRMWARE = "SMC_CC - Controller-driver version  3. 1. 2"

# ---- stages -------------------------------------------------------------------------
# Catalogue-based figures of Newport rotation stages driven by the SMC100CC. Travel is
# limited to +-170 deg here by the cable wrap of the rig (the stages themselves turn 360).
# Encoder: 0.0005 deg per count (DC servo, rotary encoder), max speed 20 deg/s.
_STAGES: dict[str, dict[str, float]] = {
    "URS75BCC": {"speed": 20.0, "accel": 80.0, "counts": 2000.0, "repeat": 0.0001},
    "URS100BCC": {"speed": 20.0, "accel": 80.0, "counts": 2000.0, "repeat": 0.0001},
    "URS150BCC": {"speed": 20.0, "accel": 80.0, "counts": 2000.0, "repeat": 0.0001},
}
_TRAVEL_DEG = 170.0


def physics_for(axis: AxisConfig) -> AxisPhysics:
    """Mechanics of the stage an SMC100 axis drives (rotation stages; linear as fallback).

    Backlash and repeatability are the world's business (``drivers.sim.rig`` replaces
    them from ``SimWorldConfig``); the values here are typical of a worm-gear stage.
    """
    spec = _STAGES.get(axis.stage.upper())
    if axis.units == "deg" or spec is not None:
        spec = spec or _STAGES["URS75BCC"]
        return AxisPhysics(
            travel_min=-_TRAVEL_DEG, travel_max=_TRAVEL_DEG,
            speed=spec["speed"], accel=spec["accel"], counts_per_unit=spec["counts"],
            backlash=0.002, repeatability=spec["repeat"], settle_s=0.05,
            home_position=0.0, home_speed=spec["speed"] / 2, requires_homing=True)
    # a linear stage on an SMC100CC (e.g. an ILS-CC): travel around the soft limits,
    # 0.5 um encoder counts, the configured speed as the stage maximum
    lo, hi = axis.soft_limits.min, axis.soft_limits.max
    margin = 0.05 * (hi - lo)
    return AxisPhysics(
        travel_min=lo - margin, travel_max=hi + margin, speed=max(axis.speed, 1.0),
        accel=max(axis.accel, 4.0), counts_per_unit=2000.0, backlash=0.001,
        repeatability=0.0002, settle_s=0.05, home_position=lo - margin,
        home_speed=max(axis.speed, 1.0) / 2, requires_homing=True)


def _fmt(x: float) -> str:
    """A number the way the controller prints it: fixed point, no trailing zeros."""
    text = f"{x:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


_LINE = re.compile(r"^\s*(\d{0,2})\s*([A-Za-z]{2})(.*?)\s*$")
_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?$")


@dataclass
class _Controller:
    """What one SMC100 on the chain remembers besides its axis' mechanics."""

    address: int
    axis: SimAxis
    stage: str
    state: int = NOT_REF_RESET
    error: str = "@"
    latched: int = 0  # latched positioner error bits (following error, homing time-out)
    sl: float = -_TRAVEL_DEG
    sr: float = _TRAVEL_DEG
    va: float = 20.0
    max_va: float = 20.0
    target: float = 0.0
    accel0: float = 80.0  # the stored acceleration RS returns to
    homing_deadline: float = math.inf


_QUERY_ONLY = frozenset({"TS", "TE", "TP", "TH", "VE"})  # take no parameter


class Smc100Emulator(Emulator):
    """One or more SMC100 controllers behind one serial port (RS-232 master + RS-485)."""

    protocol = "smc100"
    baudrate = 57600  # the real controller's line: 8N1 XON/XOFF
    HOMING_TIMEOUT_S = 60.0  # the manual's OT default: longest homing before bit 0x0040

    def __init__(self, name: str, axes: dict[int, SimAxis], clock: Clock,
                 stage: str | dict[int, str] = "URS75BCC",
                 firmware: str = FIRMWARE) -> None:
        super().__init__(name, axes, clock)
        for addr in axes:
            if not 1 <= addr <= 31:
                raise ValueError(f"SMC100 address {addr} outside 1..31 ({name})")
        self.firmware = firmware
        self._buf = bytearray()
        self.ctl: dict[int, _Controller] = {}
        for addr, ax in axes.items():
            st = stage.get(addr, "URS75BCC") if isinstance(stage, dict) else stage
            self.ctl[addr] = self._power_on(addr, ax, st)

    def _power_on(self, addr: int, ax: SimAxis, stage: str) -> _Controller:
        c = _Controller(address=addr, axis=ax, stage=stage, sl=ax.p.travel_min,
                        sr=ax.p.travel_max, va=ax.p.speed, max_va=ax.p.speed,
                        accel0=ax.p.accel)
        c.target = ax.motor_position()
        # A stage already referenced by the simulation (requires_homing=False) powers up
        # READY; a real SMC100 always starts NOT REFERENCED from reset.
        c.state = READY_HOMING if ax.homed else NOT_REF_RESET
        return c

    # ---- byte interface ------------------------------------------------------------
    def handle(self, data: bytes) -> bytes:
        self._buf += data
        out = bytearray()
        while True:
            cut = [i for i in (self._buf.find(b"\r"), self._buf.find(b"\n")) if i >= 0]
            if not cut:
                break
            i = min(cut)
            line = bytes(self._buf[:i])
            del self._buf[: i + 1]
            if line.strip():
                out += self._command(line)
        if len(self._buf) > 1024:  # a real UART buffer overflows; do not grow forever
            self._buf.clear()
        return bytes(out)

    def poll(self) -> bytes:
        for c in self.ctl.values():
            self._update(c)
        return b""

    # ---- state machine -------------------------------------------------------------
    def _update(self, c: _Controller) -> None:
        """Advance the controller state from what the mechanics did since last time."""
        ax = c.axis
        ax.motor_position()  # lets the axis finish a homing run it has completed
        moving = ax.moving
        if c.state == MOVING:
            if ax.stalled:  # the servo loop sees the following error grow: motor off
                c.latched |= ERR_FOLLOWING
                ax.stop()
                c.target = ax.motor_position()
                c.state = DISABLE_MOVING
            elif not moving:  # arrived, or stopped early by an end-of-run switch
                c.target = ax.motor_position()
                c.state = READY_MOVING
        elif c.state in HOMING_STATES:
            if ax.stalled:
                c.latched |= ERR_FOLLOWING
                ax.stop()
                ax.homed = False
                c.state = NOT_REF_HOMING
            elif self.clock.now() > c.homing_deadline:
                c.latched |= ERR_HOMING_TIMEOUT
                ax.stop()
                ax.homed = False
                c.state = NOT_REF_HOMING
            elif not moving and ax.homed:
                c.state = READY_HOMING
                c.target = ax.motor_position()

    def _errors(self, c: _Controller) -> int:
        bits = c.latched
        if c.axis.limit_low:
            bits |= ERR_NEG_END_OF_RUN
        if c.axis.limit_high:
            bits |= ERR_POS_END_OF_RUN
        return bits

    @staticmethod
    def _not_allowed(state: int) -> str:
        """The TE letter for a command the current state refuses."""
        if state in NOT_REFERENCED_STATES:
            return "H"
        if state == CONFIGURATION:
            return "I"
        if state in DISABLE_STATES:
            return "J"
        if state in READY_STATES:
            return "K"
        if state in HOMING_STATES:
            return "L"
        if state == MOVING:
            return "M"
        return "D"

    # ---- command interpreter -------------------------------------------------------
    def _command(self, raw: bytes) -> bytes:
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            self.note_command("?")
            log.debug("%s: undecodable command %r ignored", self.name, raw)
            return b""
        m = _LINE.match(text)
        self.note_command("?" if m is None else m.group(2).upper())
        if m is None:
            log.debug("%s: unparseable command %r", self.name, text)
            # no address to store the error against: the first controller takes it
            first = next(iter(self.ctl.values()), None)
            if first is not None:
                first.error = "A"
            return b""
        addr_text, cmd, arg = m.group(1), m.group(2).upper(), m.group(3).strip()
        if addr_text == "":
            # commands without an address go to every controller on the chain (e.g. ST);
            # only the first one answers queries, so the bus does not collide
            replies = [self._execute(c, cmd, arg) for c in self.ctl.values()]
            return next((r for r in replies if r), b"")
        c = self.ctl.get(int(addr_text))
        if c is None:
            return b""  # nobody on the chain has that address: silence, as on RS-485
        return self._execute(c, cmd, arg)

    def _execute(self, c: _Controller, cmd: str, arg: str) -> bytes:
        self._update(c)
        handler = getattr(self, f"_cmd_{cmd.lower()}", None)
        if handler is None:
            c.error = "A"
            return b""
        if cmd.upper() in _QUERY_ONLY and arg not in ("", "?"):
            c.error = "C"  # a query-only command given a parameter
            return b""
        reply: str | None = handler(c, arg)
        if reply is None:
            return b""
        return f"{c.address}{cmd}{reply}\r\n".encode("ascii")

    def _number(self, c: _Controller, arg: str) -> float | None:
        if not _NUMBER.match(arg):
            c.error = "C"
            return None
        value = float(arg)
        if not math.isfinite(value):
            c.error = "C"
            return None
        return value

    # queries ----------------------------------------------------------------------
    def _cmd_ts(self, c: _Controller, arg: str) -> str | None:
        return f"{self._errors(c):04X}{c.state:02X}"

    def _cmd_te(self, c: _Controller, arg: str) -> str | None:
        letter, c.error = c.error, "@"
        return letter

    def _cmd_tb(self, c: _Controller, arg: str) -> str | None:
        letter = (arg or c.error)[:1].upper()
        if letter == "?":
            letter = c.error
        if letter not in ERROR_TEXT:
            c.error = "C"
            return None
        return f"{letter} {ERROR_TEXT[letter]}"

    def _cmd_tp(self, c: _Controller, arg: str) -> str | None:
        return _fmt(c.axis.encoder_position())

    def _cmd_th(self, c: _Controller, arg: str) -> str | None:
        return _fmt(c.target)

    def _cmd_ve(self, c: _Controller, arg: str) -> str | None:
        return f" {self.firmware}"

    def _cmd_id(self, c: _Controller, arg: str) -> str | None:
        if arg == "?":
            return c.stage
        # setting the stage identifier is a CONFIGURATION-state command
        c.error = self._not_allowed(c.state) if c.state != CONFIGURATION else "C"
        return None

    # settings -----------------------------------------------------------------------
    def _limit(self, c: _Controller, arg: str, side: str) -> str | None:
        if arg == "?":
            return _fmt(c.sl if side == "SL" else c.sr)
        value = self._number(c, arg)
        if value is None:
            return None
        if c.state not in READY_STATES | NOT_REFERENCED_STATES | {CONFIGURATION}:
            c.error = self._not_allowed(c.state)
            return None
        if (side == "SL" and not -1e12 <= value <= 0) or (side == "SR" and not 0 <= value
                                                          <= 1e12):
            c.error = "C"
            return None
        if side == "SL":
            c.sl = value
        else:
            c.sr = value
        return None

    def _cmd_sl(self, c: _Controller, arg: str) -> str | None:
        return self._limit(c, arg, "SL")

    def _cmd_sr(self, c: _Controller, arg: str) -> str | None:
        return self._limit(c, arg, "SR")

    def _cmd_va(self, c: _Controller, arg: str) -> str | None:
        if arg == "?":
            return _fmt(c.va)
        value = self._number(c, arg)
        if value is None:
            return None
        if c.state not in READY_STATES | NOT_REFERENCED_STATES | {CONFIGURATION}:
            c.error = self._not_allowed(c.state)
            return None
        if not 1e-6 <= value <= c.max_va:
            c.error = "C"
            return None
        c.va = value
        return None

    def _cmd_ac(self, c: _Controller, arg: str) -> str | None:
        if arg == "?":
            return _fmt(c.axis.p.accel)
        value = self._number(c, arg)
        if value is None:
            return None
        if c.state not in READY_STATES | NOT_REFERENCED_STATES | {CONFIGURATION}:
            c.error = self._not_allowed(c.state)
            return None
        if not 1e-6 <= value <= 1e12:
            c.error = "C"
            return None
        c.axis.p.accel = value
        return None

    # motion -------------------------------------------------------------------------
    def _move(self, c: _Controller, target: float) -> None:
        ok = (c.state in READY_STATES or c.state == MOVING) and c.sl <= target <= c.sr
        self.log_target(c.axis, target, accepted=ok)
        if c.state not in READY_STATES and c.state != MOVING:
            c.error = self._not_allowed(c.state)
            return
        if not c.sl <= target <= c.sr:
            c.error = "G"
            return
        if c.state in READY_STATES and target == c.target:
            return  # a zero-length move: nothing starts, the state stays what it was
        c.target = target
        c.axis.move_to(target, speed=c.va)
        c.state = MOVING

    def _cmd_pa(self, c: _Controller, arg: str) -> str | None:
        if arg == "?":
            return _fmt(c.target)
        value = self._number(c, arg)
        if value is not None:
            self._move(c, value)
        return None

    def _cmd_pr(self, c: _Controller, arg: str) -> str | None:
        if arg == "?":
            c.error = "C"
            return None
        value = self._number(c, arg)
        if value is not None:
            self._move(c, c.target + value)
        return None

    def _cmd_st(self, c: _Controller, arg: str) -> str | None:
        self.log_stop(c.axis)
        if c.state == MOVING:
            c.axis.stop()
            c.target = c.axis.motor_position()
            c.state = READY_MOVING
        elif c.state in HOMING_STATES:
            c.axis.stop()
            c.axis.homed = False
            c.state = NOT_REF_HOMING
        return None  # in any other state a stop has nothing to do

    def _cmd_or(self, c: _Controller, arg: str) -> str | None:
        if c.state in HOMING_STATES:
            c.error = "E"
            return None
        if c.state not in NOT_REFERENCED_STATES:
            c.error = self._not_allowed(c.state)
            return None
        c.latched = 0
        c.axis.home()
        c.homing_deadline = self.clock.now() + self.HOMING_TIMEOUT_S
        c.state = HOMING_RS232
        return None

    def _cmd_mm(self, c: _Controller, arg: str) -> str | None:
        if arg == "?":
            c.error = "C"
            return None
        if arg == "0":
            if c.state in READY_STATES:
                c.state = DISABLE_READY
            elif c.state == MOVING:
                c.axis.stop()
                c.target = c.axis.motor_position()
                c.state = DISABLE_MOVING
            elif c.state not in DISABLE_STATES:
                c.error = self._not_allowed(c.state)
            return None
        if arg == "1":
            if c.state in DISABLE_STATES:
                c.latched &= ~ERR_FOLLOWING
                c.target = c.axis.motor_position()
                c.state = READY_DISABLE
            elif c.state not in READY_STATES:
                c.error = self._not_allowed(c.state)
            return None
        c.error = "C"
        return None

    def _cmd_rs(self, c: _Controller, arg: str) -> str | None:
        """Reset: motion stops, settings return to their stored values, not referenced."""
        c.axis.stop()
        c.axis.homed = False
        c.axis.p.accel = c.accel0
        fresh = self._power_on(c.address, c.axis, c.stage)
        fresh.state = NOT_REF_RESET
        self.ctl[c.address] = fresh
        return None
