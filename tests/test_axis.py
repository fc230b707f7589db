"""The vendor-independent Axis behaviour: limits, backlash approach, verification, faults."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.axis import Axis, AxisStatus, Identity, move_timeout_s
from drivers.config import AxisConfig, SoftLimits
from drivers.errors import DeviceFault, DeviceTimeoutError, LimitError, MissedTargetError
from drivers.sim.clock import ManualClock
from drivers.sim.kinematics import AxisPhysics, SimAxis


class FakeAxis(Axis):
    """An Axis straight over a SimAxis; sleeping advances the manual clock."""

    def __init__(self, cfg: AxisConfig, sim: SimAxis, clock: ManualClock) -> None:
        super().__init__(cfg, clock=clock)
        self.sim = sim
        self.sent: list[float] = []
        self.stops = 0
        self.offset_error = 0.0  # a controller that lands off target

    port = "fake://0"

    def connect(self) -> None: ...

    def close(self) -> None: ...

    def identify(self) -> Identity:
        return Identity("test", "fake", "1", "1.0")

    def home(self) -> None:
        self.sim.home()

    def _start_move(self, target: float) -> None:
        self.sent.append(target)
        self.sim.move_to(target + self.offset_error)

    def stop(self) -> None:
        self.stops += 1
        self.sim.stop()

    def position(self) -> float:
        return self.sim.encoder_position()

    def status(self) -> AxisStatus:
        return AxisStatus(moving=self.sim.moving, homed=self.sim.homed,
                          limit_low=self.sim.limit_low, limit_high=self.sim.limit_high,
                          stalled=False)


def make(**over: object) -> FakeAxis:
    clock = ManualClock()
    sim = SimAxis("x", AxisPhysics(0, 50, 5, 20, 10000, requires_homing=False), clock,
                  np.random.default_rng(0), start=25.0)
    base: dict[str, object] = {"speed": 5, "accel": 20, "deadband": 0.001,
                               "backlash_approach": 0.1, "stall_timeout_s": 1.0}
    cfg = AxisConfig(role="x", soft_limits=SoftLimits(min=2, max=48), **{**base, **over})
    return FakeAxis(cfg, sim, clock)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1.0, 48.5])
def test_bad_targets_are_refused_before_anything_is_sent(bad: float) -> None:
    ax = make()
    with pytest.raises(LimitError, match="device x"):
        ax.move_to(bad)
    assert ax.sent == []


def test_move_up_goes_straight_and_is_verified() -> None:
    ax = make()
    assert ax.move_to(30.0) == pytest.approx(30.0, abs=1e-4)
    assert ax.sent == [30.0]
    assert ax.position_known


def test_move_down_approaches_from_below() -> None:
    ax = make()
    ax.move_to(20.0)
    assert ax.sent == [pytest.approx(19.9), 20.0]
    ax2 = make(approach="-")
    ax2.move_to(30.0)
    assert ax2.sent == [pytest.approx(30.1), 30.0]


def test_pre_position_is_clamped_to_the_soft_limits() -> None:
    ax = make()
    ax.move_to(2.0)
    assert ax.sent[0] == 2.0


def test_missed_target_after_retries() -> None:
    ax = make(retries=2)
    ax.offset_error = 0.01  # lands 10 um off, ten times the deadband
    with pytest.raises(MissedTargetError, match=r"missed target 30.*3 attempts"):
        ax.move_to(30.0)
    assert len(ax.sent) >= 3


def test_stall_is_detected_and_the_axis_stopped() -> None:
    ax = make()
    ax.sim.inject_stall()
    with pytest.raises(DeviceFault, match="stall"):
        ax.move_to(40.0)
    assert ax.stops == 1


def test_move_outlasting_its_timeout_is_stopped() -> None:
    ax = make(stall_timeout_s=1000.0)
    ax.sim.p.speed = 0.05  # ten times slower than configured: the computed timeout is too short
    with pytest.raises(DeviceTimeoutError, match="did not finish"):
        ax.move_to(45.0)
    assert ax.stops == 1


def test_limit_switch_stops_and_reports_side() -> None:
    ax = make()
    ax.sim.p.travel_max = 35.0  # the mechanics end before the soft limit
    with pytest.raises(LimitError, match="high limit switch"):
        ax.move_to(40.0)
    assert ax.stops == 1


def test_timeout_formula() -> None:
    # 10 mm at 5 mm/s with 20 mm/s^2: 0.25 s ramps + 1.75 s cruise = 2.25 s
    assert move_timeout_s(10, 5, 20, margin=1.0, floor_s=0.0) == pytest.approx(2.25)
    # triangular: 0.1 mm -> 2 * sqrt(0.1 / 20)
    assert move_timeout_s(0.1, 5, 20, margin=1.0, floor_s=0.0) == pytest.approx(
        2 * math.sqrt(0.005))
