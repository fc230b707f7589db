"""Newport SMC100: codec, driver transcripts (exact bytes), emulator, driver against emulator.

Transcripts run the real ``SerialTransport`` over a scripted in-memory port, so every byte
the driver writes is checked and every reply byte is chosen by the test. The emulator is
exercised byte by byte on a ``ManualClock``; driver-against-emulator tests go over a real
pseudo-terminal and a loopback TCP port with ``EmulatorServer``.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

import numpy as np
import pytest
from scripted_serial import url_for

from drivers.config import AxisConfig, ControllerConfig, FaultConfig
from drivers.errors import (
    DeviceFault,
    DeviceTimeoutError,
    LimitError,
    ProtocolError,
    TransportError,
)
from drivers.newport_smc100 import (
    Smc100Axis,
    decode_te,
    decode_ts,
    format_command,
    make_axes,
    parse_reply,
    parse_version,
    ts_to_status,
)
from drivers.sim.clock import ManualClock, ScaledClock
from drivers.sim.kinematics import SimAxis
from drivers.sim.server import EmulatorServer
from drivers.sim.smc100_emu import Smc100Emulator, physics_for
from drivers.transport import SerialTransport

AXIS = {"role": "turntable", "units": "deg", "stage": "URS75BCC",
        "soft_limits": {"min": -30.0, "max": 30.0}, "speed": 20.0, "accel": 80.0,
        "deadband": 0.001, "backlash_approach": 0.0, "poll_interval_s": 0.001}


def axis_config(**update: object) -> AxisConfig:
    return AxisConfig.model_validate({**AXIS, **update})


# ======================================================================================
# codec
# ======================================================================================
def test_format_command_bytes() -> None:
    assert format_command(1, "PA", 10.5) == b"1PA10.5\r\n"
    assert format_command(12, "pr", -0.25) == b"12PR-0.25\r\n"
    assert format_command(1, "PA", 1e-7) == b"1PA0\r\n"  # fixed point, never 1e-07
    assert format_command(1, "PA", 123.4567891) == b"1PA123.456789\r\n"
    assert format_command(3, "TS") == b"3TS\r\n"
    assert format_command(1, "ID", "?") == b"1ID?\r\n"
    assert format_command(1, "MM", 0) == b"1MM0\r\n"
    with pytest.raises(ValueError):
        format_command(32, "TS")
    with pytest.raises(ValueError):
        format_command(1, "PA", float("nan"))


def test_parse_reply() -> None:
    r = parse_reply(b"1TP-12.34567\r\n")
    assert (r.address, r.command, r.value) == (1, "TP", "-12.34567")
    r = parse_reply(b"1VE SMC_CC - Controller-driver version  3. 1. 2\r\n")
    assert r.command == "VE" and r.value.startswith("SMC_CC")
    assert parse_reply(b"12TS000033\r\n").address == 12
    for bad in (b"TP1.0\r\n", b"1TP1.0\n", b"1T\x01P\r\n", b"1QQ5\r\n", b"\x13\r\n"):
        with pytest.raises(ValueError):
            parse_reply(bad)


def test_decode_ts_states_and_bits() -> None:
    ts = decode_ts("000033")
    assert (ts.errors, ts.state, ts.state_name, ts.family) == (0, 0x33, "READY from MOVING",
                                                               "READY")
    st = ts_to_status(ts)
    assert st.homed and not st.moving and not st.fault
    nr = ts_to_status(decode_ts("00000A"))
    assert not nr.homed and not nr.moving and not nr.fault
    homing = ts_to_status(decode_ts("00001E"))
    assert homing.moving and not homing.homed
    moving = ts_to_status(decode_ts("000028"))
    assert moving.moving and moving.homed
    # following error in DISABLE from MOVING: stalled and a fault, with both messages
    fe = ts_to_status(decode_ts("00203D"))
    assert fe.stalled and fe.fault and not fe.homed
    assert fe.messages == ("DISABLE from MOVING", "following error")
    lim = ts_to_status(decode_ts("000233"))  # 0x0002 positive end of run, READY
    assert lim.limit_high and not lim.limit_low and not lim.fault and lim.homed
    power = ts_to_status(decode_ts("020033"))  # 0x0200 output power exceeded
    assert power.fault and "80 W output power exceeded" in power.messages
    assert ts_to_status(decode_ts("000133")).limit_low
    assert ts_to_status(decode_ts("000077")).fault  # unknown state code
    for bad in ("00033", "00003G", "0000333"):
        with pytest.raises(ValueError):
            decode_ts(bad)


def test_decode_te_letters() -> None:
    assert decode_te("@") == "no error"
    assert "NOT REFERENCED" in decode_te("H")
    assert decode_te("G") == "displacement out of limits"
    assert "software limit" in decode_te("N")
    assert "MOVING" in decode_te("M")
    assert "unknown error code" in decode_te("Z")


def test_parse_version() -> None:
    assert parse_version("SMC_CC - Controller-driver version  3. 1. 2") == ("SMC100CC",
                                                                             "3.1.2")
    assert parse_version("SMC_PP - Controller-driver version 2.0") == ("SMC100PP", "2.0")


# ======================================================================================
# transcripts: the real SerialTransport over a scripted port
# ======================================================================================
class ScriptedPort:
    """A pyserial-like port: each written line must be the next expected one; its reply
    bytes (possibly none, garbage, or several lines) then become readable."""

    def __init__(self, script: list[tuple[bytes, bytes]]) -> None:
        self.script = list(script)
        self.written = b""
        self._line = b""
        self._rx = bytearray()
        self.timeout: float | None = 0.0

    def open(self) -> None: ...

    @property
    def in_waiting(self) -> int:
        return len(self._rx)

    def write(self, data: bytes) -> int:
        self.written += data
        self._line += data
        while b"\r\n" in self._line:
            line, self._line = self._line.split(b"\r\n", 1)
            assert self.script, f"unexpected command {line!r} after the end of the script"
            expected, reply = self.script.pop(0)
            assert line + b"\r\n" == expected, f"sent {line!r}, script expected {expected!r}"
            self._rx += reply
        return len(data)

    def flush(self) -> None: ...

    def read(self, n: int = 1) -> bytes:
        out = bytes(self._rx[:n])
        del self._rx[:n]
        return out

    def close(self) -> None: ...


def scripted_axis(script: list[tuple[bytes, bytes]], timeout_s: float = 0.05,
                  **cfg: object) -> tuple[Smc100Axis, ScriptedPort]:
    port = ScriptedPort(script)
    tr = SerialTransport(url_for(port, "smc100"), device="turntable", baudrate=57600,
                         timeout_s=timeout_s, xonxoff=True)
    axis = Smc100Axis(axis_config(**cfg), tr, clock=ManualClock())  # polls do not wait
    return axis, port


CONNECT = [(b"1TS\r\n", b"1TS00000A\r\n")]


def test_transcript_connect_identify() -> None:
    axis, port = scripted_axis([*CONNECT,
        (b"1ID?\r\n", b"1IDURS75BCC\r\n"),
        (b"1VE\r\n", b"1VE SMC_CC - Controller-driver version  3. 1. 2\r\n"),
    ])
    axis.connect()
    ident = axis.identify()
    assert (ident.vendor, ident.model, ident.firmware, ident.stage) == (
        "Newport", "SMC100CC", "3.1.2", "URS75BCC")
    assert port.written == b"1TS\r\n1ID?\r\n1VE\r\n"
    assert not port.script


def test_transcript_home() -> None:
    axis, port = scripted_axis([*CONNECT,
        (b"1TS\r\n", b"1TS00000A\r\n"),
        (b"1OR\r\n", b""),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS00001E\r\n"),
        (b"1TS\r\n", b"1TS00001E\r\n"),
        (b"1TS\r\n", b"1TS000032\r\n"),
        (b"1VA20\r\n", b""),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1AC80\r\n", b""),
        (b"1TE\r\n", b"1TE@\r\n"),
    ])
    with axis:
        axis.home()
        assert axis.position_known
    assert not port.script


def test_transcript_home_when_ready_sends_no_or() -> None:
    axis, port = scripted_axis([(b"1TS\r\n", b"1TS000033\r\n"),
                                (b"1TS\r\n", b"1TS000033\r\n")])
    with axis:
        axis.home()
    assert b"OR" not in port.written and not port.script


def test_transcript_homing_failure_is_a_fault() -> None:
    axis, _ = scripted_axis([*CONNECT,
        (b"1TS\r\n", b"1TS00000A\r\n"),
        (b"1OR\r\n", b""),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS00400B\r\n"),  # homing time-out, NOT REFERENCED from HOMING
    ])
    with axis, pytest.raises(DeviceFault, match="homing time-out"):
        axis.home()


def test_transcript_move_to() -> None:
    axis, port = scripted_axis([*CONNECT,
        (b"1TP\r\n", b"1TP0\r\n"),
        (b"1VA20\r\n", b""),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1AC80\r\n", b""),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1PA10.5\r\n", b""),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TS\r\n", b"1TS000028\r\n"),
        (b"1TP\r\n", b"1TP5.25\r\n"),
        (b"1TS\r\n", b"1TS000033\r\n"),
        (b"1TP\r\n", b"1TP10.5005\r\n"),
    ])
    with axis:
        assert axis.move_to(10.5) == pytest.approx(10.5005)
    assert not port.script


def test_transcript_stop_position_status() -> None:
    axis, port = scripted_axis([*CONNECT,
        (b"1ST\r\n", b""),
        (b"1TE\r\n", b"1TE@\r\n"),
        (b"1TP\r\n", b"1TP-12.3456\r\n"),
        (b"1TS\r\n", b"1TS000128\r\n"),
        (b"1SL?\r\n", b"1SL-170\r\n"),
        (b"1SR?\r\n", b"1SR170\r\n"),
        (b"1TH\r\n", b"1TH4\r\n"),
    ])
    with axis:
        axis.stop()
        assert axis.position() == pytest.approx(-12.3456)
        st = axis.status()
        assert st.moving and st.limit_low and st.raw == "000128"
        assert axis.software_limits() == (-170.0, 170.0)
        assert axis.target() == 4.0
    assert not port.script


def test_stop_refused_is_not_an_error() -> None:
    axis, _ = scripted_axis([*CONNECT, (b"1ST\r\n", b""), (b"1TE\r\n", b"1TEH\r\n")])
    with axis:
        axis.stop()


def test_soft_limit_refusal_sends_nothing() -> None:
    axis, port = scripted_axis([])
    axis._connected = True  # no connect exchange: nothing at all may reach the wire
    for bad in (30.5, -31.0, float("nan"), float("inf")):
        with pytest.raises(LimitError):
            axis.move_to(bad)
    assert port.written == b""


@pytest.mark.parametrize(("letter", "error", "text"), [
    ("G", LimitError, "displacement out of limits"),
    ("N", LimitError, "software limit"),
    ("H", DeviceFault, "NOT REFERENCED state"),
    ("J", DeviceFault, "DISABLE state"),
    ("M", DeviceFault, "MOVING state"),
    ("A", ProtocolError, "unknown message code"),
])
def test_te_error_after_pa_is_decoded(letter: str, error: type, text: str) -> None:
    axis, _ = scripted_axis([*CONNECT,
        (b"1VA20\r\n", b""), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1AC80\r\n", b""), (b"1TE\r\n", b"1TE@\r\n"),
        (b"1PA12.5\r\n", b""),
        (b"1TE\r\n", f"1TE{letter}\r\n".encode()),
    ])
    with axis, pytest.raises(error, match=text) as info:
        axis._start_move(12.5)
    assert info.value.command == "1PA12.5" and info.value.device == "turntable"
    assert f"TE {letter}" in str(info.value)


def test_late_reply_is_discarded(caplog: pytest.LogCaptureFixture) -> None:
    # the reply to an earlier TS arrives just before the reply to TP
    axis, _ = scripted_axis([*CONNECT, (b"1TP\r\n", b"1TS000033\r\n1TP1.5\r\n")])
    with axis, caplog.at_level(logging.WARNING):
        assert axis.position() == 1.5
    assert "discarding reply b'1TS000033\\r\\n'" in caplog.text


def test_reply_from_another_address_is_not_the_answer() -> None:
    axis, _ = scripted_axis([*CONNECT, (b"1TP\r\n", b"2TP9.0\r\n"), (b"1TP\r\n", b""),
                             (b"1TP\r\n", b"")])
    with axis, pytest.raises(DeviceTimeoutError):
        axis.position()


def test_garbled_reply_resyncs_and_retries_once() -> None:
    axis, port = scripted_axis([*CONNECT,
        (b"1TP\r\n", b"1TP1h.5\r\n"),  # garbled value
        (b"1TP\r\n", b"1TP1.5\r\n"),
    ])
    with axis:
        assert axis.position() == 1.5
    assert port.written.count(b"1TP\r\n") == 2


def test_garbage_at_every_attempt_raises_protocol_error() -> None:
    axis, _ = scripted_axis([*CONNECT, (b"1TS\r\n", b"\x00\xff1T\r\n"),
                                       (b"1TS\r\n", b"1TS0000Z3\r\n"),
                                       (b"1TS\r\n", b"1TS000\x803\r\n")])
    with axis, pytest.raises(ProtocolError, match="1TS"):
        axis.status()


def test_timeout_retries_then_raises() -> None:
    axis, port = scripted_axis([*CONNECT, (b"1TS\r\n", b""), (b"1TS\r\n", b"1TS000033\r\n")])
    with axis:
        assert axis.status().homed
    assert port.written == b"1TS\r\n" * 3 and not port.script
    axis, _port = scripted_axis([*CONNECT, (b"1TS\r\n", b""), (b"1TS\r\n", b""),
                                 (b"1TS\r\n", b"1TS0000")])
    with axis, pytest.raises(DeviceTimeoutError, match="truncated reply"):
        axis.status()


def test_te_is_never_resent_after_a_timeout() -> None:
    # TE clears the error it reports: resending it alone could hide a refusal. After a lost
    # TE of a PA the driver asks for the state instead: moving towards the target = taken.
    axis, port = scripted_axis([*CONNECT, (b"1PA1\r\n", b""), (b"1TE\r\n", b""),
                                (b"1TS\r\n", b"1TS000028\r\n"), (b"1TH\r\n", b"1TH0.6\r\n"),
                                (b"1TP\r\n", b"1TP0.4\r\n")])
    with axis:
        axis._profile_sent = True
        axis._start_move(1.0)
    assert port.written.count(b"1TE\r\n") == 1
    assert port.written.endswith(b"1PA1\r\n1TE\r\n1TS\r\n1TH\r\n1TP\r\n")


def test_pa_whose_te_is_lost_and_that_moves_elsewhere_is_an_error() -> None:
    axis, _port = scripted_axis([*CONNECT, (b"1PA1\r\n", b""), (b"1TE\r\n", b""),
                                 (b"1TS\r\n", b"1TS000028\r\n"), (b"1TH\r\n", b"1TH-3\r\n"),
                                 (b"1TP\r\n", b"1TP0.4\r\n")])
    with axis, pytest.raises(ProtocolError, match="moving to -3, not to 1 deg"):
        axis._profile_sent = True
        axis._start_move(1.0)


def test_pa_whose_te_is_lost_on_a_disabled_controller_is_a_fault() -> None:
    axis, _port = scripted_axis([*CONNECT, (b"1PA1\r\n", b""), (b"1TE\r\n", b""),
                                 (b"1TS\r\n", b"1TS00203D\r\n"), (b"1TH\r\n", b"1TH0.4\r\n"),
                                 (b"1TP\r\n", b"1TP0.4\r\n")])
    with axis, pytest.raises(DeviceFault, match=r"DISABLE from MOVING.*following error"):
        axis._profile_sent = True
        axis._start_move(1.0)


def test_idempotent_set_command_is_resent_with_its_te_check() -> None:
    axis, port = scripted_axis([*CONNECT,
        (b"1VA20\r\n", b""), (b"1TE\r\n", b""),  # acknowledgement lost
        (b"1VA20\r\n", b""), (b"1TE\r\n", b"1TE@\r\n"),
    ])
    with axis:
        axis.send("VA", 20)
    assert port.written == b"1TS\r\n" + b"1VA20\r\n1TE\r\n" * 2


def test_or_is_not_resent_when_its_te_check_is_lost() -> None:
    axis, port = scripted_axis([*CONNECT,
        (b"1TS\r\n", b"1TS00000A\r\n"), (b"1OR\r\n", b""), (b"1TE\r\n", b""),
        (b"1ST\r\n", b""), (b"1TE\r\n", b"1TE@\r\n"),  # the homing run may have started
    ])
    with axis, pytest.raises(DeviceTimeoutError, match=r"TE check of 1OR .*'1OR \+ 1TE'"):
        axis.home()
    assert port.written.count(b"1OR") == 1 and not port.script


def test_connect_to_a_silent_controller_fails_and_releases_the_port() -> None:
    axis, _ = scripted_axis([(b"1TS\r\n", b""), (b"1TS\r\n", b""), (b"1TS\r\n", b"")])
    with pytest.raises(DeviceTimeoutError, match=r"no reply .*port script://smc100.*'1TS'"):
        axis.connect()
    assert not axis.transport.is_open


def test_connect_and_close_are_idempotent() -> None:
    axis, port = scripted_axis(CONNECT)
    axis.connect()
    axis.connect()
    assert port.written == b"1TS\r\n"
    axis.close()
    axis.close()
    assert not axis.transport.is_open


# ======================================================================================
# emulator, byte by byte, on a manual clock
# ======================================================================================
def make_emu(addresses: tuple[int, ...] = (1,), start: float = 3.0
             ) -> tuple[Smc100Emulator, dict[int, SimAxis], ManualClock]:
    clock = ManualClock()
    rng = np.random.default_rng(7)
    axes = {a: SimAxis(f"tt{a}", physics_for(axis_config()), clock, rng, start=start)
            for a in addresses}
    return Smc100Emulator("turntable", axes, clock), axes, clock


def home(emu: Smc100Emulator, clock: ManualClock, addr: int = 1) -> None:
    assert emu.handle(f"{addr}OR\r\n".encode()) == b""
    clock.advance(5.0)
    assert emu.handle(f"{addr}TS\r\n".encode()) == f"{addr}TS000032\r\n".encode()


def test_emu_power_on_and_homing() -> None:
    emu, _axes, clock = make_emu()
    assert emu.handle(b"1TS\r\n") == b"1TS00000A\r\n"
    assert emu.handle(b"1OR\r\n") == b""
    assert emu.handle(b"1TS\r\n") == b"1TS00001E\r\n"
    assert emu.handle(b"1OR\r\n1TE\r\n") == b"1TEE\r\n"  # home sequence already started
    clock.advance(0.05)
    assert emu.handle(b"1TS\r\n") == b"1TS00001E\r\n"  # 3 deg at 10 deg/s takes > 0.3 s
    clock.advance(1.0)
    assert emu.handle(b"1TS\r\n1TP\r\n") == b"1TS000032\r\n1TP0\r\n"
    assert emu.handle(b"1OR\r\n1TE\r\n") == b"1TEK\r\n"  # not allowed in READY


def test_emu_move_states_and_kinematics() -> None:
    emu, _axes, clock = make_emu()
    home(emu, clock)
    assert emu.handle(b"1PA10.5\r\n1TE\r\n1TS\r\n") == b"1TE@\r\n1TS000028\r\n"
    clock.advance(0.35)  # accelerating at 80 deg/s^2 to 20 deg/s: a 0.25 s ramp
    pos = float(emu.handle(b"1TP\r\n")[3:])
    assert pos == pytest.approx(0.5 * 80 * 0.25**2 + 20 * 0.1, abs=0.001)
    clock.advance(1.0)
    assert emu.handle(b"1TS\r\n1TP\r\n1PA?\r\n") == b"1TS000033\r\n1TP10.5\r\n1PA10.5\r\n"
    # relative move from the set point; zero-length PR leaves the state alone
    assert emu.handle(b"1PR-0.5\r\n1TS\r\n") == b"1TS000028\r\n"
    clock.advance(1.0)
    assert emu.handle(b"1TP\r\n1PR0\r\n1TS\r\n") == b"1TP10\r\n1TS000033\r\n"


def test_emu_encoder_quantisation() -> None:
    emu, _axes, clock = make_emu()
    home(emu, clock)
    emu.handle(b"1PA1.23456\r\n")
    clock.advance(2.0)
    reply = emu.handle(b"1TP\r\n")
    assert reply == b"1TP1.2345\r\n"  # 2000 counts per degree: 0.0005 deg steps
    assert abs(float(reply[3:]) - 1.23456) <= 0.00025


def test_emu_refusals_stored_for_te() -> None:
    emu, axes, clock = make_emu()
    assert emu.handle(b"1PA5\r\n1TE\r\n1TE\r\n") == b"1TEH\r\n1TE@\r\n"  # read clears
    assert emu.handle(b"1QX\r\n1TE\r\n") == b"1TEA\r\n"
    home(emu, clock)
    assert emu.handle(b"1PA171\r\n1TE\r\n1TS\r\n") == b"1TEG\r\n1TS000032\r\n"
    assert emu.handle(b"1SR20\r\n1PR25\r\n1TE\r\n") == b"1TEG\r\n"
    assert emu.handle(b"1PAabc\r\n1TE\r\n") == b"1TEC\r\n"
    assert emu.handle(b"1VA500\r\n1TE\r\n1VA?\r\n") == b"1TEC\r\n1VA20\r\n"
    assert emu.handle(b"1TBG\r\n") == b"1TBG Displacement out of limits\r\n"
    assert axes[1].targets == []  # nothing refused ever reached the mechanics


def test_emu_case_insensitive_split_and_queries() -> None:
    emu, _axes, _clock = make_emu()
    out = b""
    for chunk in (b"1t", b"s\r", b"\n1ve?\r\n1id?", b"\r\n 1sl?\r\n1SR?\r\n1AC?\r\n1TE?\r\n"):
        out += emu.handle(chunk)
    assert out == (b"1TS00000A\r\n1VE SMC_CC - Controller-driver version  3. 1. 2\r\n"
                   b"1IDURS75BCC\r\n1SL-170\r\n1SR170\r\n1AC80\r\n1TE@\r\n")
    assert emu.commands_seen == 7


def test_emu_disable_enable() -> None:
    emu, axes, clock = make_emu()
    assert emu.handle(b"1MM0\r\n1TE\r\n") == b"1TEH\r\n"
    home(emu, clock)
    assert emu.handle(b"1MM0\r\n1TS\r\n1PA1\r\n1TE\r\n") == b"1TS00003C\r\n1TEJ\r\n"
    assert emu.handle(b"1MM1\r\n1TS\r\n") == b"1TS000034\r\n"
    emu.handle(b"1PA20\r\n")
    clock.advance(0.2)
    assert emu.handle(b"1MM0\r\n1TS\r\n") == b"1TS00003D\r\n"
    assert not axes[1].moving


def test_emu_stop_and_reset() -> None:
    emu, _axes, clock = make_emu()
    home(emu, clock)
    emu.handle(b"1PA20\r\n")
    clock.advance(0.3)
    assert emu.handle(b"1ST\r\n1TS\r\n") == b"1TS000033\r\n"
    here = float(emu.handle(b"1TP\r\n")[3:])
    clock.advance(1.0)
    assert float(emu.handle(b"1TP\r\n")[3:]) == here and 0 < here < 20
    assert emu.handle(b"1AC40\r\n1RS\r\n1TS\r\n1AC?\r\n") == b"1TS00000A\r\n1AC80\r\n"


def test_emu_stall_is_a_following_error() -> None:
    emu, axes, clock = make_emu()
    home(emu, clock)
    emu.handle(b"1PA20\r\n")
    clock.advance(0.2)
    axes[1].inject_stall()
    clock.advance(0.1)
    assert emu.handle(b"1TS\r\n") == b"1TS00203D\r\n"
    assert emu.handle(b"1TS\r\n") == b"1TS00203D\r\n"  # latched until re-enabled
    assert emu.handle(b"1MM1\r\n1TS\r\n") == b"1TS000034\r\n"


def test_emu_end_of_run_limit() -> None:
    emu, axes, clock = make_emu()
    home(emu, clock)
    emu.handle(b"1PA20\r\n")
    axes[1].inject_limit_switch("high")
    clock.advance(0.1)
    assert emu.handle(b"1TS\r\n") == b"1TS000233\r\n"
    # moving away clears the switch
    emu.handle(b"1PA0\r\n")
    clock.advance(5.0)
    assert emu.handle(b"1TS\r\n") == b"1TS000033\r\n"


def test_emu_rs485_chain_addresses() -> None:
    emu, axes, clock = make_emu(addresses=(1, 2))
    home(emu, clock, 2)
    assert emu.handle(b"1TS\r\n2TS\r\n3TS\r\n") == b"1TS00000A\r\n2TS000032\r\n"
    emu.handle(b"2PA5\r\n")
    clock.advance(0.1)
    assert emu.handle(b"ST\r\n2TS\r\n") == b"2TS000033\r\n"  # no address: every controller
    assert axes[1].targets == [] and axes[2].targets == [5.0]


def test_physics_for_rotation_stage() -> None:
    p = physics_for(axis_config())
    assert (p.travel_min, p.travel_max) == (-170.0, 170.0)
    assert p.counts_per_unit == 2000.0 and p.speed == 20.0 and p.requires_homing


# ======================================================================================
# driver against the emulator, over a real pty and TCP
# ======================================================================================
@contextlib.contextmanager
def served(mode: str, addresses: tuple[int, ...] = (1,), faults: list[FaultConfig] | None = None,
           reply_timeout_s: float = 2.0, scale: float = 20.0, start: float = 2.5
           ) -> Iterator[tuple[EmulatorServer, dict[int, SimAxis], ControllerConfig]]:
    """An emulated SMC100 chain served on ``mode``, and the controller config to reach it."""
    clock = ScaledClock(scale)
    rng = np.random.default_rng(3)
    axes = {a: SimAxis(f"tt{a}", physics_for(axis_config()), clock, rng, start=start)
            for a in addresses}
    roles = ["turntable", "x", "y"]
    with EmulatorServer(Smc100Emulator("turntable", axes, clock), mode, faults=faults) as srv:
        cfg = ControllerConfig(name="turntable", protocol="smc100", port=srv.url,
                               reply_timeout_s=reply_timeout_s,
                               axes=[{**AXIS, "role": roles[i], "address": a,
                                      "backlash_approach": 0.5}
                                     for i, a in enumerate(addresses)])
        yield srv, axes, cfg


@pytest.mark.parametrize("mode", ["pty", "tcp"])
def test_driver_homes_and_moves_within_deadband(mode: str) -> None:
    with served(mode) as (_srv, sims, cfg):
        (axis,) = make_axes(cfg, time_scale=20.0)
        assert axis.config.time_scale == 20.0
        with axis:
            assert axis.identify().stage == "URS75BCC"
            assert axis.needs_homing
            axis.home()
            assert axis.status().homed and abs(axis.position()) < 0.001
            for target in (12.345, -7.5, -7.5, 29.9999):
                reached = axis.move_to(target)
                assert abs(reached - target) <= cfg.axes[0].deadband
            # approach from +: moves down (or nowhere) first go 0.5 deg below the target
            assert sims[1].targets == pytest.approx([12.345, -8.0, -7.5, -8.0, -7.5, 29.9999])
            assert not axis.status().moving


@pytest.mark.parametrize("mode", ["pty", "tcp"])
def test_driver_soft_limit_refusal_before_any_byte(mode: str) -> None:
    with served(mode) as (srv, _sims, cfg):
        (axis,) = make_axes(cfg, time_scale=20.0)
        with axis:
            axis.home()
            seen = srv.emulator.commands_seen
            with pytest.raises(LimitError, match="outside soft limits"):
                axis.move_to(45.0)
            assert srv.emulator.commands_seen == seen


def test_driver_te_error_decoded_from_emulator() -> None:
    with served("tcp") as (_srv, sims, cfg):
        (axis,) = make_axes(cfg, time_scale=20.0)
        with axis:
            with pytest.raises(DeviceFault, match="NOT REFERENCED state") as info:
                axis.move_to(5.0)  # not homed yet
            assert info.value.command == "1PA5"
            axis.home()
            axis.send("SR", 10)  # the controller's own limit is tighter than ours
            with pytest.raises(LimitError, match=r"displacement out of limits \(TE G\)"):
                axis.move_to(15.0)
            assert 15.0 not in sims[1].targets


def test_driver_detects_late_reply_over_tcp(caplog: pytest.LogCaptureFixture) -> None:
    with served("tcp") as (_srv, _sims, cfg):
        (axis,) = make_axes(cfg, time_scale=20.0)
        with axis:
            axis.home()
            axis.move_to(4.0)
            # an earlier query whose reply nobody read (as after a timed-out exchange)
            axis.transport.write(b"1TS\r\n")
            with caplog.at_level(logging.WARNING):
                assert axis.position() == pytest.approx(4.0, abs=0.001)
            assert "discarding reply b'1TS000033\\r\\n'" in caplog.text


def test_driver_survives_a_slow_reply_over_tcp(caplog: pytest.LogCaptureFixture) -> None:
    # the second reply of the session comes after the driver gave up on it
    faults = [FaultConfig(device="turntable", kind="late_reply", on="TS", delay_s=1.5)]
    with served("tcp", faults=faults, reply_timeout_s=1.0) as (_srv, _sims, cfg):
        (axis,) = make_axes(cfg, time_scale=20.0)
        with axis, caplog.at_level(logging.WARNING):
            for _ in range(3):
                assert axis.status().raw == "00000A"
            assert axis.position() == pytest.approx(2.5, abs=0.001)
        assert "no reply; resynchronising and resending 1TS" in caplog.text


def test_driver_stall_ends_in_fault_and_stopped_axis() -> None:
    with served("pty", scale=5.0) as (_srv, sims, cfg):
        (axis,) = make_axes(cfg, time_scale=5.0)
        with axis:
            axis.home()
            sims[1].inject_stall()
            with pytest.raises(DeviceFault, match="following error"):
                axis.move_to(25.0)
            assert not sims[1].moving
            st = axis.status()
            assert st.stalled and st.fault and st.raw == "00203D"
            axis.home()  # re-enables (MM1): referenced again, no new homing run
            assert axis.status().homed
            assert abs(axis.move_to(1.0) - 1.0) <= 0.001


def test_driver_limit_switch_ends_in_limit_error() -> None:
    with served("tcp", scale=5.0) as (_srv, sims, cfg):
        (axis,) = make_axes(cfg, time_scale=5.0)
        with axis:
            axis.home()
            sims[1].inject_limit_switch("high")
            with pytest.raises(LimitError, match="high limit switch"):
                axis.move_to(25.0)
            assert not sims[1].moving


def test_two_addresses_share_one_port() -> None:
    with served("pty", addresses=(1, 2)) as (_srv, sims, cfg):
        a1, a2 = make_axes(cfg, time_scale=20.0)
        assert a1.transport is a2.transport
        with a1, a2:
            a2.home()
            assert a2.status().homed and not a1.status().homed
            assert abs(a2.move_to(-3.0) + 3.0) <= 0.001
            a1.close()
            assert a2.transport.is_open  # still in use by the second axis
            assert abs(a2.position() + 3.0) <= 0.001
        assert not a2.transport.is_open
        assert sims[1].targets == []


def test_disconnect_mid_move_ends_in_transport_error() -> None:
    faults = [FaultConfig(device="turntable", kind="disconnect", on="PA")]
    with served("tcp", faults=faults, scale=5.0, start=0.0) as (srv, _sims, cfg):
        (axis,) = make_axes(cfg, time_scale=5.0)
        with axis:
            axis.home()  # already at the index: no motion, so no disconnect yet
            with pytest.raises(TransportError, match="turntable"):
                axis.move_to(25.0)
            assert srv.disconnected


def test_wire_faults_during_home_and_move_are_recovered() -> None:
    # each fault names the exchange it hits: the first TS poll of homing, the TE check of
    # the first VA, the first TP (all of them resent after a resynchronisation)
    faults = [FaultConfig(device="turntable", kind="no_reply", on="TS"),
              FaultConfig(device="turntable", kind="garbled", on="TE", following="VA"),
              FaultConfig(device="turntable", kind="truncated", on="TP")]
    with served("tcp", faults=faults, reply_timeout_s=1.0, start=0.0) as (srv, _, cfg):
        (axis,) = make_axes(cfg, time_scale=20.0)
        with axis:
            axis.home()
            assert abs(axis.move_to(20.0) - 20.0) <= 0.001
        assert srv.faults.replies > 10 and all(f.hits == 1 for f in srv.faults.faults)


@pytest.mark.parametrize("kind", ["no_reply", "garbled", "truncated"])
def test_unreadable_te_after_pa_is_resolved_by_asking_the_controller(
        kind: str, caplog: pytest.LogCaptureFixture) -> None:
    """The move was taken: TS/TH/TP say so, and it goes on to the target (issue 15)."""
    faults = [FaultConfig(device="turntable", kind=kind, on="TE", following="PA")]
    with served("pty", faults=faults, reply_timeout_s=1.0, start=0.0, scale=5.0
                ) as (srv, sims, cfg):
        (axis,) = make_axes(cfg, time_scale=5.0)
        with axis, caplog.at_level(logging.WARNING):
            axis.home()
            assert abs(axis.move_to(20.0) - 20.0) <= 0.001
            assert axis.position_known
        assert srv.faults.faults[0].hits == 1
        assert sims[1].targets == [20.0]  # taken once, never re-issued
        assert "the TE check of 1PA20 was unreadable" in caplog.text
        assert "the move was accepted" in caplog.text


def test_refused_pa_with_a_lost_te_is_sent_again_and_its_refusal_raised(
        caplog: pytest.LogCaptureFixture) -> None:
    """Idle elsewhere after an unreadable TE: the absolute move was not taken, so it is
    sent once more, and the controller's own refusal (TE G) is what the caller sees."""
    faults = [FaultConfig(device="turntable", kind="no_reply", on="TE", following="PA",
                          nth=2)]
    with served("tcp", faults=faults, reply_timeout_s=1.0, start=0.0) as (srv, sims, cfg):
        (axis,) = make_axes(cfg, time_scale=20.0)
        with axis, caplog.at_level(logging.WARNING):
            axis.home()
            assert abs(axis.move_to(5.0) - 5.0) <= 0.001  # the 1st PA: untouched
            axis.send("SR", 10)  # the controller's own limit is tighter than ours
            with pytest.raises(LimitError, match=r"displacement out of limits \(TE G\)"):
                axis.move_to(15.0)
        assert srv.faults.faults[0].hits == 1
        assert "1PA15 was not taken" in caplog.text
        assert 15.0 not in sims[1].targets and not sims[1].moving


def test_unreadable_te_after_pa_and_no_state_stops_the_axis() -> None:
    """When the controller cannot say what it did (TH never answers), the run faults with
    both reasons and the stage is stopped: a move is never silently lost."""
    faults = [FaultConfig(device="turntable", kind="no_reply", on="TE", following="PA"),
              FaultConfig(device="turntable", kind="no_reply", on="TH", count=3)]
    with served("pty", faults=faults, reply_timeout_s=1.0, start=0.0, scale=1.0
                ) as (_, sims, cfg):
        (axis,) = make_axes(cfg, time_scale=1.0)
        with axis:
            axis.home()
            with pytest.raises(DeviceTimeoutError,
                               match=r"1PA20.*state could not be read.*1TH") as info:
                axis.move_to(20.0)
            assert info.value.command == "1PA20 + 1TE"
            assert sims[1].targets == [20.0] and not sims[1].moving  # told to stop
            assert not axis.status().moving and not axis.position_known
