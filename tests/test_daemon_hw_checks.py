"""The daemon checks its cameras at start and after reset, and keeps the systemd watchdog
fed while an axis waits for a long homing (issue 9).

Deterministic: the camera test uses cameras that fail on purpose; the watchdog test runs
a real Zaber driver against its emulator on a manual clock (every driver poll advances the
simulated time by one poll interval) and reads the daemon's ``WATCHDOG=1`` datagrams from
a real notify socket at every poll, so the gaps are measured in simulated seconds.
"""

from __future__ import annotations

import contextlib
import shutil
import socket
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from daemon_fakes import SIM_CONFIG, FakeResult, short_tmp, wait_until

from alignd.api import Peer
from alignd.config import load_config
from alignd.daemon import Daemon, Notifier
from alignd.procedures.rig import Rig
from drivers.camera import Camera, Frame
from drivers.config import ControllerConfig
from drivers.errors import CameraError
from drivers.sim.clock import ManualClock
from drivers.sim.kinematics import SimAxis
from drivers.sim.server import EmulatorServer
from drivers.sim.zaber_emu import ZaberEmulator, physics_for
from drivers.zaber_ascii import make_axes

ROOT_PEER = Peer(pid=1, uid=0, gid=0)


class BenchCamera(Camera):
    """A camera that gives a frame, or none (``broken``), counting its grabs."""

    def __init__(self, role: str, source: str, broken: str = "") -> None:
        super().__init__(role, source)
        self.broken = broken  # "open" | "grab" | ""
        self.grabs = 0

    def open(self) -> None:
        if self.broken == "open":
            raise CameraError("cannot open the device", device=self.name, port=self.source)

    def close(self) -> None:
        pass

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        self.grabs += 1
        if self.broken == "grab":
            raise CameraError("no frame within 2 s", device=self.name, port=self.source)
        return Frame(np.zeros((48, 64), np.uint8), 0.0, self.grabs)


@contextlib.contextmanager
def daemon_with(rig_factory: Any, procedures: dict[str, Any] | None = None,
                notifier: Notifier | None = None) -> Iterator[Daemon]:
    tmp = short_tmp()
    from alignd.store import Store

    store = Store(tmp / "state").open()
    daemon = Daemon(load_config(SIM_CONFIG), store, rig_factory, procedures=procedures or {},
                    notifier=notifier, stop_timeout_s=5.0)
    daemon.start()
    try:
        yield daemon
    finally:
        daemon.stop()
        store.close()
        shutil.rmtree(tmp, ignore_errors=True)


@pytest.mark.parametrize("how", ["grab", "open"])
def test_a_camera_without_frames_faults_at_start_and_reset_rechecks(how: str) -> None:
    top = BenchCamera("top", "/dev/video0")
    side = BenchCamera("side", "/dev/v4l/by-id/usb-side-cam", broken=how)

    def factory(_cfg: Any) -> Rig:
        return Rig(axes={}, cameras={"top": top, "side": side})

    with daemon_with(factory) as d:
        wait_until(lambda: d.state == "fault", timeout_s=10)
        st = d.status()
        assert "camera side (source /dev/v4l/by-id/usb-side-cam)" in st["fault"] or \
            ("device side" in st["fault"] and "/dev/v4l/by-id/usb-side-cam" in st["fault"])
        assert st["cameras"]["side"]["state"] == "fault"
        assert st["cameras"]["side"]["source"] == "/dev/v4l/by-id/usb-side-cam"
        assert "cannot open" in st["cameras"]["side"]["error"] or \
            "no frame" in st["cameras"]["side"]["error"]
        grabs = top.grabs
        assert (grabs, st["cameras"]["top"]["state"]) == ((1, "ok") if how == "grab"
                                                          else (0, "not checked"))
        side.broken = ""  # plugged back in
        d.reset(ROOT_PEER)
        wait_until(lambda: d.state == "idle", timeout_s=10)
        st = d.status()
        assert top.grabs == grabs + 1 and side.grabs >= 1  # one frame each after reset
        assert {r: (c["state"], c["size"]) for r, c in st["cameras"].items()} == {
            "top": ("ok", [64, 48]), "side": ("ok", [64, 48])}


def test_status_text_lists_cameras_and_their_state() -> None:
    from alignd.cli.daemon_cmds import status_text

    text = status_text({"version": "x", "name": "rig", "socket": "/s", "state": "fault",
                        "fault": "cannot open the rig: …",
                        "cameras": {"top": {"source": "/dev/video0", "state": "ok",
                                            "size": [1280, 720], "error": None},
                                    "side": {"source": "/dev/video2", "state": "fault",
                                             "size": None, "error": "no frame within 2 s"}}})
    assert "camera side   fault       source /dev/video2: no frame within 2 s" in text
    assert "camera top    ok          source /dev/video0: 1280x720" in text


# ---- the watchdog during a slow homing ----------------------------------------------------
class NotifySocket:
    """systemd's end of ``$NOTIFY_SOCKET``: a datagram socket the test reads."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.setblocking(False)

    def pings(self) -> int:
        n = 0
        while True:
            try:
                msg = self.sock.recv(4096).decode()
            except BlockingIOError:
                return n
            n += "WATCHDOG=1" in msg.split("\n")


def test_watchdog_is_fed_through_a_slow_homing_of_three_axes() -> None:
    """Three X-LSM axes homing at 0.2 mm/s from mid-travel: about 125 s each, 375 s in
    all, with WatchdogSec=60. Every poll of the driver reads the notify socket."""
    clock = ManualClock()
    axis_cfgs = [{"role": r, "address": i + 1, "units": "mm", "stage": "X-LSM050A",
                  "soft_limits": {"min": 2.0, "max": 48.0}, "speed": 0.2, "accel": 20.0,
                  "home_timeout_s": 200.0, "poll_interval_s": 1.0, "stall_timeout_s": 30.0}
                 for i, r in enumerate("xyz")]
    sims = {}
    for i, a in enumerate(axis_cfgs):
        ctl = ControllerConfig(name="p", protocol="zaber", port="sim", axes=[a])  # type: ignore[list-item]
        sims[i + 1] = SimAxis(str(a["role"]), physics_for(ctl.axes[0]), clock,
                              np.random.default_rng(i), start=25.0)
    emu = ZaberEmulator("platform", sims, clock)
    tmp = short_tmp()
    notify = NotifySocket(tmp / "notify")
    gaps: list[float] = []
    last = {"ping": 0.0}

    def poll_sleep(dt: float) -> None:  # the driver's wait: note pings, advance sim time
        if notify.pings():
            gaps.append(clock.now() - last["ping"])
            last["ping"] = clock.now()
        clock.advance(dt)

    notifier = Notifier(env={"NOTIFY_SOCKET": str(notify.path), "WATCHDOG_USEC": "60000000"},
                        clock=clock.now)
    homed = threading.Event()

    def home_all(rig: Rig, cfg: Any, *, progress: Any, abort: Any, recorder: Any,
                 run_id: str, commission: Any = None) -> Any:
        rig.home_where_required(["x", "y", "z"], park_mid=False)
        homed.set()
        return FakeResult("within_tolerance", (0.0, 0.0), 1.0, 1)

    with EmulatorServer(emu, "tcp") as srv:
        ctl = ControllerConfig(name="platform", protocol="zaber", port=srv.url,
                               axes=axis_cfgs)  # type: ignore[arg-type]

        class PollClock:
            """The simulation's time; every driver wait notes pings, then advances it."""

            now = staticmethod(clock.now)
            sleep = staticmethod(poll_sleep)

        def factory(_cfg: Any) -> Rig:
            axes = make_axes(ctl, clock=PollClock())
            return Rig(axes={a.config.role: a for a in axes}, cameras={})

        with daemon_with(factory, {"check": home_all}, notifier) as d:
            wait_until(lambda: d.state == "idle", timeout_s=20)
            d.start_run("check", "user", ROOT_PEER)
            assert homed.wait(120)
            wait_until(lambda: d.state != "checking", timeout_s=20)
            assert d.status()["last_run"]["verdict"] == "within_tolerance"
    notify.sock.close()
    shutil.rmtree(tmp, ignore_errors=True)
    assert all(s.homed for s in sims.values())
    assert clock.now() > 3 * 100.0  # the homing really took minutes of simulated time
    gaps.append(clock.now() - last["ping"])
    # pinged at least every quarter of WatchdogSec (+ one poll), never near 60 s
    assert max(gaps) <= 60.0 / 4 + 1.0, max(gaps)


def test_identity_warnings_at_connect_show_in_status() -> None:
    """An SMC100 answering URS100BCC where the config says URS75BCC: the daemon runs, and
    ``status`` carries the warning naming both."""
    from drivers.newport_smc100 import make_axes as smc100_axes
    from drivers.sim.smc100_emu import Smc100Emulator
    from drivers.sim.smc100_emu import physics_for as smc100_physics

    clock = ManualClock()
    cfg = {"role": "turntable", "address": 1, "units": "deg", "stage": "URS75BCC",
           "soft_limits": {"min": -30.0, "max": 30.0}}
    ctl0 = ControllerConfig(name="turntable", protocol="smc100", port="sim",
                            axes=[cfg])  # type: ignore[list-item]
    sim = SimAxis("tt", smc100_physics(ctl0.axes[0]), clock, np.random.default_rng(0))
    emu = Smc100Emulator("turntable", {1: sim}, clock, stage="URS100BCC")
    with EmulatorServer(emu, "tcp") as srv:
        ctl = ctl0.model_copy(update={"port": srv.url})

        def factory(_cfg: Any) -> Rig:
            (axis,) = smc100_axes(ctl)
            return Rig(axes={"turntable": axis}, cameras={})

        with daemon_with(factory) as d:
            wait_until(lambda: d.state == "idle", timeout_s=20)
            assert d.status()["warnings"] == [
                "turntable: controller reports stage 'URS100BCC' where the config says "
                "'URS75BCC' (same units and travel as far as known); check the config"]


def test_a_run_requested_before_the_worker_thread_runs_is_starting_not_a_fault() -> None:
    """The API listens a moment before the worker thread starts (found by ``make demo``
    under load: "the hardware worker is not running"); such a request is "starting", which
    ``alignctl`` waits out."""
    from alignd.api import Refused
    from alignd.store import Store

    tmp = short_tmp()
    store = Store(tmp / "state").open()
    try:
        d = Daemon(load_config(SIM_CONFIG), store, lambda _cfg: Rig(axes={}, cameras={}),
                   procedures={"check": lambda *a, **k: None})
        with pytest.raises(Refused) as err:
            d.start_run("check", "user", ROOT_PEER)
        assert (err.value.code, err.value.http_status) == ("starting", 409)
    finally:
        store.close()
        shutil.rmtree(tmp, ignore_errors=True)
