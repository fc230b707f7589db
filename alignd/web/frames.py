"""The cameras' latest frames for the dashboard, taken from the worker's own grabs.

Why a tap and not a second reader: a V4L2 device (or an HTTP snapshot camera) is opened
once, by the worker that owns the hardware. ``tap_cameras`` wraps each camera of the rig so
that every grab the worker makes (sweep frames during a run, preview frames while idle)
also lands here; the web server only reads. While idle the worker grabs a preview frame
only when someone watched within ``linger_s`` and at most ``fps`` times a second.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from drivers.camera import Camera, Frame


@dataclass(frozen=True)
class LiveFrame:
    """One camera's latest grab (or why there is none)."""

    role: str
    image: np.ndarray | None
    wall_time: float | None  # time.time() of the grab
    seq: int
    error: str | None = None


class LiveFrames:
    """Latest frame per camera role; thread-safe; written by the worker, read by the web."""

    def __init__(self, fps: float = 4.0, linger_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.period_s = 1.0 / fps
        self.linger_s = linger_s
        self._clock = clock
        self._lock = threading.Lock()
        self._frames: dict[str, LiveFrame] = {}
        self._seq = 0
        self._watched_at: float | None = None
        self._preview_at = -1e9
        self.grab_seconds: list[float] = []  # drained by the metrics collector
        self.unavailable: str | None = "the rig is not connected yet"

    # ---- the worker's side -------------------------------------------------------------
    def put(self, role: str, image: np.ndarray, grab_s: float | None = None) -> None:
        """The worker's frame, not copied: the web thread gets a read-only view of the
        very array the procedure is measuring, so a view that drew on it would raise
        instead of changing the procedure's frame."""
        view = image.view()
        view.flags.writeable = False
        with self._lock:
            self._seq += 1
            self._frames[role] = LiveFrame(role, view, time.time(), self._seq)
            if grab_s is not None and len(self.grab_seconds) < 10000:
                self.grab_seconds.append(grab_s)

    def fail(self, role: str, error: str) -> None:
        with self._lock:
            self._seq += 1
            old = self._frames.get(role)
            self._frames[role] = LiveFrame(role, old.image if old else None,
                                           old.wall_time if old else None, self._seq, error)

    def set_unavailable(self, reason: str | None) -> None:
        """Why no camera can be read at all (daemon faulted, rig closed), or None."""
        with self._lock:
            self.unavailable = reason

    def preview_due(self) -> bool:
        """Whether an idle worker should grab a preview now (someone is watching)."""
        now = self._clock()
        with self._lock:
            watched = self._watched_at is not None and now - self._watched_at < self.linger_s
            if not watched or now - self._preview_at < self.period_s:
                return False
            self._preview_at = now
            return True

    def wait_s(self, idle_tick_s: float, idle: bool = True) -> float:
        """How long an idle worker may sleep: until the next preview is due while watched
        (the grab's own time does not stretch the period), else its usual tick."""
        now = self._clock()
        with self._lock:
            watched = self._watched_at is not None and now - self._watched_at < self.linger_s
            if not (watched and idle):
                return idle_tick_s
            return min(idle_tick_s, max(0.01, self.period_s - (now - self._preview_at)))

    # ---- the web's side ----------------------------------------------------------------
    def watch(self) -> None:
        with self._lock:
            self._watched_at = self._clock()

    def get(self, role: str) -> LiveFrame | None:
        with self._lock:
            return self._frames.get(role)

    def roles(self) -> list[str]:
        with self._lock:
            return sorted(self._frames)

    def drain_grab_seconds(self) -> list[float]:
        with self._lock:
            out, self.grab_seconds = self.grab_seconds, []
            return out


class TappedCamera(Camera):
    """A camera whose every grab is also handed to ``LiveFrames`` (same device, one open)."""

    def __init__(self, role: str, inner: Camera, live: LiveFrames) -> None:
        super().__init__(inner.name, inner.source)
        self.role = role
        self.inner = inner
        self.live = live

    def open(self) -> None:
        self.inner.open()

    def close(self) -> None:
        self.inner.close()

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        t0 = time.perf_counter()
        try:
            frame = self.inner.grab(after=after, timeout_s=timeout_s)
        except Exception as exc:
            self.live.fail(self.role, f"{type(exc).__name__}: {exc}")
            raise
        self.live.put(self.role, frame.image, time.perf_counter() - t0)
        return frame


def tap_cameras(cameras: dict[str, Camera], live: LiveFrames) -> None:
    """Wrap every camera of a rig's ``cameras`` dict in place (idempotent)."""
    for role, cam in list(cameras.items()):
        if not isinstance(cam, TappedCamera):
            cameras[role] = TappedCamera(role, cam, live)


def grab_previews(cameras: dict[str, Camera], live: LiveFrames) -> None:
    """One preview grab per camera (the idle worker calls this; errors are shown, not
    raised: a camera unplugged while idle must not fault the daemon)."""
    for role, cam in cameras.items():
        try:
            if isinstance(cam, TappedCamera):
                cam.grab(timeout_s=1.0)
            else:
                t0 = time.perf_counter()
                live.put(role, cam.grab(timeout_s=1.0).image, time.perf_counter() - t0)
        except Exception as exc:  # shown on the dashboard; the next run reports it properly
            live.fail(role, f"{type(exc).__name__}: {exc}")
