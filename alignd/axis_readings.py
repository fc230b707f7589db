"""The axes' last read-back positions and homed flags, for ``status`` (no extra traffic).

Why a tap and not a poll: every command on a serial link is the worker's, and a periodic
status poll would interleave with the procedures' own traffic and shift the simulator's
command-counted fault triggers. Instead each axis' ``position()`` and ``status()`` are
wrapped (on the instance) to note what they returned; ``status`` shows the newest values
and when they were read.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.axis import Axis, AxisStatus


@dataclass
class Reading:
    units: str
    position: float | None = None
    homed: bool | None = None
    read_at: float | None = None  # time.time()


class AxisReadings:
    """Newest read-back per axis role; thread-safe (written by the worker)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_role: dict[str, Reading] = {}

    def note(self, role: str, units: str, position: float | None = None,
             homed: bool | None = None) -> None:
        with self._lock:
            r = self._by_role.setdefault(role, Reading(units))
            if position is not None:
                r.position = position
            if homed is not None:
                r.homed = homed
            r.read_at = time.time()

    def snapshot(self) -> dict[str, dict[str, Any]]:
        with self._lock:
            return {role: {"position": None if r.position is None else round(r.position, 6),
                           "units": r.units, "homed": r.homed,
                           "age_s": None if r.read_at is None
                           else round(time.time() - r.read_at, 1)}
                    for role, r in sorted(self._by_role.items())}

    def clear(self) -> None:
        with self._lock:
            self._by_role.clear()


_TAPPED: weakref.WeakSet[Axis] = weakref.WeakSet()


def tap_axes(axes: dict[str, Axis], readings: AxisReadings) -> None:
    """Wrap every axis' ``position``/``status`` (instance attributes) to note their values."""
    for role, ax in axes.items():
        if not isinstance(ax, Axis) or ax in _TAPPED:
            continue
        units = ax.config.units
        readings.note(role, units)
        position: Callable[[], float] = ax.position
        status: Callable[[], AxisStatus] = ax.status

        def read_position(_f: Callable[[], float] = position, _r: str = role,
                          _u: str = units) -> float:
            v = _f()
            readings.note(_r, _u, position=float(v))
            return v

        def read_status(_f: Callable[[], AxisStatus] = status, _r: str = role,
                        _u: str = units) -> AxisStatus:
            st = _f()
            readings.note(_r, _u, homed=bool(st.homed))
            return st

        ax.position = read_position  # type: ignore[method-assign]
        ax.status = read_status  # type: ignore[method-assign]
        _TAPPED.add(ax)
