"""Newport SMC100CC / SMC100PP (and CONEX-CC) motion controllers over their ASCII protocol.

Wire format (SMC100 user manual): ``[address 1-31][two letters][value or ?]`` + CR LF,
57600 8N1 with XON/XOFF on the RS-232 master; controllers 2..31 hang off the master on an
internal RS-485 chain and share its port. Set commands are silent: a command the
controller refuses stores an error letter that ``TE`` returns once (reading clears it),
so every set command here is followed by a ``TE`` read. Replies echo address and command
(``1TP`` -> ``1TP12.345``); a reply whose echo is not the command just sent (a late reply
to an earlier, timed-out command) is discarded, never taken for the answer.

The codec (pure functions: format, parse, decode ``TS`` and ``TE``) is separate from the
driver (``Smc100Axis``: units, homing, status, errors). The emulator in
``drivers.sim.smc100_emu`` has its own parser on purpose.
"""

from __future__ import annotations

import logging
import math
import re
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import TypeVar, overload

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
T = TypeVar("T")

BAUDRATE = 57600
# an exchange that is safe to repeat is tried at most this often after lost or corrupt
# replies (two in a row still pass; the soak injects about one in seventy)
ATTEMPTS = 3
# set commands that may be resent with their TE check when its reply is lost
IDEMPOTENT = frozenset({"AC", "VA", "SL", "SR", "MM", "ST"})
TERMINATOR = b"\r\n"

# Commands whose replies this driver understands (anything else in an echo is garbage).
KNOWN_COMMANDS = frozenset({
    "AC", "BA", "BH", "DV", "FD", "FE", "FF", "HT", "ID", "JD", "JM", "JR", "KD", "KI", "KP",
    "KV", "MM", "OH", "OR", "OT", "PA", "PR", "PT", "PW", "QI", "RA", "RB", "RS", "SA", "SB",
    "SE", "SL", "SR", "ST", "SU", "TB", "TE", "TH", "TP", "TS", "VA", "VE", "ZT", "ZX",
})

# ---- controller states (TS, last two hex digits) -----------------------------------
STATES: dict[int, str] = {
    0x0A: "NOT REFERENCED from reset",
    0x0B: "NOT REFERENCED from HOMING",
    0x0C: "NOT REFERENCED from CONFIGURATION",
    0x0D: "NOT REFERENCED from DISABLE",
    0x0E: "NOT REFERENCED from READY",
    0x0F: "NOT REFERENCED from MOVING",
    0x10: "NOT REFERENCED ESP stage error",
    0x11: "NOT REFERENCED from JOGGING",
    0x14: "CONFIGURATION",
    0x1E: "HOMING commanded from RS-232-C",
    0x1F: "HOMING commanded by SMC-RC",
    0x28: "MOVING",
    0x32: "READY from HOMING",
    0x33: "READY from MOVING",
    0x34: "READY from DISABLE",
    0x35: "READY from JOGGING",
    0x3C: "DISABLE from READY",
    0x3D: "DISABLE from MOVING",
    0x3E: "DISABLE from JOGGING",
    0x46: "JOGGING from READY",
    0x47: "JOGGING from DISABLE",
}

# state families (what the rest of alignd needs to know)
NOT_REFERENCED = "NOT REFERENCED"
CONFIGURATION = "CONFIGURATION"
HOMING = "HOMING"
MOVING = "MOVING"
READY = "READY"
DISABLE = "DISABLE"
JOGGING = "JOGGING"


def state_family(code: int) -> str:
    """The family (NOT REFERENCED, HOMING, READY, ...) of a TS state code; UNKNOWN if none."""
    name = STATES.get(code)
    return name.split(" from")[0].split(" ESP")[0].split(" commanded")[0] if name else "UNKNOWN"


# ---- positioner error bits (TS, first four hex digits), LSB first --------------------
POSITIONER_ERRORS: dict[int, str] = {
    0x0001: "negative end of run",
    0x0002: "positive end of run",
    0x0004: "peak current limit",
    0x0008: "RMS current limit",
    0x0010: "short circuit detection",
    0x0020: "following error",
    0x0040: "homing time-out",
    0x0080: "wrong ESP stage",
    0x0100: "DC voltage too low",
    0x0200: "80 W output power exceeded",
}
ERR_NEG_END_OF_RUN = 0x0001
ERR_POS_END_OF_RUN = 0x0002
ERR_FOLLOWING = 0x0020
FAULT_BITS = 0x0004 | 0x0008 | 0x0010 | 0x0040 | 0x0080 | 0x0100 | 0x0200

# ---- TE error letters ---------------------------------------------------------------
COMMAND_ERRORS: dict[str, str] = {
    "@": "no error",
    "A": "unknown message code or floating point controller address",
    "B": "controller address not correct",
    "C": "parameter missing or out of range",
    "D": "execution not allowed",
    "E": "home sequence already started",
    "F": "ESP stage name unknown",
    "G": "displacement out of limits",
    "H": "execution not allowed in NOT REFERENCED state (home the axis first)",
    "I": "execution not allowed in CONFIGURATION state",
    "J": "execution not allowed in DISABLE state (motor off; enable with MM1)",
    "K": "execution not allowed in READY state",
    "L": "execution not allowed in HOMING state",
    "M": "execution not allowed in MOVING state",
    "N": "current position out of software limit",
    "P": "execution not allowed in TRACKING state (CONEX-CC)",
    "S": "communication time-out",
    "U": "error during EEPROM access",
    "V": "error during command execution",
    "W": "command not allowed for PP version",
    "X": "command not allowed for CC version",
}


# ======================================================================================
# codec: pure functions
# ======================================================================================
def format_number(value: float) -> str:
    """A float in the fixed-point form the controller parses (no exponent, <= 6 decimals)."""
    if not math.isfinite(value):
        raise ValueError(f"cannot send non-finite number {value!r}")
    text = f"{value:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def format_command(address: int, command: str, value: float | int | str | None = None) -> bytes:
    """``format_command(1, "PA", 10.5)`` -> ``b"1PA10.5\\r\\n"``; ``value="?"`` queries."""
    if not 1 <= address <= 31:
        raise ValueError(f"SMC100 address {address} outside 1..31")
    if len(command) != 2 or not command.isalpha():
        raise ValueError(f"SMC100 commands are two letters, not {command!r}")
    if value is None:
        arg = ""
    elif isinstance(value, str):
        arg = value
    elif isinstance(value, bool):
        arg = str(int(value))
    elif isinstance(value, int):
        arg = str(value)
    else:
        arg = format_number(value)
    return f"{address}{command.upper()}{arg}".encode("ascii") + TERMINATOR


@dataclass(frozen=True)
class Reply:
    """One parsed reply line: ``1TP12.5`` -> address 1, command TP, value ``12.5``."""

    address: int
    command: str
    value: str


_REPLY = re.compile(rb"^(\d{1,2})([A-Z]{2})([\x20-\x7e]*)\r\n$")


def parse_reply(line: bytes) -> Reply:
    """Split a reply line into address, echoed command and value; ``ValueError`` if malformed."""
    m = _REPLY.match(line)
    if m is None:
        raise ValueError(f"malformed SMC100 reply {line!r}")
    command = m.group(2).decode("ascii")
    if command not in KNOWN_COMMANDS:
        raise ValueError(f"unknown command echo {command!r} in reply {line!r}")
    return Reply(int(m.group(1)), command, m.group(3).decode("ascii").strip())


def parse_float(value: str) -> float:
    """A position/velocity value; ``ValueError`` for anything but a plain finite number."""
    if not re.fullmatch(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?", value):
        raise ValueError(f"not a number: {value!r}")
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"not a finite number: {value!r}")
    return x


@dataclass(frozen=True)
class TsStatus:
    """A decoded ``TS`` reply: positioner error bits and controller state."""

    errors: int
    state: int

    @property
    def state_name(self) -> str:
        return STATES.get(self.state, f"unknown state 0x{self.state:02X}")

    @property
    def family(self) -> str:
        return state_family(self.state)

    @property
    def error_messages(self) -> tuple[str, ...]:
        return tuple(msg for bit, msg in POSITIONER_ERRORS.items() if self.errors & bit)

    @property
    def raw(self) -> str:
        return f"{self.errors:04X}{self.state:02X}"


def decode_ts(value: str) -> TsStatus:
    """``"000033"`` -> TsStatus(errors=0, state=0x33); ``ValueError`` if not 6 hex digits."""
    if not re.fullmatch(r"[0-9A-Fa-f]{6}", value):
        raise ValueError(f"TS value {value!r} is not 6 hex digits")
    return TsStatus(errors=int(value[:4], 16), state=int(value[4:], 16))


def decode_te(letter: str) -> str:
    """The meaning of a ``TE`` error letter (``"@"`` = no error)."""
    if len(letter) != 1:
        raise ValueError(f"TE value {letter!r} is not one letter")
    return COMMAND_ERRORS.get(letter.upper(), f"unknown error code {letter!r}")


def ts_to_status(ts: TsStatus) -> AxisStatus:
    """What the procedures need from a TS reply."""
    fam = ts.family
    limit_low = bool(ts.errors & ERR_NEG_END_OF_RUN)
    limit_high = bool(ts.errors & ERR_POS_END_OF_RUN)
    stalled = bool(ts.errors & ERR_FOLLOWING)
    fault = (bool(ts.errors & FAULT_BITS) or fam in (DISABLE, CONFIGURATION, "UNKNOWN")
             or ts.state == 0x10)
    return AxisStatus(
        moving=fam in (MOVING, HOMING, JOGGING),
        homed=fam in (READY, MOVING, JOGGING),
        limit_low=limit_low, limit_high=limit_high, stalled=stalled, fault=fault,
        raw=ts.raw, messages=(ts.state_name, *ts.error_messages))


def _te_letter(value: str) -> str:
    if len(value) != 1 or not (value == "@" or value.isalpha()):
        raise ValueError(f"TE value {value!r} is not one letter")
    return value.upper()


def parse_version(text: str) -> tuple[str, str]:
    """``"SMC_CC - Controller-driver version  3. 1. 2"`` -> (``"SMC100CC"``, ``"3.1.2"``)."""
    model = text.split(" ", 1)[0].strip() or "SMC100"
    model = {"SMC_CC": "SMC100CC", "SMC_PP": "SMC100PP"}.get(model, model)
    m = re.search(r"(\d+)\s*\.\s*(\d+)(?:\s*\.\s*(\d+))?\s*$", text)
    firmware = ".".join(g for g in m.groups() if g is not None) if m else text.strip()
    return model, firmware


# ======================================================================================
# driver
# ======================================================================================
_port_users: weakref.WeakKeyDictionary[SerialTransport, set[int]] = weakref.WeakKeyDictionary()


class Smc100Axis(Axis):
    """One SMC100 controller (one axis) at ``config.address`` on a possibly shared port."""

    reports_serial = False  # the ASCII protocol has no serial-number query

    def __init__(self, config: AxisConfig, transport: SerialTransport,
                 name: str | None = None, *, clock: Clock | None = None) -> None:
        super().__init__(config, name, clock=clock)
        if not 1 <= config.address <= 31:
            raise ValueError(f"{self.name}: SMC100 address {config.address} outside 1..31")
        self.address = config.address
        self.transport = transport
        self._connected = False
        self._resync = True  # drain before the next exchange (after open, timeouts, garbage)
        self._profile_sent = False
        # Commands whose reply timed out and may still come: the ASCII protocol has no
        # message ids, so a late reply would pass for the answer to a resent command.
        self._late: set[str] = set()

    # ---- life cycle ----------------------------------------------------------------
    @property
    def port(self) -> str:
        return self.transport.url

    def connect(self) -> None:
        """Open the (shared) port and check that this address answers."""
        if self._connected and self.transport.is_open:
            return
        users = _port_users.setdefault(self.transport, set())
        self.transport.open()
        users.add(id(self))
        self._connected = True
        self._resync = True
        self._profile_sent = False
        try:
            ts = self._status_raw()
        except DeviceError:
            self.close()
            raise
        log.info("%s: SMC100 at address %d on %s: %s", self.name, self.address, self.port,
                 ts.state_name)

    def close(self) -> None:
        """Release the port; the last axis on a shared port closes it."""
        if not self._connected:
            return
        self._connected = False
        self.position_known = False
        users = _port_users.get(self.transport, set())
        users.discard(id(self))
        if not users:
            self.transport.close()

    # ---- exchanges -----------------------------------------------------------------
    def _cmd_text(self, command: str, arg: str = "") -> str:
        return f"{self.address}{command}{arg}"

    def _write_bytes(self, data: bytes) -> None:
        text = " + ".join(data.decode("ascii").split())
        if not self._connected:
            raise TransportError("axis is not connected", device=self.name, port=self.port,
                                 command=text)
        self.transport.write(data, command=text)

    def _write(self, command: str, value: float | int | str | None = None) -> str:
        data = format_command(self.address, command, value)
        self._write_bytes(data)
        return data.decode("ascii").strip()

    @overload
    def query(self, command: str, arg: str = "", *, retry: bool = True,
              convert: None = None, before: bytes = b"") -> str: ...

    @overload
    def query(self, command: str, arg: str = "", *, retry: bool = True,
              convert: Callable[[str], T], before: bytes = b"") -> T: ...

    def query(self, command: str, arg: str = "", *, retry: bool = True,
              convert: Callable[[str], T] | None = None, before: bytes = b"") -> T | str:
        """Send ``command`` (+ ``arg``, e.g. ``"?"``) and return its reply's value.

        ``convert`` checks and converts the value (a ``ValueError`` counts as garbage).
        ``before`` (silent commands) goes out in the same write, ahead of the query, and is
        resent with it on a retry: one write instead of two also spares a Nagle/delayed-ACK
        stall on ``socket://`` links.
        A reply for another command or address is logged and skipped; garbage or a timeout
        resynchronises the link (drain) and, when ``retry``, sends the command again (at
        most ``ATTEMPTS`` tries).
        Raises ``DeviceTimeoutError`` or ``ProtocolError`` naming the command.
        """
        tr = self.transport
        text = self._cmd_text(command, arg)
        with tr.lock:
            for attempt in range(1, ATTEMPTS + 1):
                if self._resync and tr.is_open:
                    tr.drain()
                    self._resync = False
                data = format_command(self.address, command, arg or None)
                try:
                    self._write_bytes(before + data)
                    value = self._read_reply(command, text)
                    if command in self._late:
                        value = self._newest_reply(command, text, value)
                    if convert is None:
                        return value
                    try:
                        return convert(value)
                    except ValueError as exc:
                        raise ProtocolError(f"bad value in reply: {exc}", device=self.name,
                                            port=self.port, command=text) from exc
                except (DeviceTimeoutError, ProtocolError) as exc:
                    self._resync = True
                    if isinstance(exc, DeviceTimeoutError):
                        self._late.add(command)
                    if attempt == ATTEMPTS or not retry or not tr.is_open:
                        raise
                    log.warning("%s: %s; resynchronising and resending %s", self.name,
                                exc.detail, " + ".join((before + data).decode().split()))
        raise AssertionError("unreachable")  # pragma: no cover

    def _newest_reply(self, command: str, text: str, value: str) -> str:
        """After a timed-out ``command``, the reply just read may be the late answer to the
        earlier one. The controller answers in order, so the answer to this one follows
        it: take the newest reply with this echo that arrives within a reply timeout."""
        while True:
            try:
                newer = self._read_reply(command, text,
                                         timeout_s=self.transport.timeout_s)
            except DeviceTimeoutError:
                self._late.discard(command)
                return value
            log.warning("%s: reply %r to %s superseded by %r (the first was late)",
                        self.name, value, text, newer)
            value = newer

    def _read_reply(self, command: str, text: str, timeout_s: float | None = None) -> str:
        tr = self.transport
        deadline = time.monotonic() + (tr.timeout_s if timeout_s is None else timeout_s)
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceTimeoutError("no reply (only replies to other commands)",
                                         device=self.name, port=self.port, command=text)
            # up to LF, not CR LF: a reply whose CR was garbled is garbage now, not a timeout
            line = tr.read_until(b"\n", timeout_s=remaining, command=text)
            try:
                reply = parse_reply(line)
            except ValueError as exc:
                raise ProtocolError(str(exc), device=self.name, port=self.port,
                                    command=text) from exc
            if reply.address == self.address and reply.command == command:
                return reply.value
            log.warning("%s: discarding reply %r while waiting for %s (late reply to an "
                        "earlier command?)", self.name, line, text)

    def read_error(self) -> str:
        """Read (and so clear) the stored command error letter; ``"@"`` = none."""
        return self.query("TE", retry=False, convert=_te_letter)

    def send(self, command: str, value: float | int | str | None = None, *,
             retry: bool | None = None) -> None:
        """Send a silent set command and raise if the controller stored an error for it.

        The command and its ``TE`` check are resent together after a lost or garbled
        ``TE`` reply only for idempotent commands (``retry`` overrides): a resent ``OR``
        would be refused, a resent ``PA`` might be during MOVING.
        """
        data = format_command(self.address, command, value)
        if retry is None:
            retry = command.upper() in IDEMPOTENT
        letter = self._set_and_read_error(data, retry)
        if letter != "@":
            raise self._error_for(letter, data.decode("ascii").strip())

    def _set_and_read_error(self, data: bytes, retry: bool = False) -> str:
        # TE is destructive (reading clears it): it is only ever resent together with the
        # command whose outcome it reports
        try:
            return self.query("TE", retry=retry, convert=_te_letter, before=data)
        except (DeviceTimeoutError, ProtocolError) as exc:
            sent = data.decode("ascii").strip()
            raise type(exc)(f"{exc.detail} to the TE check of {sent} (it may have run)",
                            device=self.name, port=self.port,
                            command=f"{sent} + {self._cmd_text('TE')}") from exc

    def _error_for(self, letter: str, command: str) -> DeviceError:
        msg = f"controller refused the command: {decode_te(letter)} (TE {letter})"
        kw = {"device": self.name, "port": self.port, "command": command}
        if letter in ("G", "N"):
            return LimitError(msg, **kw)
        if letter in ("A", "B"):
            return ProtocolError(msg, **kw)
        return DeviceFault(msg, **kw)

    # ---- Axis primitives -----------------------------------------------------------
    def identify(self) -> Identity:
        stage = self.query("ID", "?")
        model, firmware = parse_version(self.query("VE"))
        return Identity(vendor="Newport", model=model, serial="", firmware=firmware,
                        stage=stage)

    def _status_raw(self) -> TsStatus:
        return self.query("TS", convert=decode_ts)

    def status(self) -> AxisStatus:
        return ts_to_status(self._status_raw())

    def position(self) -> float:
        return self.query("TP", convert=parse_float)

    def target(self) -> float:
        """The set-point the controller is moving to (``TH``)."""
        return self.query("TH", convert=parse_float)

    def software_limits(self) -> tuple[float, float]:
        """The controller's own software limits (``SL?``, ``SR?``)."""
        return (self.query("SL", "?", convert=parse_float),
                self.query("SR", "?", convert=parse_float))

    def controller_limits(self) -> tuple[float, float]:
        return self.software_limits()

    def stop(self) -> None:
        """``ST``; a refusal is logged, not raised (stopping a stopped axis is fine)."""
        data = format_command(self.address, "ST")
        text = data.decode("ascii").strip()
        try:
            letter = self._set_and_read_error(data, retry=True)
        except (DeviceTimeoutError, ProtocolError) as exc:
            log.warning("%s: no TE after %s: %s", self.name, text, exc.detail)
            return
        if letter != "@":
            log.info("%s: %s answered TE %s (%s)", self.name, text, letter, decode_te(letter))

    def enable(self) -> None:
        """``MM1``: leave DISABLE (e.g. after a following error); clears the latched error."""
        self.send("MM", 1)

    def disable(self) -> None:
        """``MM0``: motor off (DISABLE state), the position stays referenced."""
        self.send("MM", 0)

    def reset(self) -> None:
        """``RS``: reboot the controller; it comes back NOT REFERENCED and must be homed."""
        with self.transport.lock:
            self._write("RS")
            self._resync = True
        self.position_known = False
        self._profile_sent = False

    def _apply_profile(self) -> None:
        """Send the configured speed and acceleration once (the move timeouts assume them)."""
        if self._profile_sent:
            return
        self.send("VA", self.speed)
        self.send("AC", self.config.accel)
        self._profile_sent = True

    def _send_speed(self, speed: float) -> None:
        """``VA``: the velocity of the next moves (accepted when not moving)."""
        self.send("VA", speed)

    def home(self) -> None:
        """``OR`` from NOT REFERENCED and wait for READY; DISABLE is re-enabled instead.

        The SMC100 only homes from NOT REFERENCED; an axis already READY is referenced
        and is left alone (re-homing needs ``reset()`` first). A link error on the way
        stops the stage before it is raised.
        """
        try:
            self._home()
        except (DeviceTimeoutError, ProtocolError):
            self._stop_quietly()
            raise

    def _home(self) -> None:
        cfg = self.config
        ts = self._status_raw()
        fam = ts.family
        if fam == DISABLE:
            log.info("%s: %s; enabling (MM1) instead of homing", self.name, ts.state_name)
            self.enable()
            ts = self._status_raw()
            fam = ts.family
        if fam in (MOVING, JOGGING):
            self.stop()
            ts = self._status_raw()
            fam = ts.family
        if fam == READY:
            self.position_known = True
            return
        if fam == NOT_REFERENCED:
            self.send("OR")
        elif fam != HOMING:
            raise DeviceFault(f"cannot home from state {ts.state_name} "
                              f"({'; '.join(ts.error_messages) or 'no positioner error'})",
                              device=self.name, port=self.port, command=self._cmd_text("OR"))
        timeout = cfg.home_timeout_s / max(cfg.time_scale, 1e-9)

        def homed() -> bool:
            ts = self._status_raw()
            if ts.family == READY:
                return True
            if ts.family != HOMING:
                raise DeviceFault(f"homing failed: {ts.state_name}"
                                  + (f" ({'; '.join(ts.error_messages)})"
                                     if ts.error_messages else ""),
                                  device=self.name, port=self.port,
                                  command=self._cmd_text("OR"))
            return False

        # on a timeout home() stops the stage
        self.poll_until(homed, timeout, command=self._cmd_text("OR"), stop_on_timeout=False,
                        timeout_message=f"homing did not finish within {timeout:.1f} s")
        self.position_known = True
        self._apply_profile()

    def _start_move(self, target: float) -> None:
        """``PA``; a refusal stored for ``TE`` is raised with its decoded meaning.

        When the ``TE`` that acknowledges the ``PA`` is lost or garbled, the controller is
        asked what happened instead of giving up (``_move_was_accepted``): the move goes on
        when it was taken as commanded, the absolute move is sent once more when it was
        not, and anything else raises with the state that was found.
        """
        self._apply_profile()
        data = format_command(self.address, "PA", target)
        sent = data.decode("ascii").strip()
        for attempt in (1, 2):
            try:
                letter = self._set_and_read_error(data)
            except (DeviceTimeoutError, ProtocolError) as exc:
                if not self.transport.is_open:
                    raise
                if self._move_was_accepted(target, sent, exc):
                    return
                if attempt == 2:
                    raise
                log.warning("%s: %s was not taken (its TE check was unreadable: %s); "
                            "sending the absolute move once more", self.name, sent, exc.detail)
                continue
            if letter != "@":
                raise self._error_for(letter, sent)
            return

    def _move_was_accepted(self, target: float, sent: str, exc: DeviceError) -> bool:
        """After an unreadable acknowledgement of ``sent``: True when the controller is
        moving to (or has reached) ``target``, False when it is idle elsewhere (the move
        was not taken and may be re-issued: an absolute move is idempotent). Raises when
        the state cannot be read or is unsafe (a fault, a limit, moving somewhere else).

        ``TH`` is the profile generator's set-point: during a move it lies between the
        position (``TP``) and the target, at the end it is the target."""
        try:
            ts = self._status_raw()
            setpoint = self.target()
            here = self.position()
        except (DeviceTimeoutError, ProtocolError) as exc2:
            raise type(exc)(f"{exc.detail}, and the controller's state could not be read: "
                            f"{exc2.detail} to {exc2.command}", device=self.name,
                            port=self.port, command=exc.command) from exc
        st = ts_to_status(ts)
        found = (f"state {ts.state_name} (TS {ts.raw}), set-point {setpoint:.6g}, position "
                 f"{here:.6g} {self.config.units}")
        if st.fault or st.stalled or st.at_limit or ts.family not in (MOVING, READY):
            raise DeviceFault(f"{exc.detail}, and the controller reports {found}: "
                              f"{'; '.join(st.messages[1:]) or 'not ready to move'}",
                              device=self.name, port=self.port, command=sent) from exc
        band = self.config.deadband
        toward = (ts.family == MOVING and (setpoint - here) * (target - here) >= -band * band
                  and abs(setpoint - here) <= abs(target - here) + band)
        if abs(setpoint - target) <= band or toward:
            log.warning("%s: the TE check of %s was unreadable (%s); the controller reports "
                        "%s: the move was accepted", self.name, sent, exc.detail, found)
            return True
        if ts.family == MOVING:
            raise ProtocolError(f"{exc.detail}, and the controller is moving to "
                                f"{setpoint:.6g}, not to "
                                f"{target:.6g} {self.config.units}",
                                device=self.name, port=self.port, command=sent) from exc
        return False

    def _move_and_wait(self, target: float, start: float) -> None:
        # The base class stops the axis on faults it detects itself. A lost or garbled
        # reply (e.g. the TE after PA, when the move may well have started) must not leave
        # the stage running either: stop it, then report the link error.
        try:
            super()._move_and_wait(target, start)
        except (DeviceTimeoutError, ProtocolError):
            self._stop_quietly()
            raise

    def _stop_quietly(self) -> None:
        """Best-effort stop after a link error (the original error is what gets raised)."""
        try:
            self.stop()
        except DeviceError as exc:
            log.warning("%s: could not stop after a link error: %s", self.name, exc.detail)


def make_axes(controller: ControllerConfig, time_scale: float = 1.0, *,
              clock: Clock | None = None) -> list[Smc100Axis]:
    """The axes of one SMC100 chain, all sharing one transport on the controller's port."""
    if controller.protocol != "smc100":
        raise ValueError(f"controller {controller.name}: protocol {controller.protocol!r} "
                         "is not smc100")
    addresses = [a.address for a in controller.axes]
    if len(set(addresses)) != len(addresses):
        raise ValueError(f"controller {controller.name}: duplicate SMC100 addresses "
                         f"{addresses}")
    transport = SerialTransport(controller.port, device=controller.name,
                                baudrate=controller.baudrate or BAUDRATE,
                                timeout_s=controller.reply_timeout_s, xonxoff=True)
    return [Smc100Axis(ax.model_copy(update={"time_scale": time_scale}), transport,
                       name=ax.role, clock=clock)
            for ax in controller.axes]
