"""Stand-ins for the hardware and the procedures, for the daemon/API/store tests.

The daemon only needs a rig with ``identities``, ``axes``, ``stop_all()``, ``close()`` and
``truth``, and procedures with the signature ``(rig, cfg, *, progress, abort, recorder,
run_id) -> result`` (``alignd.daemon.Procedure``).
These fakes record what the daemon did to them (stops, closes) so tests can assert it.
Also used by ``run_fake_daemon`` in a subprocess (SIGTERM/SIGKILL tests).
"""

from __future__ import annotations

import contextlib
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from alignd.api import ApiServer, Authoriser
from alignd.client import Client
from alignd.config import load_config
from alignd.daemon import Daemon
from alignd.procedures.events import ProgressEvent
from alignd.store import Store
from drivers.axis import Identity

SIM_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "sim.yaml"


@dataclass
class FakeAxis:
    pos: float = 12.5
    broken: bool = False

    def position(self) -> float:
        if self.broken:
            raise OSError("port vanished")
        return self.pos


@dataclass
class FakeRig:
    identities: dict[str, Identity] = field(default_factory=lambda: {
        "turntable": Identity("Newport", "SMC100", "FAKE1", "1.0", "URS75BCC"),
        "x": Identity("Zaber", "X-LSM050A", "FAKE2", "7.0")})
    axes: dict[str, FakeAxis] = field(default_factory=lambda: {
        "turntable": FakeAxis(-3.25), "x": FakeAxis(25.0, broken=True)})
    stops: int = 0
    closed: bool = False
    fail_stop: bool = False

    def stop_all(self) -> list[str]:
        self.stops += 1
        return ["x: stop failed (fake)"] if self.fail_stop else []

    def close(self) -> None:
        self.closed = True

    def truth(self) -> dict[str, Any]:
        return {"offset_um": [1.0, -2.0], "offset_norm_um": 2.236}


@dataclass
class FakeResult:
    verdict: str
    offset_um: tuple[float, float]
    U_um: float
    iterations: int
    reason: str = ""
    config_error: bool = False
    details: dict[str, Any] | None = None

    def to_json(self) -> dict[str, Any]:
        return {"verdict": self.verdict, "offset_um": list(self.offset_um),
                "offset_norm_um": float(np.hypot(*self.offset_um)), "U_um": self.U_um,
                "iterations": self.iterations, "tilt_deg": 0.01, "yaw_deg": 1.5,
                "reason": self.reason}


def make_procedure(verdict: str = "aligned", *, steps: int = 5, iterations: int = 2,
                   gate: threading.Event | None = None, raise_exc: Exception | None = None,
                   step_sleep_s: float = 0.0) -> Any:
    """A procedure that reports progress, records a sweep, iteration, frame and event each
    iteration, optionally blocks on ``gate`` (until set or aborted), then returns."""

    def proc(rig: Any, cfg: Any, *, progress: Any, abort: threading.Event,
             recorder: Any, run_id: str, commission: Any = None) -> FakeResult:
        offsets = [(800.0 / 4**i, -300.0 / 4**i) for i in range(iterations + 1)]
        for it in range(iterations):
            angles = np.linspace(-10, 10, steps)
            frames = []
            hashes = []
            for k, a in enumerate(angles):
                if abort.is_set():
                    return FakeResult("aborted", offsets[it], 5.0, it,
                                      getattr(abort, "reason", None) or "abort")
                progress(ProgressEvent("sweep", "frame", step=k + 1, total=steps,
                                       iteration=it + 1))
                frames.append({"angle_deg": float(a),
                               "features": [[60.0 + k, 30.0], [70.0 + k, 30.0], None,
                                            [60.0 + k, 40.0]]})
                # a frame per step, labelled as the procedures do; a bar marks step/iteration
                img = np.zeros((72, 128), np.uint8)
                img[10 + k, 10 + 20 * it:20 + 20 * it] = 255
                hashes.append(recorder.frame(img, f"measure-{it + 1}-{k:03d}-0"))
                if step_sleep_s:
                    time.sleep(step_sleep_s)
            recorder.sweep("measure", it + 1, {"version": 1, "pixel_size_um": 160.0,
                                               "frames": frames},
                           list(angles), list(angles + 0.001))
            recorder.iteration(it + 1, {"offset_um": offsets[it], "U_um": 5.0,
                                        "centre_px": [64.0, 36.0],
                                        "cov_centre_px2": [[0.04, 0.0], [0.0, 0.09]],
                                        "offset_px": [-4.0, -6.0], "frame": hashes[0]})
            recorder.event(f"iteration {it + 1} done")
            progress(ProgressEvent("move", "correcting", iteration=it + 1,
                                   offset_um=offsets[it],
                                   offset_norm_um=float(np.hypot(*offsets[it])), U_um=5.0))
            if gate is not None:
                while not gate.wait(0.01):
                    if abort.is_set():
                        return FakeResult("aborted", offsets[it], 5.0, it + 1,
                                          getattr(abort, "reason", None) or "abort")
            if raise_exc is not None:
                raise raise_exc
        return FakeResult(verdict, offsets[-1], 5.0, iterations,
                          "" if verdict in ("aligned", "within_tolerance") else verdict)

    return proc


@dataclass
class Env:
    daemon: Daemon
    server: ApiServer
    client: Client
    rig: FakeRig
    store: Store
    sock: str
    gate: threading.Event


def short_tmp() -> Path:
    d = Path(tempfile.mkdtemp(prefix="ad-", dir="/tmp"))  # AF_UNIX paths are short
    d.chmod(0o755)
    return d


def make_env(procs: dict[str, Any] | None = None, *, rig_factory: Any = None,
             authoriser: Authoriser | None = None, config_path: Path | None = None,
             **server_kw: Any) -> Iterator[Env]:
    tmp = short_tmp()
    cfg = load_config(config_path or SIM_CONFIG)
    store = Store(tmp / "state").open()
    gate = threading.Event()
    rig = FakeRig()
    procs = procs or {"align": make_procedure("aligned", gate=gate),
                      "check": make_procedure("within_tolerance", gate=gate)}
    daemon = Daemon(cfg, store, rig_factory or (lambda _cfg: rig), procedures=procs,
                    socket_path=str(tmp / "s.sock"), stop_timeout_s=5.0,
                    config_path=config_path)
    server = ApiServer(tmp / "s.sock", daemon, authoriser or Authoriser(None), **server_kw)
    server.start()
    daemon.start()
    env = Env(daemon, server, Client(tmp / "s.sock", timeout_s=5.0), rig, store,
              str(tmp / "s.sock"), gate)
    try:
        yield env
    finally:
        gate.set()
        daemon.stop()
        server.stop()
        store.close()
        shutil.rmtree(tmp, ignore_errors=True)


def wait_until(pred: Any, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.01)


def follow(client: Client, run_id: int) -> dict[str, Any]:
    after, events = 0, []
    while True:
        r = client.events(run_id, after=after, wait_s=2.0)
        events += r["events"]
        after = r["next"]
        if r["done"]:
            return {**r, "events": events}


def fill_disk(rig: Any, cfg: Any, *, progress: Any, abort: threading.Event,
              recorder: Any, run_id: str, commission: Any = None) -> FakeResult:
    """A run that records incompressible 64 KiB frames until the disk is full (the store
    raises) or it is aborted."""
    from alignd.store import StoreError

    rng = np.random.default_rng(5)
    k = 0
    try:
        while not abort.is_set():
            recorder.frame(rng.integers(0, 256, (256, 256), dtype=np.uint8),
                           f"measure-1-{k:03d}-0")
            k += 1
    except StoreError:
        # the disk is full for every writer now (as when a log fills it): take the last
        # bytes too, so that what the failed frame file gave back does not save the day
        filler = recorder.store.state_dir.parent / "filler"
        with open(filler, "ab", buffering=0) as f, contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 4096)
        raise
    return FakeResult("aborted", (0.0, 0.0), 5.0, 0, "aborted")


def run_fake_daemon(argv: list[str], mode: str) -> int:
    """Entry for the subprocess tests: the real ``alignd`` main with a fake rig.

    mode ``block``: runs block until aborted (SIGTERM/SIGKILL tests); ``quick``: finish;
    ``fill``: an align fills the disk, a check finishes.
    """
    from alignd.daemon import main

    gate = None if mode in ("quick", "fill") else threading.Event()
    procs = {"align": make_procedure("aligned", gate=gate),
             "check": make_procedure("within_tolerance", gate=gate)}
    if mode == "fill":
        procs["align"] = fill_disk
    return main(argv, rig_factory=lambda _cfg: FakeRig(), procedures=procs)


if __name__ == "__main__":
    sys.exit(run_fake_daemon(sys.argv[2:], sys.argv[1]))


OBSERVER_SCRIPT = r"""
import json, socket, sys
def req(method, path, body=""):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(5)
    s.connect(sys.argv[1])
    data = body.encode()
    s.sendall(f"{method} {path} HTTP/1.1\r\nHost: x\r\nContent-Length: {len(data)}\r\n\r\n"
              .encode() + data)
    out = b""
    while chunk := s.recv(65536):
        out += chunk
    return int(out.split(b" ")[1]), json.loads(out.split(b"\r\n\r\n", 1)[1])
print(json.dumps([req(*r) for r in json.loads(sys.argv[2])]))
"""


def _system_python() -> str:
    import shutil as _shutil

    return _shutil.which("python3", path="/usr/bin:/bin") or "/usr/bin/python3"


def as_observer(sock: object, requests: list[tuple[str, str, str]],
                groups: list[int] | None = None) -> list[list[object]]:
    """Send ``requests`` to the daemon from a process running as ``nobody`` (uid 65534):
    an observer, in no group but ``groups`` (its supplementary groups, which the group
    database does not know about). Returns ``[[status, reply], ...]``."""
    import json as _json
    import subprocess as _subprocess

    out = _subprocess.run([_system_python(), "-c", OBSERVER_SCRIPT, str(sock),
                           _json.dumps(requests)],
                          user=65534, group=65534, extra_groups=groups or [],
                          capture_output=True, text=True, timeout=20, cwd="/")
    assert out.returncode == 0, out.stderr
    return _json.loads(out.stdout)


HOLDER_SCRIPT = r"""
import socket, sys
held = []
for request in sys.argv[2:]:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.connect(sys.argv[1])
    try:
        s.sendall(request.encode())
    except OSError:  # refused (503) and closed before we sent
        pass
    held.append(s)
print(len(held), flush=True)
sys.stdin.read()  # hold every connection until the test closes our stdin
"""


class Holder:
    """A process running as ``nobody`` that opens a connection per request text (a partial
    request: an idle connection; a long poll: a slow one) and holds them all until closed."""

    def __init__(self, sock: object, requests: list[str]) -> None:
        import subprocess as _subprocess

        self.proc = _subprocess.Popen([_system_python(), "-c", HOLDER_SCRIPT, str(sock),
                                       *requests], user=65534, group=65534, extra_groups=[],
                                      stdin=_subprocess.PIPE, stdout=_subprocess.PIPE,
                                      text=True, cwd="/")
        assert self.proc.stdout is not None
        opened = self.proc.stdout.readline().strip()
        assert opened == str(len(requests)), opened

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=20)
