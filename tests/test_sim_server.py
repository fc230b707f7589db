"""The emulator server carries bytes over real ptys and TCP, and injects wire faults."""

from __future__ import annotations

import time

import numpy as np
import pytest
import serial

from drivers.config import FaultConfig
from drivers.sim.clock import ManualClock
from drivers.sim.emulator import Emulator
from drivers.sim.kinematics import AxisPhysics, SimAxis
from drivers.sim.server import EmulatorServer


class LineEcho(Emulator):
    """A minimal line protocol: 'POS?' answers the axis position, anything else echoes."""

    protocol = "test"

    def __init__(self, name: str, axes: dict[int, SimAxis], clock: ManualClock) -> None:
        super().__init__(name, axes, clock)
        self.buf = b""

    def handle(self, data: bytes) -> bytes:
        self.buf += data
        out = b""
        while b"\n" in self.buf:
            line, self.buf = self.buf.split(b"\n", 1)
            self.note_command(line.decode(errors="replace"))
            if line == b"POS?":
                out += b"%.3f\n" % self.axes[1].encoder_position()
            elif line.startswith(b"MOVE "):
                self.axes[1].move_to(float(line[5:]))
                out += b"OK\n"
            else:
                out += b"ECHO " + line + b"\n"
        return out


def make_emulator() -> tuple[LineEcho, ManualClock]:
    clock = ManualClock()
    ax = SimAxis("x", AxisPhysics(0, 50, 5, 20, 1000, requires_homing=False), clock,
                 np.random.default_rng(0), start=10.0)
    return LineEcho("dev", {1: ax}, clock), clock


def exchange(port: serial.SerialBase, line: bytes) -> bytes:
    port.write(line + b"\n")
    return port.readline()


@pytest.mark.parametrize("mode", ["tcp", "pty"])
def test_bytes_both_ways(mode: str) -> None:
    emu, clock = make_emulator()
    with EmulatorServer(emu, mode) as srv:
        assert srv.url.startswith("socket://127.0.0.1:" if mode == "tcp" else "/dev/pts/")
        with serial.serial_for_url(srv.url, timeout=1.0) as port:
            assert exchange(port, b"hello") == b"ECHO hello\n"
            assert exchange(port, b"POS?") == b"10.000\n"
            assert exchange(port, b"MOVE 12") == b"OK\n"
            clock.advance(5.0)
            assert exchange(port, b"POS?") == b"12.000\n"
    assert emu.axes[1].targets == [12.0]


@pytest.mark.parametrize(("kind", "check"), [
    ("no_reply", lambda r: r == b""),
    ("truncated", lambda r: r == b"ECHO ab"),  # first half of 14 bytes
    ("garbled", lambda r: r != b"ECHO abcdefgh\n"),
])
def test_wire_faults_hit_only_the_chosen_replies(kind: str, check) -> None:
    emu, _ = make_emulator()
    fault = FaultConfig(device="dev", kind=kind, on="abcdefgh", nth=2)
    with EmulatorServer(emu, "tcp", faults=[fault]) as srv, \
            serial.serial_for_url(srv.url, timeout=0.3) as port:
        assert exchange(port, b"abcdefgh") == b"ECHO abcdefgh\n"
        assert exchange(port, b"POS?") == b"10.000\n"  # polls do not move the ordinal
        port.write(b"abcdefgh\n")
        got = port.read(64)  # a whole reply is 14 bytes: this waits for the timeout
        assert check(got), got
        assert srv.faults.faults[0].hits == 1
        assert exchange(port, b"abcdefgh") == b"ECHO abcdefgh\n"  # count=1: once only


def test_fault_on_a_command_that_follows_another_hits_only_that_ordinal() -> None:
    """``on`` + ``following`` + ``nth``: the 2nd ``ack`` that follows a ``MOVE`` is lost,
    whatever the number of ``ack``s and polls around it."""
    emu, _ = make_emulator()
    fault = FaultConfig(device="dev", kind="no_reply", on="ack", following="MOVE", nth=2)
    with EmulatorServer(emu, "tcp", faults=[fault]) as srv, \
            serial.serial_for_url(srv.url, timeout=0.3) as port:
        answers = []
        for lines in ([b"ack"], [b"MOVE 11", b"ack"], [b"POS?", b"ack"], [b"MOVE 12", b"ack"],
                      [b"MOVE 13", b"ack"]):
            for line in lines:
                answers.append(exchange(port, line))
        assert answers == [b"ECHO ack\n", b"OK\n", b"ECHO ack\n", answers[3], b"ECHO ack\n",
                           b"OK\n", b"", b"OK\n", b"ECHO ack\n"]
        assert srv.faults.faults[0].hits == 1 and srv.faults.faults[0].matches == 3


def test_fault_config_takes_one_trigger() -> None:
    with pytest.raises(ValueError, match="either on"):
        FaultConfig(device="dev", kind="garbled", on="TE", after_commands=3)
    with pytest.raises(ValueError, match="need on"):
        FaultConfig(device="dev", kind="garbled", nth=2)


def test_late_reply_arrives_after_the_next_command() -> None:
    emu, _ = make_emulator()
    fault = FaultConfig(device="dev", kind="late_reply", count=1, delay_s=0.4)
    with EmulatorServer(emu, "tcp", faults=[fault]) as srv, \
            serial.serial_for_url(srv.url, timeout=0.2) as port:
        assert exchange(port, b"first") == b""  # timed out
        port.timeout = 1.0
        assert exchange(port, b"second") == b"ECHO first\n"  # the stale answer comes first
        assert port.readline() == b"ECHO second\n"


def test_disconnect_mid_move_makes_the_port_vanish() -> None:
    emu, _ = make_emulator()
    fault = FaultConfig(device="dev", kind="disconnect", on="MOVE")
    with EmulatorServer(emu, "tcp", faults=[fault]) as srv, \
            serial.serial_for_url(srv.url, timeout=0.5) as port:
        assert exchange(port, b"MOVE 40") == b"OK\n"  # moving now: the cable is pulled
        deadline = time.monotonic() + 10.0
        while not srv.disconnected and time.monotonic() < deadline:
            time.sleep(0.01)
        assert srv.disconnected
        with pytest.raises(serial.SerialException):
            for _ in range(5):
                port.write(b"POS?\n")
                if port.read(16) == b"":
                    raise serial.SerialException("closed")


def test_stall_fault_freezes_the_axis_while_it_reports_moving() -> None:
    emu, clock = make_emulator()
    fault = FaultConfig(device="dev", kind="stall", on="MOVE")
    with EmulatorServer(emu, "tcp", faults=[fault]) as srv, \
            serial.serial_for_url(srv.url, timeout=0.5) as port:
        assert exchange(port, b"MOVE 40") == b"OK\n"
        deadline = time.monotonic() + 10.0  # the server thread fires it on its next tick
        while not srv.faults.faults[0].fired and time.monotonic() < deadline:
            time.sleep(0.005)
        assert srv.faults.faults[0].fired
        clock.advance(0.5)
        first = emu.axes[1].motor_position()
        clock.advance(2.0)
        assert emu.axes[1].moving
        assert emu.axes[1].motor_position() == first


def test_both_serves_a_pty_and_tcp_and_answers_whoever_asked() -> None:
    emu, _ = make_emulator()
    with EmulatorServer(emu, "both") as srv:
        ep = srv.endpoint()
        assert ep["url"].startswith("socket://127.0.0.1:") and ep["pty"].startswith("/dev/pts/")
        with serial.serial_for_url(ep["url"], timeout=1.0) as tcp, \
                serial.serial_for_url(ep["pty"], timeout=1.0) as pty:
            assert exchange(tcp, b"via tcp") == b"ECHO via tcp\n"
            assert exchange(pty, b"via pty") == b"ECHO via pty\n"
            assert exchange(tcp, b"POS?") == b"10.000\n"


def test_pacing_takes_the_time_the_bytes_take_on_the_line() -> None:
    emu, _ = make_emulator()
    emu.baudrate = 9600  # 10 bits a byte: ~1.04 ms per byte
    with EmulatorServer(emu, "tcp", pace_serial=True) as srv, \
            serial.serial_for_url(srv.url, timeout=2.0) as port:
        t0 = time.monotonic()
        assert exchange(port, b"0123456789") == b"ECHO 0123456789\n"
        # 11 bytes in + 16 bytes out at 9600 baud: at least 28 ms (a lower bound only)
        assert time.monotonic() - t0 >= 27 * 10 / 9600
