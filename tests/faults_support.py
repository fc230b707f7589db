"""Shared set-up of the fault-tolerance tests (issue 6): configs with injected faults, the
real ``alignd`` in a subprocess on the simulated rig, and the end-state checks.

The daemon subprocess is the real ``alignd.daemon.main`` with the real ``open_rig``: the
emulators serve on loopback TCP ports and the real drivers talk to them. Two things differ
from ``alignd --config``, both test-only and outside the production API:

- the measuring tools are the stand-ins of the procedure tests (the simulated world's
  projected corners + seeded noise, the real solver) and the cameras are the simulator's
  non-rendering ``SceneCamera``s: the scenarios are about faults, not vision, and must be
  fast (``FAULTS_TOOLS=real`` uses the real vision on rendered frames instead);
- a snapshot socket (``$FAULTS_SIM_SOCKET``) answers, from inside the process, whether each
  simulated axis is moving and where it is, so a test can assert "every axis stopped"
  while the daemon keeps the ports.

Every target the emulators receive is appended to ``sim.target_log`` (JSON lines) by the
emulators themselves; ``targets()`` reads it back, also after a SIGKILL.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from alignd.client import Client
from alignd.config import AligndConfig, load_config
from alignd.store import Store

REPO = Path(__file__).resolve().parents[1]
SIM_YAML = REPO / "configs" / "sim.yaml"
HERE = Path(__file__).resolve()
FAST_PROCEDURE = {"sweep_steps": 5, "max_iterations": 2, "sweep_deg": 5.0}
SWEEP_CHECKS_PROCEDURE = {"sweep_steps": 5, "max_iterations": 1, "sweep_deg": 5.0}


def thread_count(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/task"))


def threads_settled(pid: int, at_most: int, timeout_s: float = 15.0) -> int:
    """The process' thread count once it is at most ``at_most``, or the count when
    ``timeout_s`` has passed: threads that serve a finished request end on their own time,
    so a test waits for the count instead of sleeping a fixed while."""
    deadline = time.monotonic() + timeout_s
    n = thread_count(pid)
    while n > at_most and time.monotonic() < deadline:
        time.sleep(0.05)
        n = thread_count(pid)
    return n


# ---- configs ---------------------------------------------------------------------------
def short_tmp() -> Path:
    d = Path(tempfile.mkdtemp(prefix="af-", dir="/tmp"))  # AF_UNIX paths must be short
    d.chmod(0o755)
    return d


def write_config(tmp: Path, *, faults: Iterable[dict[str, Any]] = (),
                 procedure: dict[str, Any] | None = None, time_scale: float = 200.0,
                 name: str = "config.yaml", seed: int = 3, reply_timeout_s: float | None = None,
                 **top: Any) -> tuple[Path, AligndConfig]:
    """The reference sim config with small sweeps, a fast clock, a target log and faults."""
    data = yaml.safe_load(SIM_YAML.read_text())
    for c in data["controllers"]:  # far above a busy host's scheduling delays
        c["reply_timeout_s"] = 1.0 if reply_timeout_s is None else reply_timeout_s
    data["procedure"].update(FAST_PROCEDURE if procedure is None else procedure)
    data["sim"].update(time_scale=time_scale, seed=seed, faults=list(faults),
                       target_log=str(tmp / "targets.jsonl"))
    data["daemon"]["operator_group"] = None
    data.update(top)
    path = tmp / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path, load_config(path)


# ---- the emulators' target log ----------------------------------------------------------
def log_lines(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    return [json.loads(ln) for ln in path.read_text().splitlines() if ln.strip()]


def targets(path: Path, pid: int | None = None) -> list[dict[str, Any]]:
    return [r for r in log_lines(path) if r["event"] == "target"
            and (pid is None or r["pid"] == pid)]


def soft_limit_violations(path: Path, cfg: AligndConfig) -> list[dict[str, Any]]:
    """Targets (accepted or refused by the firmware) outside the configured soft limits."""
    limits = {a.role: a.soft_limits for c in cfg.controllers for a in c.axes}
    bad = []
    for r in targets(path):
        lim = limits[r["axis"]]
        t = r["target"]
        if not (isinstance(t, float) and lim.min - 1e-9 <= t <= lim.max + 1e-9):
            bad.append(r)
    return bad


# ---- the daemon subprocess ---------------------------------------------------------------
@dataclass
class DaemonProc:
    """``alignd`` (this module's ``__main__``) on the simulated rig, in a subprocess."""

    tmp: Path
    config: Path
    cfg: AligndConfig
    seed: int = 3
    env: dict[str, str] = field(default_factory=dict)
    proc: subprocess.Popen[bytes] | None = None
    sock: Path = field(init=False)
    sim_sock: Path = field(init=False)
    state: Path = field(init=False)
    log: Path = field(init=False)
    target_log: Path = field(init=False)

    def __post_init__(self) -> None:
        self.sock = self.tmp / "alignd.sock"
        self.sim_sock = self.tmp / "sim.sock"
        self.state = self.tmp / "state"
        self.log = self.tmp / "alignd.log"
        self.target_log = Path(self.cfg.sim.target_log)  # type: ignore[union-attr, arg-type]
        self.client = Client(self.sock, timeout_s=10.0)

    def start(self, wait: bool = True, *extra: str) -> DaemonProc:
        with open(self.log, "ab") as errf:
            self.proc = subprocess.Popen(
                [sys.executable, str(HERE), "--config", str(self.config), "--socket",
                 str(self.sock), "--state-dir", str(self.state), "--seed", str(self.seed),
                 "--stop-timeout", "5", *extra],
                stdout=subprocess.DEVNULL, stderr=errf, cwd=REPO,
                env={**os.environ, "FAULTS_SIM_SOCKET": str(self.sim_sock), **self.env})
        if wait:
            self.wait_state("idle", "fault")
        return self

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def stderr(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def wait_state(self, *states: str, timeout_s: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        last: Any = None
        while time.monotonic() < deadline:
            assert self.proc is not None
            if self.proc.poll() is not None:
                raise AssertionError(f"alignd exited with {self.proc.returncode}:\n"
                                     f"{self.stderr()[-3000:]}")
            try:
                last = self.client.status()
                if last["state"] in states:
                    return last
            except Exception as exc:  # not listening yet
                last = exc
            time.sleep(0.05)
        raise AssertionError(f"alignd not in {states} within {timeout_s} s: {last}\n"
                             f"{self.stderr()[-3000:]}")

    def snapshot(self) -> dict[str, dict[str, Any]]:
        """The simulated axes as the simulator sees them (moving, position, flags)."""
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(5.0)
            s.connect(str(self.sim_sock))
            data = b""
            while chunk := s.recv(65536):
                data += chunk
        return json.loads(data)

    def run_and_wait(self, kind: str, timeout_s: float = 60.0,
                     started_by: str = "user") -> dict[str, Any]:
        run_id = self.client.start(kind, started_by=started_by)["run_id"]
        return self.wait_run(run_id, timeout_s)

    def wait_run(self, run_id: int, timeout_s: float = 60.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        after = 0
        while time.monotonic() < deadline:
            r = self.client.events(run_id, after=after, wait_s=1.0)
            after = r["next"]
            if r["done"]:
                return self.client.run(run_id)
        raise AssertionError(f"run {run_id} did not end within {timeout_s} s\n"
                             f"{self.stderr()[-3000:]}")

    def terminate(self, timeout_s: float = 10.0) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout=timeout_s)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=10)


@contextlib.contextmanager
def sim_daemon(*, faults: Iterable[dict[str, Any]] = (), procedure: dict[str, Any] | None = None,
               time_scale: float = 200.0, seed: int = 3, env: dict[str, str] | None = None,
               wait: bool = True, reply_timeout_s: float | None = None,
               args: Iterable[str] = (), **top: Any) -> Iterator[DaemonProc]:
    tmp = short_tmp()
    path, cfg = write_config(tmp, faults=faults, procedure=procedure, time_scale=time_scale,
                             seed=seed, reply_timeout_s=reply_timeout_s, **top)
    dp = DaemonProc(tmp, path, cfg, seed=seed, env=env or {})
    try:
        yield dp.start(wait, *args)
    finally:  # SIGKILL: a graceful exit is scenario 15's business, and waiting costs time
        dp.kill()
        shutil.rmtree(tmp, ignore_errors=True)


# ---- the end state of every scenario --------------------------------------------------------
def assert_end_state(dp: DaemonProc, run: dict[str, Any], *, verdicts: Iterable[str],
                     reason_has: Iterable[str] = (), stopped: bool = True) -> None:
    """Every axis stopped, the run recorded with a clear reason, the database sound, the
    daemon answering, no target outside the soft limits."""
    assert run["status"] == "finished", run
    assert run["verdict"] in set(verdicts), (run["verdict"], run["reason"])
    for text in reason_has:
        assert text in (run["reason"] or ""), (text, run["reason"])
    if run["verdict"] not in ("aligned", "within_tolerance"):
        assert run["reason"], run
    if os.environ.get("FAULTS_OUTCOMES"):  # the docs' "observed outcome" column
        with open(os.environ["FAULTS_OUTCOMES"], "a") as f:
            f.write(json.dumps({"test": os.environ.get("PYTEST_CURRENT_TEST", "?"),
                                "verdict": run["verdict"], "reason": run["reason"]}) + "\n")
    if stopped:
        snap = dp.snapshot()
        assert not [r for r, s in snap.items() if s["moving"]], snap
    assert Store(dp.state).integrity_check() == ["ok"]
    assert dp.client.status()["state"] in ("idle", "fault")
    assert soft_limit_violations(dp.target_log, dp.cfg) == []


# ---- the subprocess entry -----------------------------------------------------------------------
_SIM: dict[str, Any] = {}


def _serve_snapshots(path: str) -> None:
    """Sim-only: report the simulated axes' state to the test over a Unix socket."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(4)

    def loop() -> None:
        while True:
            conn, _ = srv.accept()
            with conn:
                sim = _SIM.get("rig")
                snap = {} if sim is None else {
                    role: {"moving": ax.moving, "position": ax.motor_position(),
                           "homed": ax.homed, "stalled": ax.stalled,
                           "limit_low": ax.limit_low, "limit_high": ax.limit_high,
                           "targets": len(ax.targets)}
                    for role, ax in sim.axes.items()}
                conn.sendall(json.dumps(snap).encode())

    threading.Thread(target=loop, name="faults-snapshot", daemon=True).start()


def standin_tools(seed: int) -> Any:
    import numpy as np

    from alignd import solve as solver
    from alignd.procedures.tools import Corners, Tools, as_corners
    from drivers.sim.direct import scene_tracker

    tracker = scene_tracker(0.01, np.random.default_rng(seed + 1000))

    def track(frame: Any) -> Corners:
        if "corners_px" not in frame.metadata:
            return Corners(np.full((4, 2), np.nan), False, 0.0, "not a scene frame")
        return as_corners(tracker(frame))

    def solve(angles: Any, points: Any, px: float | None) -> Any:
        return solver.solve_centre(solver.Sweep(np.asarray(angles), np.asarray(points), px))

    def tilt(frame: Any) -> float:
        return float(frame.metadata["tilt_deg"])

    return Tools(track=track, solve=solve, tilt=tilt, eccentricity=None,
                 names={"track": "stand-in (scene corners)", "solve": "alignd.solve"})


def main(argv: list[str]) -> int:
    from alignd import daemon as daemon_mod
    from alignd.hardware import open_rig
    from alignd.procedures.align import run_alignment, run_check
    from drivers.sim.direct import SceneCamera

    args = daemon_mod.build_parser().parse_args(argv)
    real = os.environ.get("FAULTS_TOOLS") == "real"
    if os.environ.get("FAULTS_SIM_SOCKET"):
        _serve_snapshots(os.environ["FAULTS_SIM_SOCKET"])
    if os.environ.get("FAULTS_DISK_FULL_FLAG"):  # sim-only: a disk that fills up on demand
        flag = Path(os.environ["FAULTS_DISK_FULL_FLAG"])
        real_statvfs = os.statvfs

        def statvfs(path: Any) -> Any:
            st = real_statvfs(path)
            if not flag.exists():
                return st
            return os.statvfs_result((st.f_bsize, st.f_frsize, st.f_blocks, 10, 10,
                                      *tuple(st)[5:]))

        os.statvfs = statvfs  # type: ignore[assignment]
    if os.environ.get("FAULTS_REQUEST_TIMEOUT_S"):  # a stalled request is cut sooner
        daemon_mod.ApiServer = functools.partial(  # type: ignore[misc]
            daemon_mod.ApiServer, request_timeout_s=float(os.environ["FAULTS_REQUEST_TIMEOUT_S"]))

    def rig_factory(cfg: AligndConfig) -> Any:
        rig = open_rig(cfg, seed=args.seed)
        sim = rig.on_close[0].__self__  # type: ignore[attr-defined]  # SimRig.stop's rig
        _SIM["rig"] = sim
        if not real:
            rig.cameras = {role: SceneCamera(sim.world, role) for role in rig.cameras}
        return rig

    procedures = None
    if not real:
        tools = standin_tools(args.seed or 0)
        procedures = {"align": functools.partial(run_alignment, tools=tools),
                      "check": functools.partial(run_check, tools=tools)}
    return daemon_mod.main(argv, rig_factory=rig_factory, procedures=procedures)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
