"""Injectable clocks, so emulators run faster than real time or fully under test control."""

from __future__ import annotations

import threading
import time

from drivers.clock import Clock

__all__ = ["Clock", "ManualClock", "ScaledClock"]


class ScaledClock:
    """Wall time multiplied by ``scale`` (the demo's time-scale setting)."""

    def __init__(self, scale: float = 1.0) -> None:
        if scale <= 0:
            raise ValueError("time scale must be positive")
        self.scale = scale
        self._t0 = time.monotonic()

    def now(self) -> float:
        return (time.monotonic() - self._t0) * self.scale

    def sleep(self, dt: float) -> None:
        """Sleep ``dt`` simulated seconds (``dt / scale`` of wall time)."""
        time.sleep(dt / self.scale)


class ManualClock:
    """A clock that only moves when a test advances it."""

    def __init__(self, start: float = 0.0) -> None:
        self._t = start
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise ValueError("time does not run backwards")
        with self._lock:
            self._t += dt

    def sleep(self, dt: float) -> None:
        """Waiting on a manual clock advances it: a polling loop never blocks."""
        self.advance(dt)
