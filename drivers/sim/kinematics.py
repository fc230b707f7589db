"""Physical model of one stage axis: trapezoidal profile, limits, backlash, encoder.

The motor follows a trapezoidal velocity profile. The load (what the camera sees) follows
the motor through a backlash dead zone and lands with a random repeatability error. The
encoder reads the motor side, quantised to whole counts, as on the real stages. Faults
(stall, a tripped limit switch) are injectable. All times come from an injected clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.sim.clock import Clock


@dataclass
class AxisPhysics:
    """Mechanical parameters of one simulated axis (interface units: mm or deg)."""

    travel_min: float
    travel_max: float
    speed: float
    accel: float
    counts_per_unit: float
    backlash: float = 0.0
    repeatability: float = 0.0  # 1-sigma landing error of the load
    settle_s: float = 0.05
    home_position: float = 0.0
    home_speed: float | None = None
    requires_homing: bool = True


class SimAxis:
    """State of one axis as a function of simulated time."""

    def __init__(self, name: str, physics: AxisPhysics, clock: Clock,
                 rng: np.random.Generator, start: float | None = None) -> None:
        self.name = name
        self.p = physics
        self.clock = clock
        self.rng = rng
        x0 = physics.home_position if start is None else start
        self._x0 = x0  # motor position at segment start
        self._x1 = x0  # segment end (target)
        self._t0 = clock.now()
        self._v = physics.speed
        self._load0 = x0
        self._land_error = 0.0
        self.homed = not physics.requires_homing
        self.homing = False
        self.limit_low = False
        self.limit_high = False
        self.stalled = False
        self._stall_pending = False
        self._limit_pending: str | None = None
        self._limit_on_arrival: str | None = None
        self._frozen_at: float | None = None
        self.targets: list[float] = []  # every target ever commanded (safety tests read it)

    # ---- profile -------------------------------------------------------------------
    def _profile(self, t: float) -> tuple[float, bool]:
        """Motor position at time t and whether the segment is still running."""
        if self._frozen_at is not None:
            return self._frozen_at, self.stalled
        d = self._x1 - self._x0
        dist = abs(d)
        if dist == 0:
            return self._x1, False
        v, a = self._v, self.p.accel
        dt = t - self._t0
        t_ramp = v / a
        if dist < v * t_ramp:  # triangular
            t_ramp = math.sqrt(dist / a)
            v = a * t_ramp
            t_total = 2 * t_ramp
        else:
            t_total = 2 * t_ramp + (dist - v * t_ramp) / v
        if dt >= t_total:
            return self._x1, False
        if dt < t_ramp:
            s = 0.5 * a * dt * dt
        elif dt < t_total - t_ramp:
            s = 0.5 * a * t_ramp * t_ramp + v * (dt - t_ramp)
        else:
            tr = t_total - dt
            s = dist - 0.5 * a * tr * tr
        return self._x0 + math.copysign(s, d), True

    def _segment_end_time(self) -> float:
        d = abs(self._x1 - self._x0)
        v, a = self._v, self.p.accel
        t_ramp = v / a
        if d < v * t_ramp:
            return self._t0 + 2 * math.sqrt(d / a)
        return self._t0 + 2 * t_ramp + (d - v * t_ramp) / v

    def _update_faults(self, t: float) -> None:
        pos, running = self._profile(t)
        if self._stall_pending and running:
            self._stall_pending = False
            self.stalled = True
            self._frozen_at = pos
        if self._limit_pending and running:
            side = self._limit_pending
            self._limit_pending = None
            self._freeze(pos)
            if side == "low":
                self.limit_low = True
            else:
                self.limit_high = True

    def _freeze(self, pos: float) -> None:
        self._x0 = self._x1 = pos
        self._t0 = self.clock.now()
        self._frozen_at = None

    # ---- what controllers read -----------------------------------------------------
    def motor_position(self) -> float:
        return self._refresh()[0]

    def _refresh(self) -> tuple[float, bool]:
        """Position and running state now, with arrival events (homed, limits) applied."""
        t = self.clock.now()
        self._update_faults(t)
        pos, running = self._profile(t)
        if not running:
            if self.homing:
                self.homing = False
                self.homed = True
            if self._limit_on_arrival == "low":
                self.limit_low = True
            elif self._limit_on_arrival == "high":
                self.limit_high = True
            self._limit_on_arrival = None
        return pos, running

    def encoder_counts(self) -> int:
        return round(self.motor_position() * self.p.counts_per_unit)

    def encoder_position(self) -> float:
        return self.encoder_counts() / self.p.counts_per_unit

    @property
    def moving(self) -> bool:
        return self._refresh()[1]

    @property
    def settled(self) -> bool:
        return not self.moving and self.clock.now() >= self._segment_end_time() + self.p.settle_s

    def load_position(self, at: float | None = None) -> float:
        """Where the mechanics really are: motor through backlash, plus landing error.

        ``at`` (a time of the clock, default now) evaluates the current segment's profile
        at another instant without side effects: a camera integrates the pose over its
        exposure. A time before the segment began reads its start."""
        if at is None:
            m, running = self.motor_position(), self.moving
        else:
            m, running = self._profile(max(at, self._t0))
        half = self.p.backlash / 2
        load = min(max(self._load0, m - half), m + half)
        return load + (0.0 if running else self._land_error)

    # ---- commands ------------------------------------------------------------------
    def move_to(self, target: float, speed: float | None = None) -> None:
        """Start a move from the current motor position (hardware limits clip it)."""
        self.targets.append(float(target))
        t = self.clock.now()
        m = self.motor_position()
        half = self.p.backlash / 2
        self._load0 = min(max(self._load0, m - half), m + half)
        self.limit_low = self.limit_high = False
        self._limit_on_arrival = None
        if target < self.p.travel_min:
            target = self.p.travel_min
            self._limit_on_arrival = "low"
        elif target > self.p.travel_max:
            target = self.p.travel_max
            self._limit_on_arrival = "high"
        self._x0, self._x1, self._t0 = m, float(target), t
        self._v = min(speed, self.p.speed) if speed else self.p.speed  # the motor's top speed
        self._land_error = float(self.rng.normal(0.0, self.p.repeatability)) \
            if self.p.repeatability > 0 else 0.0

    def home(self) -> None:
        self.stalled = False
        self._frozen_at = None
        self.move_to(self.p.home_position, self.p.home_speed)
        self.targets.pop()  # homing is not a commanded target
        # flags after the move starts: move_to's position read would complete "homing"
        self.homing = True
        self.homed = False

    def stop(self) -> None:
        """Stop now (a real stop decelerates; a short ramp is negligible here)."""
        pos = self.motor_position()
        half = self.p.backlash / 2
        self._load0 = min(max(self._load0, pos - half), pos + half)
        self._freeze(pos)
        self.stalled = False
        self.homing = False

    # ---- fault injection -----------------------------------------------------------
    def inject_stall(self) -> None:
        """The next (or current) motion freezes while the controller still says moving."""
        self._stall_pending = True

    def inject_limit_switch(self, side: str = "high") -> None:
        """The next (or current) motion trips a limit switch and stops there."""
        self._limit_pending = side
