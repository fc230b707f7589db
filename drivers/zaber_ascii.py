"""Zaber ASCII protocol: codec, daisy-chain link and the ``Axis`` driver for X-LSM stages.

Wire format (Zaber ASCII Protocol Manual, firmware 6/7):

- command ``/[device] [axis] [id] command [args][:CK]`` + CR LF; device 0 = every device on
  the chain, axis 0 = the whole device; the message id (0-99) is echoed in the replies.
- reply ``@NN A [ID] OK|RJ IDLE|BUSY WW data[:CK]`` + CR LF, where ``NN`` is always two
  digits, ``WW`` the highest-priority warning flag or ``--``, ``data`` ``0`` when empty or
  the rejection reason after ``RJ``; info ``#NN A [ID] text``; alert ``!NN A IDLE|BUSY WW``.
- checksum: the Longitudinal Redundancy Check of every byte after the leading ``/@#!`` up
  to the colon: ``((sum & 0xFF) ^ 0xFF) + 1`` as two hex digits. Devices verify it when a
  command carries one and append one to their messages when ``comm.checksum`` is 1.

The codec (``lrc``, ``format_command``, ``parse_line``) is pure. ``ZaberChain`` owns one
transport per daisy chain and matches replies to commands by message id, device and axis,
so alerts, info lines and late replies to earlier commands are never taken as the answer.
``ZaberAxis`` is one axis of one device on the chain, in mm.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from dataclasses import dataclass

from drivers.axis import Axis, AxisStatus, Identity
from drivers.clock import Clock
from drivers.config import AxisConfig, ControllerConfig
from drivers.errors import (
    DeviceError,
    DeviceFault,
    DeviceTimeoutError,
    LimitError,
    ProtocolError,
    TransportError,
)
from drivers.transport import SerialTransport

log = logging.getLogger(__name__)
# commands safe to repeat are re-sent at most this often after a lost or corrupt reply
# (two in a row still pass)
RETRIES = 2

DEFAULT_BAUDRATE = 115200
MAX_MESSAGE_ID = 99

# ---- protocol tables ------------------------------------------------------------------

REJECTION_REASONS: dict[str, str] = {
    "AGAIN": "the command cannot be processed right now; send it again",
    "BADAXIS": "the command was sent to an axis that does not exist or does not support it",
    "BADCOMMAND": "the command or setting is incorrect or invalid",
    "BADDATA": "the data in the command is incorrectly formatted or out of range",
    "BADMESSAGEID": "the message id is not -- or a number from 0 to 99",
    "BADSPLIT": "the command cannot be split into packets",
    "DEVICEONLY": "an axis number was given for a device-only command or setting",
    "DRIVERDISABLED": "the motor driver is disabled",
    "FULL": "the device has run out of space (stream buffer, trigger or storage)",
    "INACTIVE": "the axis or device is inactive (no peripheral connected?)",
    "LOCKSTEP": "the axis is part of a lockstep group",
    "NOACCESS": "the command or setting needs a higher access level",
    "NOTSUPPORTED": "the command or setting is not supported on this device",
    "PARKED": "the device is parked; unpark it first",
    "REMOTE": "the command cannot run while the device is in remote mode",
    "STATUSBUSY": "the device is busy",
    "SYSTEMERROR": "a system error occurred; power-cycle the device",
    "DEVICEMOVING": "the device is moving",
}

WARNING_FLAGS: dict[str, str] = {
    # faults: the axis stopped itself or cannot move
    "FD": "driver disabled (overheated or fault)",
    "FQ": "encoder error",
    "FS": "stalled and stopped",
    "FT": "excessive twist (lockstep)",
    "FB": "stream bounds error",
    "FP": "interpolated path deviation",
    "FE": "limit error: the axis took too long to reach its limit sensor",
    "FM": "peripheral mismatch",
    "FO": "driver over-current / over-temperature",
    # warnings
    "WH": "device not homed (has a position reference but was not homed)",
    "WL": "unexpected limit trigger",
    "WP": "invalid calibration",
    "WV": "supply voltage out of range",
    "WT": "system temperature high",
    "WM": "displaced when stationary",
    "WR": "no reference position (not homed)",
    # notices
    "NC": "manual control",
    "NI": "command interrupted",
    "ND": "stream discontinuity",
    "NU": "setting update pending",
    "NJ": "joystick calibrating",
}

# Flags that stay until acknowledged with `warnings clear` (the rest clear themselves).
# (NI, "command interrupted", clears itself with the next move from standstill.)
LATCHED_FLAGS = frozenset({"FS", "FE", "FQ", "FT", "FB", "FP", "WL"})
NOT_HOMED_FLAGS = frozenset({"WR", "WH"})

# Microstep size of the stage families this driver knows, at the default resolution of 64
# microsteps per full step: X-LSM lead screw 0.6096 mm/turn, 200 full steps per turn
# -> 3.048 um per full step -> 0.047625 um per microstep (Zaber X-LSM product specs).
FULL_STEP_MM: dict[str, float] = {
    "X-LSM": 0.6096 / 200.0,
    "LSM": 0.6096 / 200.0,  # the older T-/A-series LSM family shares the lead screw
}
DEFAULT_RESOLUTION = 64
# Setting units of A-/X-series devices (Zaber "Set Target Speed" / "Set Acceleration"
# command references): speed = data / 1.6384 microsteps/s, acceleration =
# data x 10000 / 1.6384 microsteps/s^2, accel data at most 32767.
SPEED_UNITS_PER_STEP_S = 1.6384  # maxspeed data per microstep/s
ACCEL_UNITS_PER_STEP_S2 = 1.6384 / 10000.0  # accel data per microstep/s^2
ACCEL_DATA_MAX = 32767

# Device ids the emulator reports; anything else is shown as "device id N".
# (The numbers for the X-LSM sizes were not verifiable against Zaber's device database.)
DEVICE_IDS: dict[int, str] = {
    50079: "X-LSM025A",
    50081: "X-LSM050A",
    50082: "X-LSM100A",
    50083: "X-LSM150A",
    50084: "X-LSM200A",
}


def full_step_mm(stage: str) -> float:
    """Full-step length of ``stage`` (e.g. ``X-LSM050A``) in mm; ``KeyError`` if unknown."""
    name = stage.upper()
    for prefix in sorted(FULL_STEP_MM, key=len, reverse=True):
        if name.startswith(prefix):
            return FULL_STEP_MM[prefix]
    raise KeyError(stage)


# ---- codec ----------------------------------------------------------------------------


def lrc(body: bytes) -> int:
    """Zaber's checksum of ``body`` (the bytes after the message type, before the colon)."""
    return ((sum(body) & 0xFF) ^ 0xFF) + 1 & 0xFF


def format_command(device: int, axis: int, command: str, message_id: int | None = None,
                   checksum: bool = True) -> bytes:
    """``/device axis [id] command[:CK]`` + CR LF, ready for the wire."""
    if not 0 <= device <= 99:
        raise ValueError(f"device address {device} outside 0..99")
    if not 0 <= axis <= 9:
        raise ValueError(f"axis number {axis} outside 0..9")
    if message_id is not None and not 0 <= message_id <= MAX_MESSAGE_ID:
        raise ValueError(f"message id {message_id} outside 0..{MAX_MESSAGE_ID}")
    if any(c in command for c in ":/\r\n") or not command.isascii():
        raise ValueError(f"command {command!r} contains a reserved or non-ASCII character")
    parts = [str(device), str(axis)]
    if message_id is not None:
        parts.append(str(message_id))
    if command:
        parts.append(command)
    body = " ".join(parts).encode("ascii")
    if checksum:
        body += b":%02X" % lrc(body)
    return b"/" + body + b"\r\n"


@dataclass(frozen=True)
class Reply:
    """One parsed message from a device: a reply (``@``), info (``#``) or alert (``!``)."""

    kind: str
    device: int
    axis: int
    message_id: int | None
    flag: str  # OK | RJ (replies only)
    status: str  # IDLE | BUSY (replies and alerts)
    warning: str  # highest-priority warning flag or --
    data: str
    has_checksum: bool = False

    @property
    def ok(self) -> bool:
        return self.flag == "OK"

    @property
    def busy(self) -> bool:
        return self.status == "BUSY"

    @property
    def reason(self) -> str:
        """The rejection reason of an ``RJ`` reply, with its meaning."""
        text = REJECTION_REASONS.get(self.data)
        return f"{self.data} ({text})" if text else self.data


_REPLY_RE = re.compile(r"@(\d\d) (\d)(?: (\d\d))? (OK|RJ) (IDLE|BUSY) (\S\S) (.+)")
_INFO_RE = re.compile(r"#(\d\d) (\d)(?: (\d\d)(?= |$))?(?: (.*))?")
_ALERT_RE = re.compile(r"!(\d\d) (\d) (IDLE|BUSY) (\S\S)(?: (.*))?")


def parse_line(line: bytes) -> Reply:
    """Parse one line from a device (terminator optional); ``ProtocolError`` if malformed.

    The checksum, when present, is verified; a mismatch is a ``ProtocolError`` too.
    """
    raw = line.rstrip(b"\r\n")
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError as exc:
        raise ProtocolError(f"non-ASCII bytes in reply {line!r}") from exc
    has_ck = len(text) >= 4 and text[-3] == ":"
    if has_ck:
        body, ck = text[1:-3], text[-2:]
        try:
            sent = int(ck, 16)
        except ValueError as exc:
            raise ProtocolError(f"bad checksum field {ck!r} in reply {line!r}") from exc
        if (sum(body.encode("ascii")) + sent) & 0xFF:
            raise ProtocolError(f"checksum mismatch in reply {line!r} "
                                f"(sent {ck}, computed {lrc(body.encode('ascii')):02X})")
        text = text[:-3]
    if text.startswith("@"):
        m = _REPLY_RE.fullmatch(text)
        if m:
            mid = int(m[3]) if m[3] is not None else None
            return Reply("@", int(m[1]), int(m[2]), mid, m[4], m[5], m[6], m[7], has_ck)
    elif text.startswith("#"):
        m = _INFO_RE.fullmatch(text)
        if m:
            mid = int(m[3]) if m[3] is not None else None
            return Reply("#", int(m[1]), int(m[2]), mid, "", "", "", m[4] or "", has_ck)
    elif text.startswith("!"):
        m = _ALERT_RE.fullmatch(text)
        if m:
            return Reply("!", int(m[1]), int(m[2]), None, "", m[3], m[4], m[5] or "", has_ck)
    raise ProtocolError(f"malformed reply {line!r}")


def parse_warnings(data: str) -> tuple[str, ...]:
    """The flags of a ``warnings`` reply's data (``02 FS WR`` -> ``("FS", "WR")``)."""
    tokens = data.split()
    if not tokens or not tokens[0].isdigit():
        raise ProtocolError(f"malformed warnings data {data!r}")
    count, flags = int(tokens[0]), tuple(tokens[1:])
    if count != len(flags) or not all(re.fullmatch(r"[A-Z]{2}", f) for f in flags):
        raise ProtocolError(f"malformed warnings data {data!r}")
    return flags


# ---- the daisy chain ------------------------------------------------------------------


class ZaberChain:
    """One serial link to a daisy chain of Zaber devices, shared by their axes.

    Every command carries a message id (cycling 0..99) and, by default, a checksum. The
    reply to a command is the ``@`` line from the addressed device and axis with the same
    id; everything else on the line (alerts, info, replies to earlier commands that came
    in late) is logged and discarded. A malformed reply or a checksum mismatch drains the
    input (resynchronisation) and raises ``ProtocolError``.
    """

    def __init__(self, url: str, *, name: str = "zaber", baudrate: int = DEFAULT_BAUDRATE,
                 timeout_s: float = 0.5, checksums: bool = True,
                 reply_checksums: bool = True, transport: SerialTransport | None = None) -> None:
        self.name = name
        self.transport = transport or SerialTransport(url, device=name, baudrate=baudrate,
                                                      timeout_s=timeout_s)
        self.url = self.transport.url
        self.checksums = checksums
        self.reply_checksums = reply_checksums
        self._users = 0
        self._users_lock = threading.Lock()
        self._next_id = 0
        self.discarded: list[Reply] = []  # stray lines seen (most recent 100), for diagnosis

    # ---- life cycle: opened by the first axis, closed with the last ----------------
    def acquire(self) -> None:
        with self._users_lock:
            if not self.transport.is_open:  # first user, or the port vanished since
                self.transport.open()
                try:
                    self.transport.drain()
                    if self.reply_checksums:
                        self._enable_reply_checksums()
                except DeviceError:
                    self.transport.close()
                    raise
            self._users += 1

    def release(self) -> None:
        with self._users_lock:
            if self._users == 0:
                return
            self._users -= 1
            if self._users == 0:
                self.transport.close()

    @property
    def is_open(self) -> bool:
        return self.transport.is_open

    def _enable_reply_checksums(self) -> None:
        """Ask every device to checksum its replies (``comm.checksum 1``) if not yet on."""
        replies = self.broadcast("get comm.checksum",
                                 quiet_s=min(self.transport.timeout_s, 0.1))
        if not replies:
            raise DeviceTimeoutError("no device answered on the chain", device=self.name,
                                     port=self.url, command="get comm.checksum")
        for r in replies:
            if r.ok and r.data.strip() != "1":
                log.info("%s: enabling reply checksums on device %d", self.name, r.device)
                self.command(r.device, 0, "set comm.checksum 1", retries=RETRIES)

    # ---- exchanges ---------------------------------------------------------------
    def _take_id(self) -> int:
        mid = self._next_id
        self._next_id = (mid + 1) % (MAX_MESSAGE_ID + 1)
        return mid

    def _discard(self, reply: Reply, why: str) -> None:
        log.debug("%s: discarded %s (%s)", self.name, reply, why)
        self.discarded.append(reply)
        del self.discarded[:-100]

    def _read_reply(self, deadline: float, command: str) -> Reply:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise DeviceTimeoutError("no reply", device=self.name, port=self.url,
                                     command=command)
        line = self.transport.read_until(b"\n", timeout_s=remaining, command=command)
        try:
            return parse_line(line)
        except ProtocolError as exc:
            self.transport.drain()
            raise ProtocolError(f"{exc.detail}; input drained to resynchronise",
                                device=self.name, port=self.url, command=command) from exc

    def command(self, device: int, axis: int, command: str, *,
                timeout_s: float | None = None, retries: int = 0) -> Reply:
        """Send ``command`` to one device/axis and return its matching ``@`` reply.

        ``retries`` re-sends after a corrupted or lost reply (``ProtocolError``,
        ``DeviceTimeoutError``); only for commands that are safe to repeat. A late reply to
        the first try cannot pass for the answer to the next: it carries the old message
        id. Rejections (``RJ``) are returned, not raised.
        """
        if device == 0:
            raise ValueError("use broadcast() for device 0")
        attempt = 0
        while True:
            try:
                return self._exchange(device, axis, command, timeout_s)
            except (ProtocolError, DeviceTimeoutError) as exc:
                if attempt >= retries or not self.transport.is_open:
                    raise
                attempt += 1
                log.warning("%s: %s to %r on device %d, retrying (%d/%d)", self.name,
                            exc.detail, command, device, attempt, retries)

    def _exchange(self, device: int, axis: int, command: str,
                  timeout_s: float | None) -> Reply:
        what = f"/{device} {axis} {command}".rstrip()
        with self.transport.lock:
            mid = self._take_id()
            self.transport.write(format_command(device, axis, command, mid, self.checksums),
                                 command=what)
            deadline = time.monotonic() + (self.transport.timeout_s if timeout_s is None
                                           else timeout_s)
            while True:
                try:
                    reply = self._read_reply(deadline, what)
                except DeviceTimeoutError:
                    if self.transport.is_open:
                        self.transport.drain()  # drop a partial line before the next try
                    raise
                if reply.kind != "@":
                    self._discard(reply, "alert" if reply.kind == "!" else "info")
                elif reply.message_id != mid:
                    self._discard(reply, f"message id {reply.message_id}, expected {mid}")
                elif reply.device != device or reply.axis != axis:
                    self._discard(reply, f"from {reply.device}/{reply.axis}, "
                                         f"expected {device}/{axis}")
                else:
                    return reply

    def broadcast(self, command: str, *, axis: int = 0,
                  quiet_s: float | None = None) -> list[Reply]:
        """Send ``command`` to every device (device 0); collect replies until quiet.

        The first reply may take the whole reply timeout (a busy host or a slow link);
        after it, ``quiet_s`` without another reply ends the collection."""
        what = f"/0 {axis} {command}".rstrip()
        quiet = self.transport.timeout_s if quiet_s is None else quiet_s
        replies: list[Reply] = []
        with self.transport.lock:
            mid = self._take_id()
            self.transport.write(format_command(0, axis, command, mid, self.checksums),
                                 command=what)
            while True:
                wait = quiet if replies else max(quiet, self.transport.timeout_s)
                try:
                    reply = self._read_reply(time.monotonic() + wait, what)
                except DeviceTimeoutError:
                    break
                if reply.kind == "@" and reply.message_id == mid:
                    replies.append(reply)
                else:
                    self._discard(reply, "not a reply to the broadcast")
        return sorted(replies, key=lambda r: (r.device, r.axis))


# ---- the axis driver ------------------------------------------------------------------


def _flag_text(flags: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(f"{f}: {WARNING_FLAGS.get(f, 'unknown flag')}" for f in flags)


class ZaberAxis(Axis):
    """One axis of one Zaber device (``config.address`` = device, ``config.axis`` = axis)."""

    def __init__(self, config: AxisConfig, chain: ZaberChain, name: str | None = None, *,
                 clock: Clock | None = None) -> None:
        super().__init__(config, name, clock=clock)
        if config.units != "mm":
            raise DeviceError(f"Zaber driver supports linear stages in mm, not "
                              f"{config.units!r}", device=self.name, port=chain.url)
        try:
            self._full_step_mm = full_step_mm(config.stage)
        except KeyError:
            known = ", ".join(sorted(FULL_STEP_MM))
            raise DeviceError(f"unknown Zaber stage {config.stage!r} (known families: "
                              f"{known})", device=self.name, port=chain.url) from None
        if not 1 <= config.address <= 99:
            raise DeviceError(f"Zaber device address {config.address} outside 1..99",
                              device=self.name, port=chain.url)
        self.chain = chain
        self.device = config.address
        self.axis_number = config.axis
        self.resolution = DEFAULT_RESOLUTION
        self._connected = False
        self._latched: frozenset[str] = frozenset()
        self._target: float | None = None  # last commanded absolute target, mm

    # ---- units ------------------------------------------------------------------
    @property
    def microstep_mm(self) -> float:
        return self._full_step_mm / self.resolution

    def to_steps(self, mm: float) -> int:
        return round(mm / self.microstep_mm)

    def to_mm(self, steps: int) -> float:
        return steps * self.microstep_mm

    def speed_data(self, mm_s: float) -> int:
        """mm/s -> ``maxspeed`` data (microsteps/s x 1.6384)."""
        return round(mm_s / self.microstep_mm * SPEED_UNITS_PER_STEP_S)

    def accel_data(self, mm_s2: float) -> int:
        """mm/s^2 -> ``accel`` data (microsteps/s^2 x 1.6384 / 10000)."""
        return round(mm_s2 / self.microstep_mm * ACCEL_UNITS_PER_STEP_S2)

    @property
    def port(self) -> str:
        return self.chain.url

    # ---- plumbing ---------------------------------------------------------------
    def _cmd(self, text: str, *, device_scope: bool = False, retries: int = 0,
             timeout_s: float | None = None) -> Reply:
        axis = 0 if device_scope else self.axis_number
        if not self._connected:
            raise TransportError("axis is not connected", device=self.name, port=self.port,
                                 command=text)
        return self.chain.command(self.device, axis, text, retries=retries,
                                  timeout_s=timeout_s)

    def _checked(self, text: str, **kw: object) -> Reply:
        reply = self._cmd(text, **kw)  # type: ignore[arg-type]
        if not reply.ok:
            raise DeviceFault(f"command rejected: {reply.reason}", device=self.name,
                              port=self.port, command=text)
        return reply

    def _get_int(self, setting: str, *, device_scope: bool = False) -> int:
        reply = self._checked(f"get {setting}", device_scope=device_scope, retries=RETRIES)
        try:
            return int(reply.data.split()[0])
        except (ValueError, IndexError) as exc:
            raise ProtocolError(f"non-integer value {reply.data!r} for {setting}",
                                device=self.name, port=self.port,
                                command=f"get {setting}") from exc

    # ---- life cycle ---------------------------------------------------------------
    def connect(self) -> None:
        if self._connected:
            return
        self.chain.acquire()
        self._connected = True
        try:
            axes = self._get_int("system.axiscount", device_scope=True)
            if self.axis_number > axes:
                raise DeviceError(f"device {self.device} has {axes} axis/axes, config asks "
                                  f"for axis {self.axis_number}", device=self.name,
                                  port=self.port)
            self.resolution = self._get_int("resolution")
            self._apply_motion_settings()
        except BaseException:
            self.close()
            raise
        log.info("%s: connected to Zaber device %d axis %d on %s (%.6g um/microstep)",
                 self.name, self.device, self.axis_number, self.port, self.microstep_mm * 1e3)

    def _apply_motion_settings(self) -> None:
        """Make the device's maxspeed/accel match the config, so move timeouts hold."""
        want = {"maxspeed": self.speed_data(self.speed),
                "accel": self.accel_data(self.config.accel)}
        if not 1 <= want["accel"] <= ACCEL_DATA_MAX:
            limit = ACCEL_DATA_MAX / ACCEL_UNITS_PER_STEP_S2 * self.microstep_mm
            raise DeviceError(f"accel {self.config.accel:g} mm/s^2 is {want['accel']} in "
                              f"device units, outside 1..{ACCEL_DATA_MAX} (at most "
                              f"{limit:.0f} mm/s^2 at this resolution): lower axes.accel",
                              device=self.name, port=self.port, command="set accel")
        for setting, value in want.items():
            have = self._get_int(setting)
            if abs(have - value) > max(1, 0.01 * value):
                log.info("%s: set %s %d (was %d)", self.name, setting, value, have)
                self._checked(f"set {setting} {value}", retries=RETRIES)

    def _send_speed(self, speed: float) -> None:
        """``set maxspeed``: the velocity of the next moves (device units)."""
        self._checked(f"set maxspeed {self.speed_data(speed)}", retries=RETRIES)

    def close(self) -> None:
        if not self._connected:
            return
        self._connected = False
        self.position_known = False
        self.chain.release()

    # ---- Axis primitives ----------------------------------------------------------
    def identify(self) -> Identity:
        device_id = self._get_int("deviceid", device_scope=True)
        serial = self._checked("get system.serial", device_scope=True, retries=RETRIES).data
        version = self._checked("get version", device_scope=True, retries=RETRIES).data
        peripheral = self._get_int("peripheralid")
        model = DEVICE_IDS.get(device_id, f"Zaber device id {device_id}")
        # An integrated device (no peripheral) is its own stage: report what it says it is.
        if peripheral != 0:
            stage = f"peripheral id {peripheral}"
        else:
            stage = DEVICE_IDS.get(device_id, self.config.stage)
        return Identity(vendor="Zaber", model=model, serial=serial.strip(),
                        firmware=version.strip(), stage=stage)

    def home(self) -> None:
        if self._latched:
            self._clear_warnings()
        self._checked("home")
        self._target = None
        timeout = self.config.home_timeout_s / max(self.config.time_scale, 1e-9)
        st = self.wait_until_stopped(timeout, command="home")
        if not st.homed:
            raise DeviceFault(f"homing ended without a reference position: "
                              f"{'; '.join(st.messages) or st.raw}", device=self.name,
                              port=self.port, command="home")
        self.position_known = True

    def _start_move(self, target: float) -> None:
        if self._latched:
            self._clear_warnings()
        steps = self.to_steps(target)
        text = f"move abs {steps}"
        # an absolute move is idempotent: after a lost or corrupt reply it is sent again
        # (with a new message id, so a late first reply cannot pass for the second)
        reply = self._cmd(text, retries=RETRIES)
        if reply.ok:
            self._target = self.to_mm(steps)
            return
        if reply.warning in NOT_HOMED_FLAGS:
            raise DeviceFault(f"move rejected ({reply.data}): axis is not homed "
                              f"({reply.warning}); home it first", device=self.name,
                              port=self.port, command=text)
        if reply.data == "BADDATA":
            raise LimitError(f"move to {target:.6g} mm ({steps} microsteps) rejected: "
                             f"{reply.reason}", device=self.name, port=self.port,
                             command=text)
        raise DeviceFault(f"move rejected: {reply.reason}", device=self.name,
                          port=self.port, command=text)

    def stop(self) -> None:
        self._checked("stop", retries=RETRIES)

    def controller_limits(self) -> tuple[float, float]:
        """``limit.min`` / ``limit.max``: the device refuses moves outside them."""
        return self.to_mm(self._get_int("limit.min")), self.to_mm(self._get_int("limit.max"))

    def position(self) -> float:
        return self.to_mm(self._get_int("pos"))

    def _clear_warnings(self) -> None:
        reply = self._checked("warnings clear", retries=RETRIES)
        log.warning("%s: cleared latched warnings %s", self.name, reply.data)
        self._latched = frozenset()

    def status(self) -> AxisStatus:
        reply = self._checked("warnings", retries=RETRIES)
        try:
            flags = parse_warnings(reply.data)
        except ProtocolError as exc:
            raise ProtocolError(exc.detail, device=self.name, port=self.port,
                                command="warnings") from exc
        self._latched = frozenset(flags) & LATCHED_FLAGS
        limit_low = limit_high = False
        if "WL" in flags:
            # The flag does not say which end. A move stopped short of its target was
            # heading towards the sensor that tripped; otherwise the nearer end tells.
            here = self.position()
            if self._target is not None:
                limit_high = self._target > here
            else:
                limit_high = here >= sum(self.config.soft_limits.model_dump().values()) / 2
            limit_low = not limit_high
        return AxisStatus(
            moving=reply.busy,
            homed=not (set(flags) & NOT_HOMED_FLAGS),
            limit_low=limit_low,
            limit_high=limit_high,
            stalled="FS" in flags,
            fault=any(f.startswith("F") and f != "FS" for f in flags),
            raw=f"{reply.status} {' '.join(flags) or '--'}",
            messages=_flag_text(flags),
        )


def make_axes(controller: ControllerConfig, time_scale: float = 1.0, *,
              clock: Clock | None = None) -> list[ZaberAxis]:
    """One ``ZaberAxis`` per configured axis, all sharing one chain (one serial port)."""
    chain = ZaberChain(controller.port, name=controller.name,
                       baudrate=controller.baudrate or DEFAULT_BAUDRATE,
                       timeout_s=controller.reply_timeout_s)
    return [ZaberAxis(ax.model_copy(update={"time_scale": time_scale}), chain, clock=clock)
            for ax in controller.axes]


__all__ = [
    "DEVICE_IDS", "LATCHED_FLAGS", "REJECTION_REASONS", "WARNING_FLAGS", "Reply",
    "ZaberAxis", "ZaberChain", "format_command", "full_step_mm", "lrc", "make_axes",
    "parse_line", "parse_warnings",
]

