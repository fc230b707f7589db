"""``alignd``: the alignment daemon. One worker thread owns the hardware.

Why one worker: serial links and cameras are not safe to share, and a run is a sequence of
moves that must not interleave with another. The API threads only read state, queue a job
or set the abort event; every byte to a controller comes from the worker (the one
exception: if the worker does not stop within the stop timeout, the main thread stops the
axes itself, because a stopped stage matters more than ownership).

States: ``starting`` (connecting the rig), ``idle``, ``aligning``, ``checking``, ``fault``
(the hardware is in an unknown state: a run ended in a fault or the rig could not be
opened; ``POST /reset`` / ``alignctl reset`` re-reads the config file, validated first (a
bad file is refused with the reason and the old config stays), and reconnects). A run is
recorded in the store
before it is queued, so a run that cannot be recorded never starts. A run left ``running``
by a killed daemon is marked ``interrupted`` at the next start and never resumed.

systemd: ``Type=notify``: ``READY=1`` once the API listens, ``STATUS=`` with the state and
progress, ``WATCHDOG=1`` from the worker (so a hung worker gets the service restarted),
``STOPPING=1`` on SIGTERM, after which all axes are stopped within the stop timeout.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import logging
import math
import os
import queue
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from types import FrameType
from typing import Any, Literal, Protocol, TextIO, TypeGuard, get_args

from alignd import __version__
from alignd.api import ApiServer, Authoriser, Peer, Refused
from alignd.axis_readings import AxisReadings, tap_axes
from alignd.client import resolve_socket
from alignd.config import (
    AligndConfig,
    check_config_file,
    config_hash,
    frame_keeper,
    load_config,
    run_footprint,
)
from alignd.errors import AligndError, ConfigError, StateError
from alignd.logsetup import configure_logging
from alignd.procedures.commission import CommissionRecord
from alignd.procedures.events import ProgressCallback, ProgressEvent
from alignd.procedures.recorder import RunRecorder
from alignd.procedures.rig import AbortEvent, Rig
from alignd.store import SqliteRecorder, Store, StoreError, jsonable
from alignd.web.frames import LiveFrames, grab_previews, tap_cameras
from drivers.axis import Axis
from drivers.errors import CameraError
from drivers.tone_curves import curve_text, is_linear

log = logging.getLogger(__name__)

EXIT_OK, EXIT_USAGE, EXIT_FAULT = 0, 2, 3
DEFAULT_STOP_TIMEOUT_S = 10.0
CAMERA_CHECK_TIMEOUT_S = 5.0  # one frame from each camera at start and after reset
EVENT_BUFFER = 5000  # live progress events kept in memory (all runs)
State = Literal["starting", "idle", "aligning", "checking", "commissioning", "fault"]
STATES: tuple[State, ...] = get_args(State)
BUSY_STATES: tuple[State, ...] = ("aligning", "checking", "commissioning")
RunKind = Literal["align", "check", "commission"]
JobKind = Literal["align", "check", "commission", "reset"]
RUN_STATES: dict[str, State] = {"align": "aligning", "check": "checking",
                                "commission": "commissioning"}


def _is_run_kind(kind: str) -> TypeGuard[RunKind]:
    return kind in get_args(RunKind)


class ProcedureResult(Protocol):
    """What a procedure returns (``alignd.procedures.RunResult``)."""

    def to_json(self) -> dict[str, Any]:
        """The run-result contract object."""
        ...

    @property
    def config_error(self) -> bool:
        """The fault was caused by the config (alignctl exits 2)."""
        ...

    @property
    def details(self) -> dict[str, Any] | None:
        """The full record kept with the run."""
        ...


class Procedure(Protocol):
    """A run the daemon executes (``run_alignment``, ``run_check``, ``run_commission``).
    ``commission``: the latest valid commission record for align and check, else None."""

    def __call__(self, rig: Rig, cfg: AligndConfig, *, progress: ProgressCallback,
                 abort: threading.Event, recorder: RunRecorder, run_id: str,
                 commission: CommissionRecord | None) -> ProcedureResult: ...


RigFactory = Callable[[AligndConfig], Rig]  # config -> rig (connected, or by the daemon)


# ---- systemd notification -----------------------------------------------------------------
class Notifier:
    """sd_notify over ``$NOTIFY_SOCKET`` (a datagram socket; a no-op outside systemd)."""

    def __init__(self, env: Mapping[str, str] | None = None, watchdog: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        env = os.environ if env is None else env
        self._clock = clock
        addr = env.get("NOTIFY_SOCKET") or None
        if addr and addr.startswith("@"):
            addr = "\0" + addr[1:]  # abstract namespace
        self.address = addr
        self.watchdog_s: float | None = None
        usec, pid = env.get("WATCHDOG_USEC"), env.get("WATCHDOG_PID")
        if watchdog and usec and usec.isdigit() and (not pid or pid == str(os.getpid())):
            self.watchdog_s = int(usec) / 1e6
        self._last_ping = -math.inf
        self._last_status = ""

    def send(self, message: str) -> bool:
        if not self.address:
            return False
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as s:
                # never wait: a receiver whose queue is full (it is not reading) would
                # otherwise block the worker, and with it every stop
                s.setblocking(False)
                s.connect(self.address)
                s.sendall(message.encode())
            return True
        except BlockingIOError:
            log.debug("sd_notify to %r dropped (its queue is full): %r", self.address, message)
            return False
        except OSError as exc:
            log.warning("sd_notify to %r failed: %s", self.address, exc)
            return False

    def ready(self, status: str = "idle") -> None:
        self.send(f"READY=1\nSTATUS={status}\nMAINPID={os.getpid()}")

    def status(self, text: str) -> None:
        if text != self._last_status:
            self._last_status = text
            self.send(f"STATUS={text}")

    def stopping(self) -> None:
        self.send("STOPPING=1\nSTATUS=stopping")

    def watchdog(self) -> None:
        """Ping if due (at a quarter of the watchdog interval); cheap to call often."""
        if self.watchdog_s is None:
            return
        now = self._clock()
        if now - self._last_ping >= self.watchdog_s / 4:
            self._last_ping = now
            self.send("WATCHDOG=1")

    @property
    def tick_s(self) -> float:
        """How often an idle worker must wake to keep the watchdog fed."""
        return 1.0 if self.watchdog_s is None else max(0.05, min(1.0, self.watchdog_s / 4))


# ---- the worker's jobs --------------------------------------------------------------------
@dataclass
class _Job:
    kind: JobKind
    run_id: int | None = None
    started_by: str = "user"
    user: str | None = None
    abort: AbortEvent = field(default_factory=AbortEvent)
    config: AligndConfig | None = None  # reset: the config to reconnect with


def _result_dict(result: ProcedureResult) -> tuple[dict[str, Any], Any]:
    """A procedure's ``RunResult`` as (the run-result contract's dict, its details)."""
    out = result.to_json()
    if not isinstance(out, dict):
        raise StateError(f"procedure returned {type(result).__name__}, not a run result")
    out = jsonable(out)
    if result.config_error:
        out["config_error"] = True  # a fault caused by the config: alignctl exits 2
    return out, jsonable(result.details)


def _identities(rig: Rig) -> dict[str, Any]:
    return {role: jsonable(ident) for role, ident in rig.identities.items()}


def _camera_state(source: str, state: str, *, size: tuple[int, int] | None = None,
                  error: str | None = None) -> dict[str, Any]:
    """One camera in ``status``: its source, ok / fault / not checked, frame size, why."""
    return {"source": source, "state": state, "size": list(size) if size else None,
            "error": error}


def default_procedures() -> dict[str, Procedure]:
    from alignd.procedures.align import run_alignment, run_check
    from alignd.procedures.commission import run_commission

    return {"align": run_alignment, "check": run_check, "commission": run_commission}


class Daemon:
    """The instrument's state machine and its worker; the API's ``Controller``."""

    def __init__(self, cfg: AligndConfig, store: Store, rig_factory: RigFactory, *,
                 procedures: Mapping[str, Procedure] | None = None,
                 notifier: Notifier | None = None, socket_path: str = "",
                 stop_timeout_s: float = DEFAULT_STOP_TIMEOUT_S,
                 config_path: str | Path | None = None) -> None:
        self.cfg = cfg
        self.config_path = None if config_path is None else Path(config_path)
        # called with a newly loaded config (by reset), before the rig is reopened
        self.on_config: list[Callable[[AligndConfig], None]] = []
        self.store = store
        self.rig_factory = rig_factory
        self.procedures = dict(procedures) if procedures is not None else default_procedures()
        self.notifier = notifier or Notifier(env={})
        self.socket_path = socket_path
        self.stop_timeout_s = stop_timeout_s
        self.config_hash = config_hash(cfg)
        self._config_json = cfg.model_dump_json()
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._state: State = "starting"
        self._fault: str | None = None
        self._current: _Job | None = None
        self._progress: dict[str, Any] | None = None
        self._last_run: dict[str, Any] | None = None
        self._events: collections.deque[dict[str, Any]] = collections.deque(maxlen=EVENT_BUFFER)
        self._seq = 0
        self._jobs: queue.Queue[_Job | None] = queue.Queue()
        self._stopping = threading.Event()
        self._rig: Rig | None = None
        self._devices: dict[str, Any] = {}
        self._cameras: dict[str, dict[str, Any]] = {
            c.role: _camera_state(c.source, "not checked") for c in cfg.cameras}
        self._warnings: list[str] = []
        self._worker = threading.Thread(target=self._worker_main, name="alignd-worker",
                                        daemon=True)
        self._started_at = time.monotonic()
        self._status_sent = 0.0
        self.live = LiveFrames()  # the cameras' latest grabs, for the web dashboard
        self.faults = 0  # times the daemon entered the fault state (metrics)
        self.web_url: str | None = None  # the read-only dashboard, when served
        self.readings = AxisReadings()  # the axes' last read-backs (status), no extra traffic

    # ---- lifecycle ------------------------------------------------------------------
    def start(self) -> None:
        self._worker.start()

    def stop(self, reason: str = "daemon stopping") -> bool:
        """Abort any run, stop every axis and release the hardware within the stop timeout.
        Returns True if the worker finished in time."""
        deadline = time.monotonic() + self.stop_timeout_s
        with self._lock:
            self._stopping.set()
            job = self._current
        if job is not None:
            log.warning("stopping: aborting run %s (%s)", job.run_id, reason)
            job.abort.request(reason)
        self._jobs.put(None)
        if self._worker.is_alive():
            self._worker.join(timeout=max(0.1, deadline - time.monotonic() - 1.0))
        if self._worker.is_alive():
            log.error("worker did not stop within %.1f s: stopping all axes from the main "
                      "thread", self.stop_timeout_s)
            rig = self._rig
            if rig is not None:
                with contextlib.suppress(Exception):
                    rig.stop_all()
            if job is not None and job.run_id is not None:
                with contextlib.suppress(StoreError):
                    self.store.mark_interrupted(f"{reason}; the run did not end within the stop"
                                                f" timeout of {self.stop_timeout_s:g} s")
            return False
        return True

    @property
    def state(self) -> State:
        return self._state

    # ---- the worker -----------------------------------------------------------------
    def _set_state(self, state: State, fault: str | None = None) -> None:
        with self._cond:
            if state == "fault" and self._state != "fault":
                self.faults += 1
            self._state = state
            self._fault = fault
            self._cond.notify_all()
        self._update_status(force=True)

    def _worker_main(self) -> None:
        try:
            self._open_rig()
            while True:
                self.notifier.watchdog()
                try:
                    job = self._jobs.get(timeout=self.live.wait_s(
                        self.notifier.tick_s, idle=self._state == "idle"))
                except queue.Empty:
                    if self._stopping.is_set():
                        break
                    self._preview()
                    continue
                if job is None:
                    break
                if job.kind == "reset":
                    self._close_rig()
                    if job.config is not None:
                        self._apply_config(job.config)
                    self._open_rig()
                else:
                    self._run(job)
        except BaseException:
            log.exception("worker crashed")
            self._set_state("fault", "internal error in the worker (see the log)")
            raise
        finally:
            self._close_rig()

    def _open_rig(self) -> None:
        self._set_state("starting")
        rig = None
        with self._lock:
            self._cameras = {c.role: _camera_state(c.source, "not checked")
                             for c in self.cfg.cameras}
        try:
            rig = self.rig_factory(self.cfg)
            self._feed_watchdog_while_axes_wait(rig)
            if not rig.identities:
                rig.connect()
            self._check_cameras(rig)
        except Exception as exc:  # any failure leaves the daemon up, in fault, saying why
            if isinstance(exc, CameraError) and exc.device in self._cameras:
                with self._lock:  # a camera that could not even be opened
                    self._cameras[exc.device] = _camera_state(exc.port or "?", "fault",
                                                              error=exc.detail)
            if rig is not None:  # release what was opened (ports, simulator threads)
                with contextlib.suppress(Exception):
                    rig.stop_all()
                with contextlib.suppress(Exception):
                    rig.close()
            if not isinstance(exc, AligndError):
                log.exception("opening the rig failed")
            reason = f"cannot open the rig: {exc}"
            log.error("%s", reason)
            self.live.set_unavailable(reason)
            self._set_state("fault", reason)
            return
        self._rig = rig
        self._devices = _identities(rig)
        self._warnings = list(getattr(rig, "warnings", None) or [])
        cameras = getattr(rig, "cameras", None)
        if isinstance(cameras, dict):
            tap_cameras(cameras, self.live)
        axes = getattr(rig, "axes", None)
        self.readings.clear()
        if isinstance(axes, dict):
            tap_axes(axes, self.readings)
        self.live.set_unavailable(None)
        self._set_state("idle")
        log.info("rig ready: %s", ", ".join(sorted(self._devices)) or "(no identities)")

    def _preview(self) -> None:
        """While idle and watched, grab preview frames for the dashboard (the worker owns
        the cameras; the web server never opens one)."""
        cameras = getattr(self._rig, "cameras", None)
        if self._state == "idle" and isinstance(cameras, dict) and self.live.preview_due():
            grab_previews(cameras, self.live)

    def _apply_config(self, cfg: AligndConfig) -> None:
        """Use a newly loaded config from now on (worker thread, no run in progress)."""
        old = self.config_hash
        with self._lock:
            self.cfg = cfg
            self.config_hash = config_hash(cfg)
            self._config_json = cfg.model_dump_json()
        for fn in self.on_config:
            fn(cfg)
        log.info("config %s reloaded: hash %s -> %s", self.config_path, old[:12],
                 self.config_hash[:12])

    def _feed_watchdog_while_axes_wait(self, rig: Any) -> None:
        """Ping the watchdog from every axis' poll loop: a homing may take minutes (up to
        ``home_timeout_s`` per axis, one after another) without a progress event."""
        axes = getattr(rig, "axes", None)
        for ax in axes.values() if isinstance(axes, dict) else ():
            hooks = getattr(ax, "on_wait", None)
            if isinstance(hooks, list) and self.notifier.watchdog not in hooks:
                hooks.append(self.notifier.watchdog)

    def _check_cameras(self, rig: Any) -> None:
        """Grab one frame from every camera of the rig; raise ``CameraError`` naming each
        camera (and its source) that gives none. The states show in ``status``."""
        cameras = getattr(rig, "cameras", None)
        failures: list[str] = []
        for role, cam in (cameras.items() if isinstance(cameras, dict) else ()):
            source = str(getattr(cam, "source", "?"))
            self.notifier.watchdog()
            try:
                cam.open()
                frame = cam.grab(timeout_s=CAMERA_CHECK_TIMEOUT_S)
                h, w = frame.image.shape[:2]
                state = _camera_state(source, "ok", size=(int(w), int(h)))
            except Exception as exc:  # any camera failure is reported, not raised here
                detail = exc.detail if isinstance(exc, CameraError) else str(exc)
                state = _camera_state(source, "fault", error=detail)
                failures.append(f"camera {role} (source {source}): {detail}")
            with self._lock:
                self._cameras[role] = state
        if failures:
            raise CameraError("no frame at start-up from " + "; ".join(failures))

    def _close_rig(self) -> None:
        rig, self._rig = self._rig, None
        self.live.set_unavailable("the rig is closed (reconnecting or stopping)")
        if rig is None:
            return
        for e in rig.stop_all():
            log.error("stop on shutdown: %s", e)
        with contextlib.suppress(Exception):
            rig.close()

    def _run(self, job: _Job) -> None:
        assert job.run_id is not None
        run_id = job.run_id
        recorder = SqliteRecorder(self.store, run_id, on_write=self.notifier.watchdog,
                                  keep_frame=frame_keeper(self.cfg),
                                  on_event=lambda msg, level: self._emit(
                                      run_id, {"type": "event", "level": level, "msg": msg}))
        self._emit(run_id, {"type": "state", "msg": f"{job.kind} started (run {run_id}, "
                            f"by {job.user or '?'} as {job.started_by})"})
        verdict, reason, result, details = "fault", "", None, None
        crashed = False
        try:
            if self._rig is None:
                raise StateError("the rig is not connected")
            proc = self.procedures[job.kind]
            commission = None
            if job.kind in ("align", "check"):
                commission, note = self.commission_record()
                recorder.event(note)
            raw = proc(self._rig, self.cfg, progress=lambda ev: self._on_progress(run_id, ev),
                       abort=job.abort, recorder=recorder, run_id=str(run_id),
                       commission=commission)
            result, details = _result_dict(raw)
            verdict = str(result.get("verdict") or "fault")
            reason = str(result.get("reason") or "")
        except Exception as exc:
            crashed = True
            if not isinstance(exc, AligndError):
                log.exception("run %d: the procedure raised", run_id)
            verdict = "aborted" if job.abort.is_set() and isinstance(exc, AligndError) \
                else "fault"
            reason = (job.abort.reason or str(exc)) if verdict == "aborted" else \
                f"{type(exc).__name__}: {exc}"
        if verdict in ("fault", "aborted") or crashed:
            for e in self._rig.stop_all() if self._rig is not None else []:
                log.error("run %d: stopping after %s: %s", run_id, verdict, e)
            self._record_positions(run_id, recorder)
        if result is None:
            result = {"verdict": verdict, "reason": reason, "offset_um": None,
                      "offset_norm_um": None, "U_um": None, "iterations": 0,
                      "tilt_deg": None, "yaw_deg": None}
        result["run_id"] = run_id
        truth = self._rig.truth if self._rig is not None else None
        if "truth" not in result and truth is not None:
            try:
                result["truth"] = jsonable(truth())
            except Exception as exc:  # the truth block is informative only
                log.warning("run %d: reading the simulator's truth failed: %s", run_id, exc)
        try:
            self.store.finish_run(run_id, verdict=verdict, reason=reason or None, result=result,
                                  details=details)
        except StoreError as exc:
            log.error("%s", exc)
            verdict, reason = "fault", f"the run's outcome could not be recorded: {exc}"
        log.info("run %d (%s) ended: %s%s", run_id, job.kind, verdict,
                 f" ({reason})" if reason else "")
        self._emit(run_id, {"type": "end", "verdict": verdict, "reason": reason})
        with self._cond:
            self._current = None
            self._last_run = {"id": run_id, "kind": job.kind, "verdict": verdict,
                              "reason": reason or None}
            if verdict == "fault":
                self.faults += 1
            # a run refused by the config (a reversed turntable, a sweep beyond the soft
            # limits) stopped before anything went wrong with the hardware: stay idle
            if verdict == "fault" and not result.get("config_error"):
                self._state, self._fault = "fault", reason or "fault"
            else:
                self._state, self._fault = "idle", None
            self._cond.notify_all()
        self._update_status(force=True)

    def _record_positions(self, run_id: int, recorder: SqliteRecorder) -> None:
        """After a stop, note where every axis ended up (or that it is unknown)."""
        axes = self._rig.axes if self._rig is not None else {}
        if not axes:
            return
        parts = []
        for role, ax in axes.items():
            unit = f" {ax.config.units}" if isinstance(ax, Axis) else ""
            try:
                parts.append(f"{role}={float(ax.position()):.6g}{unit}")
            except Exception as exc:  # a dead link: say so, do not hide the run's outcome
                parts.append(f"{role}=unknown ({exc})")
        try:
            recorder.event("positions after stop: " + ", ".join(parts), "warning")
        except AligndError as exc:
            log.error("run %d: %s", run_id, exc)

    # ---- progress -------------------------------------------------------------------
    def _emit(self, run_id: int, event: dict[str, Any]) -> None:
        with self._cond:
            self._seq += 1
            event = {"seq": self._seq, "run_id": run_id, "t": time.time(), **event}
            self._events.append(event)
            self._cond.notify_all()

    def _on_progress(self, run_id: int, ev: ProgressEvent) -> None:
        self.notifier.watchdog()
        d = jsonable(ev.to_dict())
        d.pop("timestamp", None)
        with self._cond:
            self._progress = d
        self._emit(run_id, {"type": "progress", **d})
        self._update_status()

    def _update_status(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._status_sent < 1.0:
            return
        self._status_sent = now
        self.notifier.status(status_line(self.status()))

    # ---- commissioning -----------------------------------------------------------------
    def commission_record(self) -> tuple[CommissionRecord | None, str]:
        """The latest valid commission record (or None) and a sentence saying which/why not.

        Valid: the newest finished commission run, verdict ``commissioned``, made with this
        config (hash) and these devices (models and serial numbers)."""

        last = self.store.latest_run("commission")
        if last is None:
            return None, ("no commission record: using the config's conventions (run "
                          "'alignctl commission' once per rig)")
        try:
            rec = CommissionRecord.from_json(last["result"] or {})
        except ValueError as exc:
            return None, f"commission run {last['id']} unusable ({exc}): using the config"
        why = rec.valid_for(self.config_hash, self._devices)
        if why:
            return None, (f"commission run {last['id']} ({last['ended_at']}) not used: {why}; "
                          "using the config's conventions (run 'alignctl commission' again)")
        amp = rec.runout.amplitude_um if rec.runout is not None else None
        return rec, (f"using commission run {last['id']} ({last['ended_at']}): turntable "
                     f"direction {rec.turntable_sign:+d}, angle scale {rec.angle_scale:.5f}, "
                     f"pixel size {rec.pixel_size_um:.2f} um/px"
                     + (f", runout map {amp:.1f} um peak" if amp is not None else ""))

    def _commission_status(self) -> dict[str, Any] | None:
        last = self.store.latest_run("commission")
        if last is None:
            return None
        rec, note = self.commission_record()
        return {"run_id": last["id"], "ended_at": last["ended_at"],
                "verdict": last["verdict"], "valid": rec is not None, "note": note}

    # ---- the API's Controller -------------------------------------------------------
    def status(self) -> dict[str, Any]:
        refused = self.store.space_problem()  # why a new run would be refused (disk space)
        try:
            commission = self._commission_status()
        except AligndError as exc:  # the history is unreadable: say so, keep the status
            commission = {"valid": False, "note": f"commission record unreadable: {exc}"}
        with self._lock:
            job = self._current
            return {
                "state": self._state, "fault": self._fault,
                "run_id": job.run_id if job else None, "kind": job.kind if job else None,
                "started_by": job.started_by if job else None,
                "progress": dict(self._progress) if job and self._progress else None,
                "last_run": dict(self._last_run) if self._last_run else None,
                "name": self.cfg.name, "version": __version__,
                "config_hash": self.config_hash, "devices": self._devices,
                "cameras": {role: dict(c) for role, c in self._cameras.items()},
                "warnings": list(self._warnings),
                "pid": os.getpid(), "uptime_s": round(time.monotonic() - self._started_at, 1),
                "state_dir": str(self.store.state_dir), "socket": self.socket_path,
                "runs_refused": refused,
                "web": self.web_url, "axes": self.readings.snapshot(),
                "commission": commission,
            }

    def history(self, limit: int) -> list[dict[str, Any]]:
        return self.store.list_runs(limit)

    def run(self, run_id: int) -> dict[str, Any] | None:
        return self.store.get_run(run_id)

    def frame(self, digest: str) -> bytes | None:
        try:
            return self.store.frame_path(digest).read_bytes()
        except FileNotFoundError:
            return None

    def events(self, run_id: int, after: int, wait_s: float) -> dict[str, Any] | None:
        """Live progress of a run after ``after`` (long-poll up to ``wait_s``)."""
        deadline = time.monotonic() + wait_s
        with self._cond:
            while True:
                evs = [e for e in self._events if e["run_id"] == run_id and e["seq"] > after]
                live = self._current is not None and self._current.run_id == run_id
                remaining = deadline - time.monotonic()
                if evs or not live or remaining <= 0:
                    break
                self._cond.wait(remaining)
        out: dict[str, Any] = {"run_id": run_id, "events": evs,
                               "next": evs[-1]["seq"] if evs else after, "done": not live}
        if not live:
            st = self.store.run_status(run_id)
            if st is None:
                return None
            out["status"], out["verdict"] = st
            out["result"] = self.store.result(run_id)
        return out

    def start_run(self, kind: str, started_by: str, peer: Peer) -> dict[str, Any]:
        if kind not in self.procedures or not _is_run_kind(kind):
            raise Refused(HTTPStatus.NOT_FOUND, "not_found", f"no procedure {kind!r}")
        with self._cond:
            if self._stopping.is_set():
                raise Refused(HTTPStatus.SERVICE_UNAVAILABLE, "stopping", "alignd is stopping")
            self._require_worker()
            if self._current is not None or self._state in BUSY_STATES:
                cur = self._current
                raise Refused(HTTPStatus.CONFLICT, "busy",
                              f"busy: run {cur.run_id if cur else '?'} "
                              f"({cur.kind if cur else self._state}) is in progress",
                              state=self._state, run_id=cur.run_id if cur else None)
            if self._state == "starting":
                raise Refused(HTTPStatus.CONFLICT, "starting",
                              "alignd is still connecting the hardware; try again shortly",
                              state=self._state)
            if self._state == "fault":
                raise Refused(HTTPStatus.CONFLICT, "fault",
                              f"alignd is faulted: {self._fault}; fix the cause, then "
                              "'alignctl reset'", state=self._state, fault=self._fault)
            try:
                self.store.check_writable()
                run_id = self.store.start_run(
                    kind, started_by=started_by, software_version=__version__,
                    config_hash=self.config_hash, config_json=self._config_json,
                    user=peer.user, uid=peer.uid, devices=self._devices)
            except StoreError as exc:
                log.error("refusing to start a %s: %s", kind, exc)
                raise Refused(HTTPStatus.SERVICE_UNAVAILABLE, "store",
                              f"refusing to start: the run could not be recorded ({exc})"
                              ) from None
            job = _Job(kind=kind, run_id=run_id, started_by=started_by, user=peer.user)
            self._current = job
            self._progress = None
            self._state = RUN_STATES.get(kind, "checking")
            self._cond.notify_all()
        log.info("run %d (%s) requested by %s as %s", run_id, kind, peer.describe(), started_by)
        self._jobs.put(job)
        self._update_status(force=True)
        return {"run_id": run_id, "kind": kind, "state": self._state}

    def abort(self, peer: Peer) -> dict[str, Any]:
        with self._lock:
            job = self._current
        if job is None:
            return {"aborted": None, "message": "no run in progress"}
        reason = f"aborted by {peer.describe()}"
        job.abort.request(reason)
        log.warning("run %s: %s", job.run_id, reason)
        self._emit(job.run_id or 0, {"type": "event", "level": "warning", "msg": reason})
        return {"aborted": job.run_id, "message": reason}

    def reset(self, peer: Peer) -> dict[str, Any]:
        """Re-read the config file (a bad one is refused: the old config stays) and
        reconnect the hardware with it."""
        self._check_resettable()
        cfg, note = self._reload_config()
        with self._cond:
            self._check_resettable()
            self._state = "starting"
        log.warning("reset requested by %s: reconnecting the rig (%s)", peer.describe(), note)
        self._jobs.put(_Job(kind="reset", config=cfg))
        return {"state": "starting", "message": f"reconnecting the hardware ({note})"}

    def _check_resettable(self) -> None:
        if self._current is not None or self._state in BUSY_STATES:
            raise Refused(HTTPStatus.CONFLICT, "busy", "busy: abort the run first",
                          state=self._state)
        if self._stopping.is_set():
            raise Refused(HTTPStatus.SERVICE_UNAVAILABLE, "stopping", "alignd is stopping")
        self._require_worker()

    def _reload_config(self) -> tuple[AligndConfig | None, str]:
        """The config file, loaded and validated now, and a note on what changed."""
        if self.config_path is None:
            return None, "no config file to re-read"
        try:
            cfg = load_config(self.config_path)
        except ConfigError as exc:
            log.error("reset refused: %s", exc)
            raise Refused(HTTPStatus.CONFLICT, "config",
                          f"reset refused, the config file is not valid: {exc}\nalignd keeps "
                          f"the config it has (hash {self.config_hash[:12]}); fix the file "
                          "and reset again") from None
        new = config_hash(cfg)
        if new == self.config_hash:
            return None, f"config {self.config_path} unchanged"
        note = f"config {self.config_path} reloaded, hash {new[:12]}"
        if cfg.daemon.socket != self.cfg.daemon.socket:
            note += "; the new daemon.socket takes effect when alignd restarts"
        return cfg, note

    def _require_worker(self) -> None:
        if self._worker.ident is None and not self._stopping.is_set():
            # the API may answer before the worker thread is started: that is "starting"
            raise Refused(HTTPStatus.CONFLICT, "starting",
                          "alignd is still connecting the hardware; try again shortly",
                          state=self._state)
        if not self._worker.is_alive():
            raise Refused(HTTPStatus.SERVICE_UNAVAILABLE, "fault",
                          "the hardware worker is not running (see the log); restart alignd",
                          state=self._state)


def status_line(st: Mapping[str, Any]) -> str:
    """One line for systemd's STATUS= and ``alignctl status``."""
    state = st.get("state", "?")
    if state == "fault":
        return f"fault: {st.get('fault')}"
    if state not in BUSY_STATES:
        refused = st.get("runs_refused")
        return f"{state}; runs refused: {refused}" if refused else str(state)
    text = f"{state} (run {st.get('run_id')})"
    p = st.get("progress") or {}
    bits = []
    if p.get("phase"):
        bits.append(str(p["phase"]))
    if p.get("iteration") is not None:
        bits.append(f"iteration {p['iteration']}")
    if p.get("step") is not None and p.get("total") is not None:
        bits.append(f"step {p['step']}/{p['total']}")
    if p.get("offset_norm_um") is not None:
        u = f" ± {p['U_um']:.1f}" if p.get("U_um") is not None else ""
        bits.append(f"offset {p['offset_norm_um']:.1f}{u} um")
    return text + (": " + ", ".join(bits) if bits else "")


# ---- command line ---------------------------------------------------------------------------
def resolve_state_dir(arg: str | None, env: Mapping[str, str] | None = None) -> Path:
    """``--state-dir``, else ``$STATE_DIRECTORY`` (systemd; first entry), else
    ``$XDG_STATE_HOME/alignd``, else ``~/.local/state/alignd``."""
    env = os.environ if env is None else env
    if arg:
        return Path(arg)
    if env.get("STATE_DIRECTORY"):
        return Path(env["STATE_DIRECTORY"].split(":")[0])
    base = env.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "alignd"


def lock_state_dir(state_dir: Path) -> TextIO:
    """Hold ``<state_dir>/alignd.lock`` (flock) for the daemon's lifetime: one daemon per
    history. Without it a second instance would mark the first one's running run as
    interrupted. The kernel drops the lock when the process dies, even by SIGKILL."""
    import fcntl

    path = state_dir / "alignd.lock"
    try:
        state_dir.mkdir(parents=True, exist_ok=True)
        f = open(path, "a+")  # noqa: SIM115 - held open until exit
    except OSError as exc:
        raise StoreError(f"{state_dir}: cannot use the state directory: "
                         f"{exc.strerror or exc}") from None
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        f.close()
        raise StoreError(f"{state_dir}: another alignd is using this state directory "
                         f"(lock {path} is held)") from None
    f.truncate(0)
    f.write(f"{os.getpid()}\n")
    f.flush()
    return f


def use_space_floor(store: Store, cfg: AligndConfig) -> None:
    """Refuse runs unless there is room for one run of this config (its frames)."""
    store.min_free_bytes, store.space_note = run_footprint(cfg)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="alignd", description="The alignment daemon (runs in the "
                                "foreground; systemd runs it the same way).")
    p.add_argument("--version", action="version", version=f"alignd {__version__}")
    p.add_argument("--config", help="instrument config (YAML)")
    p.add_argument("--check-config", metavar="FILE", help="validate a config without "
                   "touching hardware and exit (0 valid, 2 invalid)")
    p.add_argument("--config-reference", action="store_true",
                   help="print the config reference (Markdown) and exit")
    p.add_argument("--config-schema", action="store_true",
                   help="print the config's JSON Schema (for editors) and exit")
    p.add_argument("--socket", help="control socket (default: $ALIGND_SOCKET, else the "
                   "config's daemon.socket)")
    p.add_argument("--state-dir", help="database, frames (default: $STATE_DIRECTORY, else "
                   "$XDG_STATE_HOME/alignd)")
    p.add_argument("--seed", type=int, help="simulated rig: seed for its misalignment and noise")
    p.add_argument("--stop-timeout", type=float, default=DEFAULT_STOP_TIMEOUT_S,
                   help="seconds to stop all axes and exit on SIGTERM (default %(default)s)")
    p.add_argument("--web", metavar="HOST:PORT", help="serve the read-only web dashboard and "
                   "/metrics here (default: the config's daemon.web; off unless set; "
                   "':8080' binds 127.0.0.1)")
    p.add_argument("-v", "--verbose", action="count", default=0)
    return p


def main(argv: Sequence[str] | None = None, *, rig_factory: RigFactory | None = None,
         procedures: Mapping[str, Procedure] | None = None) -> int:
    """Run the daemon until SIGTERM/SIGINT. ``rig_factory``/``procedures`` are for tests."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.config_reference or args.config_schema:
        from alignd.config_doc import json_schema, reference_markdown

        sys.stdout.write(reference_markdown() if args.config_reference else json_schema())
        return EXIT_OK
    if args.check_config:
        try:
            cfg, notes = check_config_file(args.check_config)
        except ConfigError as exc:
            print(f"alignd: {exc}", file=sys.stderr)
            return EXIT_USAGE
        for n in notes:
            print(f"warning: {n}")
        print(f"{args.check_config}: valid ({cfg.name}, config hash {config_hash(cfg)[:12]})")
        for c in cfg.controllers:
            print(f"  {c.name}: {c.protocol} on {c.port}: "
                  + ", ".join(f"{a.role} (address {a.address}, {a.stage or 'no stage'})"
                              for a in c.axes))
        for cam in cfg.cameras:
            curve = "" if is_linear(cam.gamma) else \
                f" (tone curve: {curve_text(cam.gamma)}, undone)"
            lens = "" if cam.lens is None else (
                f" (lens: k1 {cam.lens.k1:g} at {cam.lens.focal_px:g} px focal length"
                + (", straightened)" if cam.role == "top" else ", not used by the side camera)"))
            print(f"  camera {cam.role}: {cam.source}{curve}{lens}")
        return EXIT_OK
    if not args.config:
        parser.error("--config FILE is required (or --check-config FILE)")
    configure_logging([logging.INFO, logging.DEBUG][min(args.verbose, 1)])
    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        print(f"alignd: {exc}", file=sys.stderr)
        return EXIT_USAGE
    state_dir = resolve_state_dir(args.state_dir)
    socket_path = resolve_socket(args.socket, cfg.daemon.socket)
    try:
        lock = lock_state_dir(state_dir)
    except StoreError as exc:
        print(f"alignd: refusing to start: {exc}", file=sys.stderr)
        return EXIT_FAULT
    store = Store(state_dir)
    use_space_floor(store, cfg)
    try:
        store.open()
        store.mark_interrupted()
    except StoreError as exc:
        print(f"alignd: refusing to start, the history cannot be used: {exc}", file=sys.stderr)
        store.close()
        lock.close()
        return EXIT_FAULT
    try:  # short of space: start anyway, say so in status, refuse runs until there is room
        store.check_writable()
    except StoreError as exc:
        log.warning("runs are refused until this is fixed: %s", exc)
    if rig_factory is None:
        seed = args.seed

        def rig_factory(cfg: AligndConfig) -> Rig:
            from alignd.hardware import open_rig

            return open_rig(cfg, seed=seed)

    notifier = Notifier(watchdog=cfg.daemon.watchdog)
    web_at = args.web or cfg.daemon.web
    web = None
    try:
        daemon = Daemon(cfg, store, rig_factory, procedures=procedures, notifier=notifier,
                        socket_path=socket_path, stop_timeout_s=args.stop_timeout,
                        config_path=args.config)
        server = ApiServer(socket_path, daemon, Authoriser(cfg.daemon.operator_group))
        def use_operator_group(new: AligndConfig) -> None:
            server.authoriser = Authoriser(new.daemon.operator_group)

        daemon.on_config.append(use_operator_group)
        daemon.on_config.append(lambda new: use_space_floor(store, new))
        if web_at:
            from alignd.web.server import WebServer, parse_address

            try:
                web = WebServer(parse_address(web_at), daemon)
            except (OSError, ConfigError) as exc:
                server.stop()
                if isinstance(exc, ConfigError):
                    raise
                raise OSError(f"web dashboard on {web_at}: {exc.strerror or exc}") from None
            daemon.web_url = web.url
    except (AligndError, ImportError, OSError) as exc:
        where = "" if isinstance(exc, ConfigError) else f"cannot start on {socket_path}: "
        print(f"alignd: {where}{exc}", file=sys.stderr)
        store.close()
        lock.close()
        return EXIT_USAGE if isinstance(exc, ConfigError) else EXIT_FAULT

    stop = threading.Event()
    received: list[str] = []

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        received.append(signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    log.info("alignd %s: config %s (%s), state %s, socket %s", __version__, args.config,
             daemon.config_hash[:12], state_dir, socket_path)
    daemon.start()  # the worker first: a request queued on the socket may be served at once
    server.start()
    if web is not None:
        web.start()
    notifier.ready("starting")
    while not stop.wait(0.5):
        pass
    why = received[0] if received else "stop"
    log.info("%s received: stopping all axes and exiting", why)
    notifier.stopping()
    clean = daemon.stop(f"daemon stopping ({why})")
    if web is not None:
        web.stop()
    server.stop()
    store.close()
    lock.close()
    return EXIT_OK if clean else EXIT_FAULT


if __name__ == "__main__":
    sys.exit(main())
