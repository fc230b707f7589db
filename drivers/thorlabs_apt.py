"""Thorlabs APT binary protocol: codec, stage scales, and the ``AptAxis`` driver.

Written from the Thorlabs "APT Controllers Host-Controller Communications Protocol"
(issues 15-25) and checked against well-used open implementations (pylablib's kinesis
module, thorlabs-apt-protocol). Targets the KDC101 K-cube DC servo driver (MTS25-Z8,
MTS50-Z8, PRM1-Z8 stages) and the K10CR1 integrated stepper rotation mount.

Wire format: every message starts with a 6-byte little-endian header ``u16 id`` followed
either by two ``u8`` parameters (header-only message) or by a ``u16`` data length, with the
destination byte OR 0x80 flagging that a data packet of that length follows; then ``u8``
destination and ``u8`` source. The host is 0x01, a USB stand-alone controller 0x50.

The link is not strictly request/reply: MOVE_COMPLETED, MOVE_HOMED, MOVE_STOPPED and (when
enabled) periodic status updates arrive whenever the controller has them, so the reader
frames every message by its header, hands the awaited reply back by id and records the
unsolicited ones. A header that is not a known controller-to-host message is garbage: the
link is drained and ``ProtocolError`` raised; such bytes are never parsed as a value.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag

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
# a read is asked at most this often after lost or corrupt replies (two in a row pass)
READ_ATTEMPTS = 3

# ---- addresses ------------------------------------------------------------------------
HOST = 0x01
RACK = 0x11
USB_CONTROLLER = 0x50  # a stand-alone USB unit (K-cube, T-cube, K10CR1)
DATA_FLAG = 0x80
HEADER_LEN = 6
BAUDRATE = 115200

_HEADER_SHORT = struct.Struct("<HBBBB")  # id, param1, param2, dest, source
_HEADER_DATA = struct.Struct("<HHBB")  # id, data length, dest | 0x80, source


class Msg(IntEnum):
    """Message ids used here (names without the MGMSG_ prefix)."""

    HW_DISCONNECT = 0x0002
    HW_REQ_INFO = 0x0005
    HW_GET_INFO = 0x0006
    HW_START_UPDATEMSGS = 0x0011
    HW_STOP_UPDATEMSGS = 0x0012
    HW_NO_FLASH_PROGRAMMING = 0x0018
    HW_RESPONSE = 0x0080
    HW_RICHRESPONSE = 0x0081
    MOD_SET_CHANENABLESTATE = 0x0210
    MOD_REQ_CHANENABLESTATE = 0x0211
    MOD_GET_CHANENABLESTATE = 0x0212
    MOD_IDENTIFY = 0x0223
    MOT_SET_ENCCOUNTER = 0x0409
    MOT_REQ_ENCCOUNTER = 0x040A
    MOT_GET_ENCCOUNTER = 0x040B
    MOT_SET_POSCOUNTER = 0x0410
    MOT_REQ_POSCOUNTER = 0x0411
    MOT_GET_POSCOUNTER = 0x0412
    MOT_SET_VELPARAMS = 0x0413
    MOT_REQ_VELPARAMS = 0x0414
    MOT_GET_VELPARAMS = 0x0415
    MOT_SET_JOGPARAMS = 0x0416
    MOT_REQ_JOGPARAMS = 0x0417
    MOT_GET_JOGPARAMS = 0x0418
    MOT_REQ_STATUSBITS = 0x0429
    MOT_GET_STATUSBITS = 0x042A
    MOT_SET_HOMEPARAMS = 0x0440
    MOT_REQ_HOMEPARAMS = 0x0441
    MOT_GET_HOMEPARAMS = 0x0442
    MOT_MOVE_HOME = 0x0443
    MOT_MOVE_HOMED = 0x0444
    MOT_MOVE_RELATIVE = 0x0448
    MOT_MOVE_ABSOLUTE = 0x0453
    MOT_MOVE_VELOCITY = 0x0457
    MOT_MOVE_COMPLETED = 0x0464
    MOT_MOVE_STOP = 0x0465
    MOT_MOVE_STOPPED = 0x0466
    MOT_MOVE_JOG = 0x046A
    MOT_REQ_STATUSUPDATE = 0x0480
    MOT_GET_STATUSUPDATE = 0x0481
    MOT_REQ_DCSTATUSUPDATE = 0x0490
    MOT_GET_DCSTATUSUPDATE = 0x0491
    MOT_ACK_DCSTATUSUPDATE = 0x0492


# Controller-to-host messages we accept: id -> data length (None = header-only). Anything
# else in a header position is garbage (or a message we never ask for) and triggers resync.
INCOMING: dict[int, int | None] = {
    Msg.HW_DISCONNECT: None,
    Msg.HW_GET_INFO: 84,
    Msg.HW_RESPONSE: None,
    Msg.HW_RICHRESPONSE: 68,
    Msg.MOD_GET_CHANENABLESTATE: None,
    Msg.MOT_GET_ENCCOUNTER: 6,
    Msg.MOT_GET_POSCOUNTER: 6,
    Msg.MOT_GET_VELPARAMS: 14,
    Msg.MOT_GET_JOGPARAMS: 22,
    Msg.MOT_GET_STATUSBITS: 6,
    Msg.MOT_GET_HOMEPARAMS: 14,
    Msg.MOT_MOVE_HOMED: None,
    Msg.MOT_MOVE_COMPLETED: 14,
    Msg.MOT_MOVE_STOPPED: 14,
    Msg.MOT_GET_STATUSUPDATE: 14,
    Msg.MOT_GET_DCSTATUSUPDATE: 14,
}

STOP_IMMEDIATE = 0x01
STOP_PROFILED = 0x02
CHAN_ENABLED = 0x01
CHAN_DISABLED = 0x02


def channel_ident(channel: int) -> int:
    """Channel number (1-4) -> the bit mask MOD_*_CHANENABLESTATE and MOD_IDENTIFY use."""
    if not 1 <= channel <= 4:
        raise ValueError(f"APT channel {channel} out of range 1..4")
    return 1 << (channel - 1)


# ---- messages -------------------------------------------------------------------------
@dataclass(frozen=True)
class AptMessage:
    """One framed message. ``data`` is None for header-only messages."""

    msg_id: int
    dest: int
    source: int
    param1: int = 0
    param2: int = 0
    data: bytes | None = None

    @property
    def name(self) -> str:
        try:
            return Msg(self.msg_id).name
        except ValueError:
            return f"0x{self.msg_id:04X}"


def pack_short(msg_id: int, param1: int = 0, param2: int = 0, *, dest: int = USB_CONTROLLER,
               source: int = HOST) -> bytes:
    """A header-only message with its two parameter bytes."""
    return _HEADER_SHORT.pack(msg_id, param1 & 0xFF, param2 & 0xFF, dest & 0x7F, source)


def pack_data(msg_id: int, data: bytes, *, dest: int = USB_CONTROLLER,
              source: int = HOST) -> bytes:
    """A header with the data-packet flag (dest | 0x80) followed by ``data``."""
    if len(data) > 0xFFFF:
        raise ValueError("APT data packet longer than 65535 bytes")
    return _HEADER_DATA.pack(msg_id, len(data), (dest & 0x7F) | DATA_FLAG, source) + data


def pack_message(msg: AptMessage) -> bytes:
    if msg.data is None:
        return pack_short(msg.msg_id, msg.param1, msg.param2, dest=msg.dest, source=msg.source)
    return pack_data(msg.msg_id, msg.data, dest=msg.dest, source=msg.source)


@dataclass(frozen=True)
class Header:
    msg_id: int
    dest: int  # without the data flag
    source: int
    data_len: int | None  # None: header-only
    param1: int = 0
    param2: int = 0


def unpack_header(raw: bytes) -> Header:
    """Split a 6-byte header; the data flag in the destination byte selects the layout."""
    if len(raw) != HEADER_LEN:
        raise ValueError(f"APT header must be 6 bytes, got {len(raw)}")
    if raw[4] & DATA_FLAG:
        msg_id, length, dest, source = _HEADER_DATA.unpack(raw)
        return Header(msg_id, dest & 0x7F, source, length)
    msg_id, p1, p2, dest, source = _HEADER_SHORT.unpack(raw)
    return Header(msg_id, dest, source, None, p1, p2)


def unpack_message(raw: bytes) -> AptMessage:
    """A complete message (header plus data packet, if flagged) from bytes."""
    h = unpack_header(raw[:HEADER_LEN])
    if h.data_len is None:
        if len(raw) != HEADER_LEN:
            raise ValueError(f"header-only message with {len(raw) - HEADER_LEN} extra bytes")
        return AptMessage(h.msg_id, h.dest, h.source, h.param1, h.param2)
    data = raw[HEADER_LEN:]
    if len(data) != h.data_len:
        raise ValueError(f"data packet of {len(data)} bytes, header says {h.data_len}")
    return AptMessage(h.msg_id, h.dest, h.source, data=bytes(data))


# ---- payloads ---------------------------------------------------------------------------
_MOVE = struct.Struct("<Hi")  # channel, position/distance (also POSCOUNTER, ENCCOUNTER)
_STATUSBITS = struct.Struct("<HI")
_DCSTATUS = struct.Struct("<HiHHI")  # channel, position, velocity, reserved, status
_STATUSUPDATE = struct.Struct("<HiiI")  # channel, position, encoder count, status
_VELPARAMS = struct.Struct("<Hiii")  # channel, min velocity, acceleration, max velocity
_HOMEPARAMS = struct.Struct("<HHHii")  # channel, direction, limit switch, velocity, offset
_HW_INFO = struct.Struct("<I8sH4B48s10sHHHH")  # 84 bytes, stage id at 76


def pack_move(channel: int, counts: int) -> bytes:
    """MOVE_ABSOLUTE / MOVE_RELATIVE / SET_POSCOUNTER payload."""
    return _MOVE.pack(channel, counts)


def unpack_counter(data: bytes) -> tuple[int, int]:
    """GET_POSCOUNTER / GET_ENCCOUNTER: (channel, counts)."""
    return _MOVE.unpack(data)


def unpack_statusbits(data: bytes) -> tuple[int, int]:
    """GET_STATUSBITS (0x042A): (channel, status bits)."""
    return _STATUSBITS.unpack(data)


def pack_statusbits(channel: int, bits: int) -> bytes:
    return _STATUSBITS.pack(channel, bits)


@dataclass(frozen=True)
class ChannelStatus:
    """A status report: DC (0x0491, MOVE_COMPLETED/STOPPED) or stepper (0x0481) layout."""

    channel: int
    position: int
    bits: int
    velocity: int = 0  # DC layout only
    encoder: int = 0  # 0x0481 layout only


def unpack_dc_status(data: bytes) -> ChannelStatus:
    ch, pos, vel, _reserved, bits = _DCSTATUS.unpack(data)
    return ChannelStatus(ch, pos, bits, velocity=vel)


def pack_dc_status(st: ChannelStatus) -> bytes:
    return _DCSTATUS.pack(st.channel, st.position, st.velocity & 0xFFFF, 0, st.bits)


def unpack_status_update(data: bytes) -> ChannelStatus:
    ch, pos, enc, bits = _STATUSUPDATE.unpack(data)
    return ChannelStatus(ch, pos, bits, encoder=enc)


def pack_status_update(st: ChannelStatus) -> bytes:
    return _STATUSUPDATE.pack(st.channel, st.position, st.encoder, st.bits)


@dataclass(frozen=True)
class VelParams:
    channel: int
    min_velocity: int
    acceleration: int
    max_velocity: int


def pack_velparams(p: VelParams) -> bytes:
    return _VELPARAMS.pack(p.channel, p.min_velocity, p.acceleration, p.max_velocity)


def unpack_velparams(data: bytes) -> VelParams:
    return VelParams(*_VELPARAMS.unpack(data))


@dataclass(frozen=True)
class HomeParams:
    channel: int
    direction: int  # 1 forward, 2 reverse
    limit_switch: int  # 1 reverse hardware switch, 4 forward hardware switch
    velocity: int
    offset: int


def pack_homeparams(p: HomeParams) -> bytes:
    return _HOMEPARAMS.pack(p.channel, p.direction, p.limit_switch, p.velocity, p.offset)


def unpack_homeparams(data: bytes) -> HomeParams:
    return HomeParams(*_HOMEPARAMS.unpack(data))


@dataclass(frozen=True)
class HwInfo:
    """HW_GET_INFO: who the controller is."""

    serial: int
    model: str
    hw_type: int
    firmware: tuple[int, int, int]  # major, interim, minor
    notes: str
    stage_id: int  # KDC101/TDC001: the connected stage (bytes 76-77), else 0
    hw_version: int
    mod_state: int
    channels: int

    @property
    def firmware_str(self) -> str:
        return "{}.{}.{}".format(*self.firmware)


def _cstr(raw: bytes) -> str:
    return raw.split(b"\x00", 1)[0].decode("latin-1").strip()


def unpack_hw_info(data: bytes) -> HwInfo:
    (serial, model, hw_type, fw_minor, fw_interim, fw_major, _fw_unused, notes, _empty,
     stage_id, hw_version, mod_state, nch) = _HW_INFO.unpack(data)
    return HwInfo(serial, _cstr(model), hw_type, (fw_major, fw_interim, fw_minor),
                  _cstr(notes), stage_id, hw_version, mod_state, nch)


def pack_hw_info(info: HwInfo) -> bytes:
    major, interim, minor = info.firmware
    return _HW_INFO.pack(info.serial, info.model.encode("latin-1"), info.hw_type, minor,
                         interim, major, 0, info.notes.encode("latin-1"), b"", info.stage_id,
                         info.hw_version, info.mod_state, info.channels)


# ---- status bits ----------------------------------------------------------------------
class StatusBit(IntFlag):
    """Motor status bits (0x042A, 0x0481, 0x0491 and the move messages).

    The protocol document names 0x01/0x10 "CW"/forward, but KDC101 units report the
    reverse limit switch on 0x01 and motion towards it on 0x10 (pylablib, tested on
    KDC101/K10CR1; thorlabs_apt_device swaps them for the same reason). We follow the
    hardware: 0x01/0x10 are the low (reverse) side, 0x02/0x20 the high (forward) side.
    """

    HW_LIMIT_REV = 0x00000001
    HW_LIMIT_FWD = 0x00000002
    SW_LIMIT_REV = 0x00000004
    SW_LIMIT_FWD = 0x00000008
    MOVING_REV = 0x00000010
    MOVING_FWD = 0x00000020
    JOGGING_REV = 0x00000040
    JOGGING_FWD = 0x00000080
    CONNECTED = 0x00000100
    HOMING = 0x00000200
    HOMED = 0x00000400
    INITIALISING = 0x00000800
    TRACKING = 0x00001000
    SETTLED = 0x00002000
    MOTION_ERROR = 0x00004000
    INSTRUMENT_ERROR = 0x00008000
    INTERLOCK = 0x00010000
    OVERTEMP = 0x00020000
    VOLTAGE_FAULT = 0x00040000
    COMMUTATION_ERROR = 0x00080000
    CURRENT_LIMIT = 0x01000000
    ENCODER_FAULT = 0x02000000
    OVERCURRENT = 0x04000000
    CURRENT_FAULT = 0x08000000
    POWER_OK = 0x10000000
    ACTIVE = 0x20000000
    ERROR = 0x40000000
    ENABLED = 0x80000000


MOTION_BITS = (StatusBit.MOVING_REV | StatusBit.MOVING_FWD | StatusBit.JOGGING_REV
               | StatusBit.JOGGING_FWD | StatusBit.HOMING)
FAULT_BITS = (StatusBit.INSTRUMENT_ERROR | StatusBit.OVERTEMP | StatusBit.VOLTAGE_FAULT
              | StatusBit.COMMUTATION_ERROR | StatusBit.ENCODER_FAULT | StatusBit.OVERCURRENT
              | StatusBit.CURRENT_FAULT | StatusBit.ERROR)
_BIT_TEXT = {
    StatusBit.HW_LIMIT_REV: "reverse (low) hardware limit switch active",
    StatusBit.HW_LIMIT_FWD: "forward (high) hardware limit switch active",
    StatusBit.SW_LIMIT_REV: "reverse software limit reached",
    StatusBit.SW_LIMIT_FWD: "forward software limit reached",
    StatusBit.MOTION_ERROR: "motion error (excessive position error: stall or following error)",
    StatusBit.INSTRUMENT_ERROR: "instrument error",
    StatusBit.INTERLOCK: "interlock",
    StatusBit.OVERTEMP: "over temperature",
    StatusBit.VOLTAGE_FAULT: "supply voltage fault",
    StatusBit.COMMUTATION_ERROR: "commutation error",
    StatusBit.CURRENT_LIMIT: "motor current limit reached",
    StatusBit.ENCODER_FAULT: "encoder fault",
    StatusBit.OVERCURRENT: "overcurrent",
    StatusBit.CURRENT_FAULT: "supply current fault",
    StatusBit.ERROR: "controller error",
}


def decode_status(bits: int) -> AxisStatus:
    """Status bits -> the flags the procedures need, with readable messages."""
    b = StatusBit(bits & 0xFFFFFFFF)
    messages = [text for bit, text in _BIT_TEXT.items() if b & bit]
    if not b & StatusBit.ENABLED:
        messages.append("channel disabled (motor not powered)")
    if b & StatusBit.HOMING:
        messages.append("homing")
    return AxisStatus(
        moving=bool(b & MOTION_BITS),
        homed=bool(b & StatusBit.HOMED),
        limit_low=bool(b & StatusBit.HW_LIMIT_REV),
        limit_high=bool(b & StatusBit.HW_LIMIT_FWD),
        stalled=bool(b & StatusBit.MOTION_ERROR),
        fault=bool(b & FAULT_BITS),
        raw=f"0x{bits & 0xFFFFFFFF:08X}",
        messages=tuple(messages),
    )


# ---- scales -----------------------------------------------------------------------------
# Time base of the DC servo K/T-cubes (KDC101, TDC001): T = 2048 / 6e6 s. Velocity
# registers hold counts/T * 65536, acceleration registers counts/T^2 * 65536.
DC_SERVO_T = 2048 / 6e6
# Stepper cubes and the K10CR1 (KST101, TST101 family): velocity register = microsteps/s
# x 53.68, acceleration register = microsteps/s^2 x 53.68 x 204.94e-6 (about 0.0110).
STEPPER_VEL = 53.68
STEPPER_ACC = 53.68 * 204.94e-6

CONTROLLER_KIND = {"KDC101": "dc", "TDC001": "dc", "K10CR1": "stepper", "KST101": "stepper",
                   "TST101": "stepper"}


@dataclass(frozen=True)
class StageScale:
    """Encoder/microstep counts per interface unit of a stage, and its catalogue limits."""

    name: str
    units: str  # "mm" | "deg"
    counts_per_unit: float
    controller: str  # model of the controller that drives it normally
    max_speed: float  # units/s
    max_accel: float  # units/s^2


STAGES: dict[str, StageScale] = {
    # Z8 DC servo stages: 512-line encoder x 67:1 gearbox on a 1 mm lead screw.
    "MTS25-Z8": StageScale("MTS25-Z8", "mm", 34304.0, "KDC101", 2.4, 4.5),
    "MTS50-Z8": StageScale("MTS50-Z8", "mm", 34304.0, "KDC101", 2.4, 4.5),
    "PRM1-Z8": StageScale("PRM1-Z8", "deg", 1919.6418578623391, "KDC101", 25.0, 25.0),
    # K10CR1: 200 steps x 2048 microsteps per motor turn, 120:1 worm gear.
    "K10CR1": StageScale("K10CR1", "deg", 409600 / 3, "K10CR1", 10.0, 20.0),
}
# Stage ids a KDC101/TDC001 reports in HW_GET_INFO bytes 76-77.
STAGE_IDS = {2: "Z706", 3: "Z712", 4: "Z725", 5: "CR1-Z7", 6: "PRM1-Z8", 7: "MTS25-Z8",
             8: "MTS50-Z8", 9: "Z825", 10: "Z812", 11: "Z806"}


def stage_scale(stage: str) -> StageScale:
    key = stage.strip().upper().replace("/M", "")
    if key not in STAGES:
        raise ValueError(f"unknown Thorlabs stage {stage!r}; known: "
                         f"{', '.join(sorted(STAGES))}")
    return STAGES[key]


def _kind(controller_model: str) -> str:
    kind = CONTROLLER_KIND.get(controller_model.upper())
    if kind is None:
        raise ValueError(f"no velocity scaling known for APT controller {controller_model!r}")
    return kind


def velocity_to_register(v: float, counts_per_unit: float, controller_model: str) -> int:
    """Units/s -> the controller's velocity register value."""
    counts = v * counts_per_unit
    if _kind(controller_model) == "dc":
        return round(counts * DC_SERVO_T * 65536)
    return round(counts * STEPPER_VEL)


def register_to_velocity(reg: int, counts_per_unit: float, controller_model: str) -> float:
    if _kind(controller_model) == "dc":
        return reg / (DC_SERVO_T * 65536) / counts_per_unit
    return reg / STEPPER_VEL / counts_per_unit


def accel_to_register(a: float, counts_per_unit: float, controller_model: str) -> int:
    """Units/s^2 -> the controller's acceleration register value."""
    counts = a * counts_per_unit
    if _kind(controller_model) == "dc":
        return round(counts * DC_SERVO_T**2 * 65536)
    return round(counts * STEPPER_ACC)


def register_to_accel(reg: int, counts_per_unit: float, controller_model: str) -> float:
    if _kind(controller_model) == "dc":
        return reg / (DC_SERVO_T**2 * 65536) / counts_per_unit
    return reg / STEPPER_ACC / counts_per_unit


# ---- the link ---------------------------------------------------------------------------
@dataclass
class ChannelEvents:
    """What unsolicited messages told us about one channel."""

    homed: int = 0  # MOVE_HOMED count
    completed: int = 0  # MOVE_COMPLETED count
    stopped: int = 0  # MOVE_STOPPED count
    last: ChannelStatus | None = None  # most recent status carried by any message
    updates: int = 0  # periodic status updates seen


@dataclass
class _LinkState:
    events: dict[int, ChannelEvents] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)  # HW_RESPONSE / HW_RICHRESPONSE texts


class AptLink:
    """One serial port to an APT controller, shared by the channels (axes) it drives.

    Owns framing: ``request`` writes a command and reads messages until the awaited reply,
    recording unsolicited ones; a bad header drains the port and raises ``ProtocolError``.
    """

    def __init__(self, url: str, *, device: str, baudrate: int = BAUDRATE,
                 reply_timeout_s: float = 0.5, dest: int = USB_CONTROLLER,
                 transport: SerialTransport | None = None) -> None:
        self.transport = transport or SerialTransport(url, device=device, baudrate=baudrate,
                                                      timeout_s=reply_timeout_s, rtscts=True)
        self.device = device
        self.dest = dest
        self.reply_timeout_s = reply_timeout_s
        self.state = _LinkState()
        self.info: HwInfo | None = None
        self._users = 0
        self._lock = threading.RLock()
        self._last_ack = 0.0
        # After a timed-out request its reply may still come: until then, messages already
        # waiting are read (and recorded as unsolicited) before each new request is sent.
        self._late_until = 0.0
        # Reply ids of timed-out requests: a late one of the same id as a new request would
        # pass for its answer (APT has no sequence numbers), so that request syncs first.
        self._late_ids: set[int] = set()
        self._syncing = False

    @property
    def url(self) -> str:
        return self.transport.url

    # ---- life cycle ------------------------------------------------------------------
    def open(self) -> None:
        """Open on first use: purge, claim the link, stop update messages, read HW info."""
        with self._lock:
            self._users += 1
            if self._users > 1 and self.transport.is_open:
                return
            try:
                self.transport.open()
                self.transport.drain()
                # Tells units that would otherwise write settings to flash on start-up not
                # to; units it does not apply to ignore it.
                self.send(pack_short(Msg.HW_NO_FLASH_PROGRAMMING, dest=self.dest),
                          "HW_NO_FLASH_PROGRAMMING")
                # We poll; periodic updates from an earlier session would only add traffic.
                self.send(pack_short(Msg.HW_STOP_UPDATEMSGS, dest=self.dest),
                          "HW_STOP_UPDATEMSGS")
                self.info = self.read_info()
            except DeviceError:
                self._users -= 1
                self.transport.close()
                raise

    def close(self) -> None:
        with self._lock:
            self._users = max(0, self._users - 1)
            if self._users == 0:
                self.transport.close()

    def read_info(self) -> HwInfo:
        """HW_REQ_INFO, asked again (at most ``READ_ATTEMPTS`` times) after a lost or
        corrupt reply."""
        raw = pack_short(Msg.HW_REQ_INFO, dest=self.dest)
        for _ in range(READ_ATTEMPTS - 1):
            try:
                return self._info_from(self.request(raw, Msg.HW_GET_INFO, "HW_REQ_INFO"))
            except (DeviceTimeoutError, ProtocolError) as exc:
                if not self.transport.is_open:
                    raise
                log.warning("%s: %s; asking again", self.device, exc.detail)
        return self._info_from(self.request(raw, Msg.HW_GET_INFO, "HW_REQ_INFO"))

    @staticmethod
    def _info_from(reply: AptMessage) -> HwInfo:
        assert reply.data is not None
        return unpack_hw_info(reply.data)

    # ---- I/O -------------------------------------------------------------------------
    def events(self, channel: int) -> ChannelEvents:
        return self.state.events.setdefault(channel, ChannelEvents())

    def send(self, raw: bytes, command: str) -> None:
        with self._lock:
            self.transport.write(raw, command=command)

    def request(self, raw: bytes, reply_id: int, command: str,
                channel: int | None = None) -> AptMessage:
        """Send ``raw`` and return the reply with ``reply_id`` (and ``channel``, if given)."""
        with self._lock:
            if time.monotonic() < self._late_until:
                self.pump(command=command)
            if reply_id in self._late_ids and not self._syncing:
                self._sync(command)
            self.transport.write(raw, command=command)
            deadline = time.monotonic() + self.reply_timeout_s
            while True:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self.transport.drain()
                    self._late_ids.add(reply_id)
                    self._late_until = time.monotonic() + 10 * self.reply_timeout_s
                    raise DeviceTimeoutError(f"no {Msg(reply_id).name} reply",
                                             device=self.device, port=self.url,
                                             command=command)
                try:
                    msg = self.read_message(remaining, command)
                except DeviceTimeoutError as exc:
                    self._late_ids.add(reply_id)
                    self._late_until = time.monotonic() + 10 * self.reply_timeout_s
                    raise DeviceTimeoutError(
                        f"no {Msg(reply_id).name} reply within {self.reply_timeout_s:g} s",
                        device=self.device, port=self.url, command=command) from exc
                if msg.msg_id == reply_id:
                    got = _reply_channel(msg)
                    if channel is not None and got is not None and got != channel:
                        self.transport.drain()
                        raise ProtocolError(f"{msg.name} for channel {got}, expected channel "
                                            f"{channel}", device=self.device, port=self.url,
                                            command=command)
                    return msg
                self._unsolicited(msg)

    def _sync(self, command: str) -> None:
        """Make sure no reply owed to a timed-out request is still on its way.

        The controller answers in order, so once the reply to a request of another id
        arrives, every earlier reply has arrived too (and was recorded as unsolicited).
        """
        if Msg.HW_GET_INFO not in self._late_ids:
            raw, reply_id, name = (pack_short(Msg.HW_REQ_INFO, dest=self.dest),
                                   Msg.HW_GET_INFO, "HW_REQ_INFO")
        else:
            raw, reply_id, name = (pack_short(Msg.MOT_REQ_STATUSBITS, 1, dest=self.dest),
                                   Msg.MOT_GET_STATUSBITS, "MOT_REQ_STATUSBITS")
        log.info("%s: resynchronising with %s before %s (a reply may be late)", self.device,
                 name, command)
        self._syncing = True
        try:
            self.request(raw, reply_id, f"{name} (resync before {command})")
        finally:
            self._syncing = False
        self._late_ids.clear()

    def pump(self, timeout_s: float = 0.0, command: str = "read") -> int:
        """Read and record messages that are already waiting (or arrive within timeout)."""
        n = 0
        with self._lock:
            while True:
                try:
                    first = self.transport.read_exact(1, timeout_s=max(timeout_s, 0.001),
                                                      command=command)
                except DeviceTimeoutError:
                    return n
                self._unsolicited(self._read_rest(first, command))
                n += 1
                timeout_s = 0.0

    def read_message(self, timeout_s: float, command: str) -> AptMessage:
        """Frame one message by its header; resynchronise and raise on garbage."""
        try:
            first = self.transport.read_exact(1, timeout_s=timeout_s, command=command)
        except DeviceTimeoutError:
            self.transport.drain()
            raise
        return self._read_rest(first, command)

    def _read_rest(self, first: bytes, command: str) -> AptMessage:
        try:
            raw = first + self.transport.read_exact(HEADER_LEN - 1, command=command)
        except DeviceTimeoutError as exc:
            self.transport.drain()
            raise ProtocolError(f"truncated APT header: {exc.detail}", device=self.device,
                                port=self.url, command=command) from exc
        h = unpack_header(raw)
        problem = self._header_problem(h)
        if problem:
            junk = self.transport.drain()
            raise ProtocolError(f"bad APT header {raw.hex(' ')} ({problem}); discarded "
                                f"{len(junk)} more bytes to resynchronise",
                                device=self.device, port=self.url, command=command)
        if h.data_len is None:
            return AptMessage(h.msg_id, h.dest, h.source, h.param1, h.param2)
        try:
            data = self.transport.read_exact(h.data_len, command=command)
        except DeviceTimeoutError as exc:
            self.transport.drain()
            raise ProtocolError(f"truncated {Msg(h.msg_id).name} data packet: {exc.detail}",
                                device=self.device, port=self.url, command=command) from exc
        return AptMessage(h.msg_id, h.dest, h.source, data=data)

    def _header_problem(self, h: Header) -> str:
        if h.msg_id not in INCOMING:
            return f"unknown message id 0x{h.msg_id:04X}"
        if h.source != self.dest:
            return f"source 0x{h.source:02X}, expected controller 0x{self.dest:02X}"
        if h.dest != HOST:
            return f"destination 0x{h.dest:02X}, expected host 0x{HOST:02X}"
        expected = INCOMING[h.msg_id]
        if expected != h.data_len:
            want = "header-only" if expected is None else f"{expected} data bytes"
            got = "header-only" if h.data_len is None else f"{h.data_len} data bytes"
            return f"{Msg(h.msg_id).name} must be {want}, header says {got}"
        return ""

    def _unsolicited(self, msg: AptMessage) -> None:
        """Record a message nobody is waiting for (or a reply that came too late)."""
        mid = msg.msg_id
        if mid == Msg.MOT_MOVE_HOMED:
            self.events(msg.param1).homed += 1
        elif mid in (Msg.MOT_MOVE_COMPLETED, Msg.MOT_MOVE_STOPPED,
                     Msg.MOT_GET_DCSTATUSUPDATE, Msg.MOT_GET_STATUSUPDATE):
            assert msg.data is not None
            # Steppers (K10CR1) send MOVE_COMPLETED/STOPPED in the 0x0481 layout; channel,
            # position and status sit at the same offsets in both 14-byte layouts.
            st = (unpack_status_update(msg.data) if mid == Msg.MOT_GET_STATUSUPDATE
                  else unpack_dc_status(msg.data))
            ev = self.events(st.channel)
            ev.last = st
            if mid == Msg.MOT_MOVE_COMPLETED:
                ev.completed += 1
            elif mid == Msg.MOT_MOVE_STOPPED:
                ev.stopped += 1
            else:
                ev.updates += 1
                # Periodic updates keep coming only while the host acknowledges them
                # (about once a second is what vendor software does).
                now = time.monotonic()
                if now - self._last_ack > 0.5:
                    self._last_ack = now
                    self.transport.write(pack_short(Msg.MOT_ACK_DCSTATUSUPDATE,
                                                    dest=self.dest),
                                         command="MOT_ACK_DCSTATUSUPDATE")
        elif mid in (Msg.HW_RESPONSE, Msg.HW_RICHRESPONSE):
            text = "controller reported an error (HW_RESPONSE)"
            if msg.data is not None:
                ref, code = struct.unpack_from("<HH", msg.data)
                text = (f"controller error {code} on message 0x{ref:04X}: "
                        f"{_cstr(msg.data[4:])}")
            log.warning("%s: %s", self.device, text)
            self.state.errors.append(text)
        elif mid == Msg.HW_DISCONNECT:
            log.warning("%s: controller announced HW_DISCONNECT", self.device)
            self.state.errors.append("controller announced HW_DISCONNECT")
        else:
            log.debug("%s: ignoring late or unsolicited %s", self.device, msg.name)


def _reply_channel(msg: AptMessage) -> int | None:
    """The channel a reply is about, where its layout carries one."""
    if msg.data is not None and msg.msg_id != Msg.HW_GET_INFO and len(msg.data) >= 2:
        return int(struct.unpack_from("<H", msg.data)[0])
    if msg.msg_id == Msg.MOD_GET_CHANENABLESTATE:
        return {1: 1, 2: 2, 4: 3, 8: 4}.get(msg.param1)
    return None


# ---- the driver -------------------------------------------------------------------------
class AptAxis(Axis):
    """One channel of a Thorlabs APT motor controller (KDC101, K10CR1, ...).

    ``config.address`` is the channel (1 for single-channel cubes), ``config.stage`` the
    stage model that sets the counts per unit (MTS25-Z8, MTS50-Z8, PRM1-Z8, K10CR1).
    """

    def __init__(self, config: AxisConfig, link: AptLink, name: str | None = None, *,
                 clock: Clock | None = None) -> None:
        super().__init__(config, name, clock=clock)
        self.link = link
        self.channel = config.address
        channel_ident(self.channel)  # validates
        stage = config.stage or ("K10CR1" if config.units == "deg" else "MTS25-Z8")
        self.scale = stage_scale(stage)
        if self.scale.units != config.units:
            raise ValueError(f"stage {stage} moves in {self.scale.units}, axis {self.name} is "
                             f"configured in {config.units}")
        self._connected = False
        self._identity: Identity | None = None

    # ---- helpers ---------------------------------------------------------------------
    @property
    def port(self) -> str:
        return self.link.url

    @property
    def model(self) -> str:
        return self.link.info.model if self.link.info else self.scale.controller

    def _counts(self, value: float) -> int:
        counts = round(value * self.scale.counts_per_unit)
        if not -(2**31) <= counts < 2**31:
            raise LimitError(f"{value:g} {self.config.units} does not fit the 32-bit counter",
                             device=self.name, port=self.port)
        return counts

    def _units(self, counts: int) -> float:
        return counts / self.scale.counts_per_unit

    def _require_connected(self, command: str) -> None:
        if not self._connected:
            raise TransportError("axis is not connected", device=self.name, port=self.port,
                                 command=command)

    def _request(self, raw: bytes, reply_id: int, command: str) -> AptMessage:
        """A read request, asked again (at most ``READ_ATTEMPTS`` times) after a lost or
        corrupt reply: reads are idempotent, and the link keeps a late earlier answer from
        passing for a later one."""
        self._require_connected(command)
        for _ in range(READ_ATTEMPTS - 1):
            try:
                return self.link.request(raw, reply_id, command, channel=self.channel)
            except (DeviceTimeoutError, ProtocolError) as exc:
                if not self.link.transport.is_open:
                    raise
                log.warning("%s: %s; asking again", self.name, exc.detail)
        return self.link.request(raw, reply_id, command, channel=self.channel)

    # ---- life cycle --------------------------------------------------------------------
    def connect(self) -> None:
        if self._connected:
            return
        self.link.open()
        self._connected = True
        try:
            info = self.link.info
            assert info is not None
            self._identity = self._make_identity(info)
            self._enable_channel()
            self._set_velocity(self.speed, self.config.accel)
            st = self.status()
            self.position_known = st.homed
        except BaseException:
            self._connected = False
            self.link.close()
            raise
        log.info("%s: connected to %s s/n %s (%s) on %s, channel %d, %s", self.name,
                 self._identity.model, self._identity.serial, self._identity.stage, self.port,
                 self.channel, "homed" if self.position_known else "not homed")

    def close(self) -> None:
        if not self._connected:
            return
        self._connected = False
        self.position_known = False
        self.link.close()

    def _make_identity(self, info: HwInfo) -> Identity:
        if info.model not in CONTROLLER_KIND:
            raise DeviceFault(f"unsupported APT controller model {info.model!r}",
                              device=self.name, port=self.port, command="HW_REQ_INFO")
        reported = "K10CR1" if info.model == "K10CR1" else STAGE_IDS.get(info.stage_id, "")
        if reported and reported in STAGES and \
                STAGES[reported].counts_per_unit != self.scale.counts_per_unit:
            raise DeviceFault(f"controller reports stage {reported} but the config says "
                              f"{self.scale.name}: positions would be scaled wrongly",
                              device=self.name, port=self.port, command="HW_REQ_INFO")
        return Identity(vendor="Thorlabs", model=info.model, serial=str(info.serial),
                        firmware=info.firmware_str, stage=reported or self.scale.name)

    def _enable_channel(self) -> None:
        ident = channel_ident(self.channel)
        reply = self._request(pack_short(Msg.MOD_REQ_CHANENABLESTATE, ident,
                                         dest=self.link.dest),
                              Msg.MOD_GET_CHANENABLESTATE, "MOD_REQ_CHANENABLESTATE")
        if reply.param2 == CHAN_ENABLED:
            return
        log.info("%s: enabling channel %d", self.name, self.channel)
        self.link.send(pack_short(Msg.MOD_SET_CHANENABLESTATE, ident, CHAN_ENABLED,
                                  dest=self.link.dest), "MOD_SET_CHANENABLESTATE")
        reply = self._request(pack_short(Msg.MOD_REQ_CHANENABLESTATE, ident,
                                         dest=self.link.dest),
                              Msg.MOD_GET_CHANENABLESTATE, "MOD_REQ_CHANENABLESTATE")
        if reply.param2 != CHAN_ENABLED:
            raise DeviceFault(f"channel {self.channel} stays disabled after "
                              "MOD_SET_CHANENABLESTATE", device=self.name, port=self.port,
                              command="MOD_SET_CHANENABLESTATE")

    def _set_velocity(self, speed: float, accel: float) -> None:
        """Write the configured trapezoid (clamped to the stage) so move timeouts hold."""
        s = self.scale
        if speed > s.max_speed or accel > s.max_accel:
            log.warning("%s: speed %g / accel %g above %s limits %g / %g; clamped", self.name,
                        speed, accel, s.name, s.max_speed, s.max_accel)
        speed, accel = min(speed, s.max_speed), min(accel, s.max_accel)
        params = VelParams(self.channel, 0,
                           accel_to_register(accel, s.counts_per_unit, self.model),
                           velocity_to_register(speed, s.counts_per_unit, self.model))
        self.link.send(pack_data(Msg.MOT_SET_VELPARAMS, pack_velparams(params),
                                 dest=self.link.dest), "MOT_SET_VELPARAMS")
        got = self.velocity_params()
        if (got.acceleration, got.max_velocity) != (params.acceleration, params.max_velocity):
            raise DeviceFault(f"velocity parameters not taken: wrote {params}, read {got}",
                              device=self.name, port=self.port, command="MOT_SET_VELPARAMS")

    def _send_speed(self, speed: float) -> None:
        """``MOT_SET_VELPARAMS`` with the configured acceleration, read back."""
        self._set_velocity(speed, self.config.accel)

    def velocity_params(self) -> VelParams:
        reply = self._request(pack_short(Msg.MOT_REQ_VELPARAMS, self.channel,
                                         dest=self.link.dest),
                              Msg.MOT_GET_VELPARAMS, "MOT_REQ_VELPARAMS")
        assert reply.data is not None
        return unpack_velparams(reply.data)

    # ---- Axis primitives ---------------------------------------------------------------
    def identify(self) -> Identity:
        self._require_connected("HW_REQ_INFO")
        info = self.link.read_info()
        self._identity = self._make_identity(info)
        return self._identity

    def flash_led(self) -> None:
        """MOD_IDENTIFY: blink the controller's front panel, to find it on the bench."""
        self._require_connected("MOD_IDENTIFY")
        self.link.send(pack_short(Msg.MOD_IDENTIFY, channel_ident(self.channel),
                                  dest=self.link.dest), "MOD_IDENTIFY")

    def status_bits(self) -> int:
        """The status word, by REQ_STATUSBITS.

        Not by REQ_DCSTATUSUPDATE/REQ_STATUSUPDATE: when update messages are on (another
        program may have started them), their replies cannot be told from the periodic
        updates, and a stale update would read as "not moving" right after a move starts.
        GET_STATUSBITS never arrives unsolicited, so its reply is always ours.
        """
        reply = self._request(pack_short(Msg.MOT_REQ_STATUSBITS, self.channel,
                                         dest=self.link.dest),
                              Msg.MOT_GET_STATUSBITS, "MOT_REQ_STATUSBITS")
        assert reply.data is not None
        return unpack_statusbits(reply.data)[1]

    def status(self) -> AxisStatus:
        st = decode_status(self.status_bits())
        errors = self.link.state.errors
        if errors:  # the controller reported an error since the last look: surface it once
            msgs, errors[:] = tuple(errors), []
            st = AxisStatus(moving=st.moving, homed=st.homed, limit_low=st.limit_low,
                            limit_high=st.limit_high, stalled=st.stalled, fault=True,
                            raw=st.raw, messages=st.messages + msgs)
        return st

    def position(self) -> float:
        reply = self._request(pack_short(Msg.MOT_REQ_POSCOUNTER, self.channel,
                                         dest=self.link.dest),
                              Msg.MOT_GET_POSCOUNTER, "MOT_REQ_POSCOUNTER")
        assert reply.data is not None
        return self._units(unpack_counter(reply.data)[1])

    def _check_ready(self, command: str) -> int:
        bits = self.status_bits()
        if not bits & StatusBit.ENABLED:
            raise DeviceFault(f"channel {self.channel} is disabled: the controller ignores "
                              "motion commands", device=self.name, port=self.port,
                              command=command)
        return bits

    def home(self) -> None:
        cmd = "MOT_MOVE_HOME"
        self._check_ready(cmd)
        ev = self.link.events(self.channel)
        homed_before = ev.homed
        self.link.send(pack_short(Msg.MOT_MOVE_HOME, self.channel, dest=self.link.dest), cmd)
        timeout = self.config.home_timeout_s / max(self.config.time_scale, 1e-9)
        seen_homing = False

        def homed() -> bool:
            nonlocal seen_homing
            bits = self.status_bits()
            if ev.homed > homed_before:
                return True
            seen_homing |= bool(bits & StatusBit.HOMING)
            if seen_homing and bits & StatusBit.HOMED and not bits & MOTION_BITS:
                log.debug("%s: homed bit set without MOVE_HOMED; accepting", self.name)
                return True
            st = decode_status(bits)
            if st.stalled or st.fault or not bits & StatusBit.ENABLED:
                self.stop()
                raise DeviceFault(f"homing failed: {'; '.join(st.messages) or st.raw}",
                                  device=self.name, port=self.port, command=cmd)
            return False

        self.poll_until(homed, timeout, command=cmd,
                        timeout_message=f"no MOVE_HOMED within {timeout:.1f} s")
        self.position_known = True
        log.info("%s: homed", self.name)

    def _start_move(self, target: float) -> None:
        cmd = f"MOT_MOVE_ABSOLUTE {target:.6g}"
        counts = self._counts(target)
        bits = self._check_ready(cmd)
        if not bits & StatusBit.HOMED:
            raise DeviceFault("not homed: home the axis before absolute moves",
                              device=self.name, port=self.port, command=cmd)
        self.link.send(pack_data(Msg.MOT_MOVE_ABSOLUTE, pack_move(self.channel, counts),
                                 dest=self.link.dest), cmd)

    def stop(self) -> None:
        self._require_connected("MOT_MOVE_STOP")
        self.link.send(pack_short(Msg.MOT_MOVE_STOP, self.channel, STOP_IMMEDIATE,
                                  dest=self.link.dest), "MOT_MOVE_STOP")


def make_axes(controller: ControllerConfig, time_scale: float = 1.0, *,
              clock: Clock | None = None) -> list[AptAxis]:
    """The axes of one APT controller config, sharing one link (one serial port)."""
    if controller.protocol != "apt":
        raise ValueError(f"controller {controller.name} speaks {controller.protocol}, not apt")
    link = AptLink(controller.port, device=controller.name,
                   baudrate=controller.baudrate or BAUDRATE,
                   reply_timeout_s=controller.reply_timeout_s)
    return [AptAxis(ax.model_copy(update={"time_scale": time_scale}), link, clock=clock)
            for ax in controller.axes]
