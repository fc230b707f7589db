"""Time as an argument: what an ``Axis`` polls and waits with.

The wall clock by default; the simulator's clocks (``drivers.sim.clock``) for emulators
running faster than real time, and a manual clock that makes a test's waits instant.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Seconds since an arbitrary origin (monotonic)."""
        ...

    def sleep(self, dt: float) -> None:
        """Let ``dt`` seconds of this clock's time pass."""
        ...


class SystemClock:
    """The machine's monotonic clock; ``sleep`` really sleeps."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, dt: float) -> None:
        time.sleep(dt)


SYSTEM_CLOCK = SystemClock()
