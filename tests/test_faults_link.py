"""Issue 6, scenarios 1-5: the serial link fails (no reply; truncated, garbled or
bad-checksum replies; late replies; a vanished port; a port held by another process).

Driver-level checks run each real driver against its emulator on a loopback TCP port with
the server's fault injector; the daemon-level checks run the real ``alignd`` in a
subprocess on the simulated rig and assert the end state (``faults_support``)."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from collections.abc import Iterator
from typing import Any

import pytest
from faults_support import SIM_YAML, assert_end_state, sim_daemon, targets

from alignd.config import load_config
from drivers import registry
from drivers.axis import Axis
from drivers.config import FaultConfig, SimConfig
from drivers.errors import DeviceTimeoutError, PortBusyError, ProtocolError, TransportError
from drivers.sim.kinematics import SimAxis
from drivers.sim.rig import SimRig
from drivers.sim.server import EmulatorServer, FaultInjector

CFG = load_config(SIM_YAML)
CONTROLLERS = {c.name: c for c in CFG.controllers}
ROLE = {"turntable": "turntable", "translator": "translator", "platform": "x"}
MOVE_COMMAND = {"smc100": "PA", "apt": "0x0453", "zaber": "move abs"}  # absolute moves


@contextlib.contextmanager
def served(name: str, *, reply_timeout_s: float = 1.0, time_scale: float = 50.0,
           **axis_update: Any) -> Iterator[tuple[Axis, SimAxis, EmulatorServer]]:
    """One controller of the reference rig on its emulator, its driver connected and homed."""
    ctl = CONTROLLERS[name]
    ctl = ctl.model_copy(update={"reply_timeout_s": reply_timeout_s, "axes": [
        a.model_copy(update=axis_update) for a in ctl.axes]})
    with SimRig([ctl], [], SimConfig(time_scale=time_scale, seed=5)) as rig:
        srv = rig.servers[name]
        live = ctl.model_copy(update={"port": srv.url})
        axes = registry.make_axes(live, time_scale)
        axis = next(a for a in axes if a.config.role == ROLE[name])
        try:
            for a in axes:
                a.connect()
            axis.home()
            yield axis, rig.axes[ROLE[name]], srv
        finally:
            for a in axes:
                a.close()


def inject(srv: EmulatorServer, kind: str, seed: int = 0, **kw: Any) -> FaultInjector:
    """Arm a wire fault on the next reply(ies) of a running server."""
    kw.setdefault("count", 1)
    srv.faults = FaultInjector([FaultConfig(device=srv.emulator.name, kind=kind, **kw)], seed)
    return srv.faults


# ---- 2. truncated, garbled or bad-checksum replies --------------------------------------------
@pytest.mark.parametrize("kind", ["truncated", "garbled", "bad_checksum"])
@pytest.mark.parametrize("name", ["turntable", "translator", "platform"])
def test_corrupt_reply_is_never_a_value_and_the_link_resyncs(name: str, kind: str) -> None:
    with served(name) as (axis, _sim, srv):
        here = axis.move_to(axis.config.soft_limits.min + 1.25)
        for seed in range(3):
            fi = inject(srv, kind, seed)
            try:
                got = axis.position()
            except (ProtocolError, DeviceTimeoutError) as exc:  # detected: names the command
                assert exc.device in (axis.name, name) and exc.port == srv.url and exc.command
            else:  # the driver resynchronised and asked again: the true value
                assert got == here
            assert fi.faults[0].hits == 1  # the fault did hit a reply
            assert axis.position() == here  # the link is in step again


@pytest.mark.parametrize(("on", "following", "nth"), [
    ("TE", "PA", 3),  # the acknowledgement of a sweep move: resolved by asking TS/TH/TP
    ("TP", None, 12),  # a position read: resent after a resynchronisation
])
def test_garbled_reply_mid_sweep_with_the_real_vision_does_not_end_the_run(
        on: str, following: str | None, nth: int) -> None:
    """Scenario 2 at the daemon level, on rendered frames tracked by ``alignd.vision``.
    The fault names the exchange it hits, so the outcome never depends on how many status
    polls ran before it (issue 15)."""
    faults = [{"device": "turntable", "kind": "garbled", "on": on, "following": following,
               "nth": nth}]
    with sim_daemon(faults=faults, env={"FAULTS_TOOLS": "real"}) as dp:
        run = dp.run_and_wait("check")
        assert_end_state(dp, run, verdicts=["within_tolerance", "out_of_tolerance"])
        assert dp.stderr().count("fault garbled on turntable") == 1
        if on == "TE":
            assert "the move was accepted" in dp.stderr()
        for sw in run["sweeps"]:  # every recorded read-back is a real position
            for c, r in zip(sw["commanded"], sw["readback"], strict=True):
                assert abs(c - r) <= 0.001


# ---- 3. a late reply to an earlier command -----------------------------------------------------
@pytest.mark.parametrize("name", ["turntable", "translator", "platform"])
def test_late_reply_is_not_taken_for_the_current_answer(name: str) -> None:
    with served(name) as (axis, sim, srv):
        lim = axis.config.soft_limits
        old = axis.move_to(lim.min + 1.0)
        new = lim.min + 3.0
        fi = inject(srv, "late_reply", delay_s=2.5)
        made = fi.on_reply

        def teleport(reply: bytes, emulator: Any) -> tuple[bytes, float]:
            """Once the late reply is made (in the server's thread, before it reads the
            next command), the stage is elsewhere: no race with the driver's retry."""
            out = made(reply, emulator)
            if fi.faults[0].hits == 1 and sim.motor_position() == pytest.approx(old, abs=1e-3):
                with srv.lock:
                    sim._freeze(sim.motor_position() + (new - old))
            return out

        fi.on_reply = teleport  # type: ignore[method-assign]
        answers = []
        for _ in range(8):
            try:
                answers.append(axis.position())
            except (DeviceTimeoutError, ProtocolError):
                continue
        assert answers, "no answer after the late reply"
        assert all(a == pytest.approx(new, abs=1e-3) for a in answers), (old, new, answers)


# ---- 4. the port vanishes mid-move ---------------------------------------------------------------
@pytest.mark.parametrize("name", ["turntable", "translator", "platform"])
def test_disconnect_mid_move_leaves_position_unknown(name: str) -> None:
    with served(name, time_scale=20.0) as (axis, sim, srv):
        lim = axis.config.soft_limits
        axis.move_to(lim.min + 0.5)
        assert axis.position_known
        inject(srv, "disconnect", on=MOVE_COMMAND[srv.emulator.protocol])
        with pytest.raises(TransportError) as info:
            axis.move_to(lim.min + 0.5 + 0.5 * (lim.max - lim.min))
        assert info.value.device and info.value.port == srv.url
        assert srv.disconnected
        assert not axis.position_known  # until re-homed or verified
        deadline = time.monotonic() + 10
        while sim.moving and time.monotonic() < deadline:  # no link: the move runs out
            time.sleep(0.02)
        assert not sim.moving and lim.min <= sim.targets[-1] <= lim.max


def test_daemon_disconnect_mid_run_faults_safely() -> None:
    faults = [{"device": "platform", "kind": "disconnect", "on": "move abs", "nth": 1}]
    with sim_daemon(faults=faults) as dp:
        run = dp.run_and_wait("align")
        assert_end_state(dp, run, verdicts=["fault"], reason_has=["platform", "socket://"],
                         stopped=False)
        deadline = time.monotonic() + 10  # the unreachable stages finish their bounded move
        while any(s["moving"] for s in dp.snapshot().values()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(s["moving"] for s in dp.snapshot().values())
        events = " ".join(e["msg"] for e in run["events"])
        assert "positions after stop" in events and "x=unknown" in events
        st = dp.client.status()
        assert st["state"] == "fault" and "platform" in st["fault"]


# ---- 1. no reply ----------------------------------------------------------------------------
def test_no_reply_mid_run_is_bounded_stops_and_names_device_port_command() -> None:
    # mute from the TE acknowledging the 2nd move on: every later reply is lost
    faults = [{"device": "turntable", "kind": "no_reply", "on": "TE", "following": "PA",
               "nth": 2, "count": 0}]
    with sim_daemon(faults=faults, reply_timeout_s=0.5) as dp:
        t0 = time.monotonic()
        run = dp.run_and_wait("check")
        elapsed = time.monotonic() - t0
        assert_end_state(dp, run, verdicts=["fault"],
                         reason_has=["no reply", "device turntable", "port socket://127.0.0.1:",
                                     "command '1"])
        assert elapsed < 15  # bounded retries, not a hang
        assert [t for t in targets(dp.target_log) if t["axis"] == "turntable"]  # it had moved
        stops = [r for r in dp.target_log.read_text().splitlines() if '"stop"' in r]
        assert stops  # the stop reached the controller, although its replies did not return
        assert dp.client.status()["state"] == "fault"


# ---- 5. a port held by another process -------------------------------------------------------
_HOLDER = r"""
import sys, time, serial
s = serial.serial_for_url(sys.argv[1], do_not_open=True)
s.exclusive = True
s.open()
print("held", flush=True)
time.sleep(60)
"""


def test_port_held_by_another_process_is_a_clear_start_up_failure() -> None:
    platform = CONTROLLERS["platform"]
    rig = SimRig([platform], [], SimConfig(time_scale=50.0), transport="pty").start()
    url = rig.url("platform")
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, url], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        ports = {"platform": url}
        with sim_daemon(controllers=[
                {**c.model_dump(mode="json"), "port": ports.get(c.name, "sim")}
                for c in CFG.controllers]) as dp:
            st = dp.wait_state("fault")
            assert "held by another process" in st["fault"] and url in st["fault"]
            assert "platform" in st["fault"]
            with pytest.raises(Exception, match="faulted"):
                dp.client.start("align")
            assert dp.client.history() == []
            holder.kill()
            holder.wait()
            dp.client.reset()  # the operator freed the port
            assert dp.wait_state("idle", "fault")["state"] == "idle"
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait()
        rig.stop()
    with pytest.raises(PortBusyError):  # and the driver's own error, for the record
        rig2 = SimRig([platform], [], SimConfig(time_scale=50.0), transport="pty").start()
        try:
            from drivers.transport import SerialTransport

            a = SerialTransport(rig2.url("platform"), device="platform")
            b = SerialTransport(rig2.url("platform"), device="platform")
            a.open()
            try:
                b.open()
            finally:
                a.close()
        finally:
            rig2.stop()

