"""The ``Axis`` interface the rest of alignd moves stages through.

Units at this interface are mm (linear) and degrees (rotary), as floats. A driver
implements the ``_``-prefixed primitives; this base class owns the behaviour that must be
the same for every vendor: soft-limit and finiteness checks before any byte is sent, the
backlash approach from one side, the move timeout from distance/speed/acceleration,
read-back verification within a deadband with bounded retries, and the polling waits (of a
move and of homing) on the axis' ``Clock``, which a caller's ``cancel`` event interrupts.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Literal, Self

from drivers import stages
from drivers.clock import SYSTEM_CLOCK, Clock
from drivers.config import AxisConfig
from drivers.errors import (
    Cancelled,
    ConfigMismatchError,
    DeviceError,
    DeviceFault,
    DeviceTimeoutError,
    LimitError,
    MissedTargetError,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Identity:
    """Who a controller says it is (kept in every run record)."""

    vendor: str
    model: str
    serial: str
    firmware: str
    stage: str = ""


@dataclass(frozen=True)
class AxisStatus:
    """The controller's flags, decoded to what the procedures need."""

    moving: bool = False
    homed: bool = False
    limit_low: bool = False
    limit_high: bool = False
    stalled: bool = False  # stall or following error
    fault: bool = False
    raw: str = ""
    messages: tuple[str, ...] = field(default_factory=tuple)

    @property
    def at_limit(self) -> bool:
        return self.limit_low or self.limit_high


MOVE_TIMEOUT_FLOOR_S = 2.0  # real seconds added to every move's timeout


def move_timeout_s(distance: float, speed: float, accel: float, margin: float = 2.0,
                   floor_s: float = 2.0) -> float:
    """Time a trapezoidal move of ``distance`` needs, times ``margin``, plus a floor."""
    d = abs(distance)
    if speed <= 0 or accel <= 0:
        return floor_s + 60.0
    t_ramp = speed / accel
    d_ramp = speed * t_ramp  # accelerate + decelerate distance
    t = 2 * math.sqrt(d / accel) if d < d_ramp else 2 * t_ramp + (d - d_ramp) / speed
    return floor_s + margin * t


class Axis(ABC):
    """One motion axis. Context manager; ``connect``/``close`` are idempotent."""

    def __init__(self, config: AxisConfig, name: str | None = None, *,
                 clock: Clock | None = None) -> None:
        self.config = config
        self.name = name or config.role
        self.position_known = False  # False until homed or verified; set False on disconnect
        self.clock: Clock = clock or SYSTEM_CLOCK  # a manual clock makes waits instant
        self.speed = config.speed  # the velocity moves run at now (``set_speed``)
        self._cancel: threading.Event | None = None  # set by ``cancel_on``
        # Called on every poll while the axis waits for the controller (homing, moves):
        # the daemon feeds the systemd watchdog from here, as a homing can take minutes.
        self.on_wait: list[Callable[[], None]] = []

    reports_serial = True  # False for controllers with no serial number to ask for

    # ---- primitives each driver implements -------------------------------------------
    @abstractmethod
    def connect(self) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def identify(self) -> Identity: ...

    @abstractmethod
    def home(self) -> None:
        """Run the controller's homing and block until done (or raise)."""

    @abstractmethod
    def _start_move(self, target: float) -> None:
        """Send an absolute move to ``target`` (already checked) and return at once."""

    @abstractmethod
    def stop(self) -> None:
        """Stop motion now. Must be safe to call at any time, also when not moving."""

    @abstractmethod
    def position(self) -> float:
        """The controller's read-back position in mm or degrees."""

    @abstractmethod
    def status(self) -> AxisStatus: ...

    @property
    @abstractmethod
    def port(self) -> str: ...

    def _send_speed(self, speed: float) -> None:
        """Write the move velocity (units/s) to the controller. Drivers that can do so
        override this; the base refuses."""
        raise DeviceError(f"{type(self).__name__} cannot change its velocity",
                          device=self.name, port=self.port, command="set velocity")

    def controller_limits(self) -> tuple[float, float] | None:
        """The travel limits the controller itself enforces (read from it), in units;
        None where the protocol has nothing to ask (the stage identity stands for it)."""
        return None

    # ---- shared behaviour ------------------------------------------------------------
    def _wait(self, command: str) -> None:
        """One poll interval of waiting for the controller (every wait goes through here):
        the ``on_wait`` hooks run, a cancel set by ``cancel_on`` ends the wait."""
        for fn in self.on_wait:
            fn()
        self.check_cancel(command)
        self.clock.sleep(self.config.poll_interval_s)

    def check_identity(self, ident: Identity) -> list[str]:
        """Compare what the controller says with the config; return warnings.

        Raises ``ConfigMismatchError`` where running would be unsafe: the controller's own
        limits do not contain the configured soft limits, or the stage it reports moves in
        other units or over another travel than the configured one. A different model of
        the same units and travel, an unknown reported model or an empty serial number
        is a warning naming both.
        """
        cfg = self.config
        warnings: list[str] = []
        lim = cfg.soft_limits
        reported = self.controller_limits()
        if reported is not None:
            lo, hi = reported
            if not (lo <= lim.min and lim.max <= hi):
                raise ConfigMismatchError(
                    f"configured soft limits [{lim.min:g}, {lim.max:g}] {cfg.units} lie "
                    f"outside the limits the controller reports [{lo:.6g}, {hi:.6g}] "
                    f"{cfg.units}; fix soft_limits or the controller's limits",
                    device=self.name, port=self.port)
        said, want = ident.stage.strip(), cfg.stage.strip()
        if said and want and said.upper() != want.upper():
            got, conf = stages.lookup(said), stages.lookup(want)
            if got is not None and conf is not None and got.name == conf.name:
                pass  # the same model spelt differently (e.g. a -E03 suffix)
            elif got is not None and conf is not None and (
                    got.units != conf.units or got.travel != conf.travel):
                raise ConfigMismatchError(
                    f"controller reports stage {got.name} ({got.units}, travel "
                    f"{_travel(got)}) where the config says {conf.name} ({conf.units}, "
                    f"travel {_travel(conf)}): units or travel would be wrong",
                    device=self.name, port=self.port)
            else:
                warnings.append(f"{self.name}: controller reports stage {said!r} where the "
                                f"config says {want!r} (same units and travel as far as "
                                "known); check the config")
        if self.reports_serial and ident.serial.strip() in ("", "0"):
            warnings.append(f"{self.name}: {ident.vendor} {ident.model} reports no serial "
                            f"number (got {ident.serial!r}); runs cannot name the unit")
        for w in warnings:
            log.warning("%s", w)
        return warnings

    def __enter__(self) -> Self:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def set_speed(self, speed: float) -> None:
        """Run the next moves at ``speed`` units/s (at most the configured ``speed``, which
        the move timeouts and the controller's profile were set up for).

        Why: a continuous sweep turns at a speed chosen for the camera's exposure, slower
        than a positioning move. Raises ``LimitError`` for a speed that is not a positive
        finite number up to the configured one."""
        top = self.config.speed
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and 0 < speed <= top):
            raise LimitError(f"velocity {speed!r} {self.config.units}/s outside (0, {top:g}] "
                             "(the axis' configured speed is the most it runs at)",
                             device=self.name, port=self.port, command="set velocity")
        self._send_speed(float(speed))
        self.speed = float(speed)

    @contextlib.contextmanager
    def speed_limited(self, speed: float) -> Iterator[None]:
        """Within the block moves run at ``speed``; the configured speed is restored after
        (also on an error; a failed restore is logged, as the block's own error matters
        more)."""
        self.set_speed(speed)
        try:
            yield
        finally:
            try:
                self.set_speed(self.config.speed)
            except Exception:  # the axis may be the reason the block failed
                log.exception("%s: restoring the configured speed failed", self.name)

    def start_move(self, target: float) -> None:
        """Start an absolute move to ``target`` (checked against the soft limits) and
        return at once, with no backlash approach: for moves during which something is
        measured (a continuous sweep). ``end_move`` waits for it and verifies it."""
        target = self.check_target(target)
        self.position_known = False
        self._start_move(target)

    def end_move(self, target: float, start: float) -> float:
        """Wait for a move begun with ``start_move`` from ``start`` and verify its
        read-back within the deadband (``MissedTargetError`` otherwise); the read-back."""
        cfg = self.config
        timeout = move_timeout_s(target - start, self.speed, cfg.accel, floor_s=0.0) / max(
            cfg.time_scale, 1e-9) + MOVE_TIMEOUT_FLOOR_S
        self.wait_until_stopped(timeout, command=f"move to {target:.6g}")
        reached = self.position()
        if abs(reached - target) > cfg.deadband:
            raise MissedTargetError(f"missed target {target:.6g} {cfg.units}: read-back "
                                    f"{reached:.6g} (deadband {cfg.deadband:g})",
                                    device=self.name, port=self.port)
        self.position_known = True
        return reached

    @property
    def needs_homing(self) -> bool:
        return not self.status().homed

    def check_target(self, target: float) -> float:
        """Reject NaN/inf and targets outside the soft limits, before any byte is sent."""
        lo, hi = self.config.soft_limits.min, self.config.soft_limits.max
        if not isinstance(target, (int, float)) or not math.isfinite(target):
            raise LimitError(f"target {target!r} is not a finite number", device=self.name,
                             port=self.port)
        if not lo <= target <= hi:
            raise LimitError(
                f"target {target:.6g} {self.config.units} outside soft limits [{lo:g}, {hi:g}]",
                device=self.name, port=self.port)
        return float(target)

    @contextlib.contextmanager
    def cancel_on(self, cancel: threading.Event | None) -> Iterator[None]:
        """Within the block, every wait of this axis (moves, homing) ends with ``Cancelled``
        as soon as ``cancel`` is set (the caller stops the axis)."""
        saved, self._cancel = self._cancel, cancel
        try:
            yield
        finally:
            self._cancel = saved

    def check_cancel(self, command: str, cancel: threading.Event | None = None) -> None:
        """Raise ``Cancelled`` if ``cancel`` (or the one of ``cancel_on``) is set."""
        ev = cancel if cancel is not None else self._cancel
        if ev is not None and ev.is_set():
            raise Cancelled(f"{command} cancelled", device=self.name, port=self.port,
                            command=command)

    def move_to(self, target: float, approach: Literal["+", "-"] | None = None, *,
                cancel: threading.Event | None = None) -> float:
        """Move to ``target``, approaching from the configured side; return the read-back.

        ``approach`` overrides the configured side for this move (commissioning arrives
        from both sides to measure the backlash).

        Blocks until the move is done and verified within the deadband, retrying at most
        ``config.retries`` times. Raises ``LimitError`` before moving for a bad target,
        ``DeviceTimeoutError`` when a move outlasts its computed timeout, ``DeviceFault``
        on a controller fault, ``MissedTargetError`` when retries are exhausted,
        ``Cancelled`` when ``cancel`` is set while waiting (the axis is not stopped).
        """
        with self.cancel_on(cancel if cancel is not None else self._cancel):
            return self._move_verified(target, approach)

    def _move_verified(self, target: float, approach: Literal["+", "-"] | None) -> float:
        target = self.check_target(target)
        cfg = self.config
        sign = 1.0 if (approach or cfg.approach) == "+" else -1.0
        lo, hi = cfg.soft_limits.min, cfg.soft_limits.max
        here = self.position()
        reached = here
        # unknown from the first byte of motion until the read-back is verified: a move
        # cut off by a fault or a vanished port leaves the stage somewhere in between
        self.position_known = False
        for attempt in range(cfg.retries + 1):
            # Arrive moving in the approach direction: if the final move would go the other
            # way (or nowhere), first go past the target by the backlash distance.
            if cfg.backlash_approach > 0 and (target - here) * sign < cfg.deadband:
                pre = min(max(target - sign * cfg.backlash_approach, lo), hi)
                self._move_and_wait(pre, here)
                here = self.position()
            self._move_and_wait(target, here)
            reached = self.position()
            if abs(reached - target) <= cfg.deadband:
                self.position_known = True
                return reached
            log.warning("%s: read-back %.6g outside deadband %.3g of target %.6g (attempt %d)",
                        self.name, reached, cfg.deadband, target, attempt + 1)
            here = reached
        raise MissedTargetError(
            f"missed target {target:.6g} {cfg.units}: read-back {reached:.6g} after "
            f"{cfg.retries + 1} attempts (deadband {cfg.deadband:g})",
            device=self.name, port=self.port)

    def _move_and_wait(self, target: float, start: float) -> None:
        cfg = self.config
        # the motion's time scales with a simulator's clock; the floor (polling, link
        # latency, a loaded machine) does not: at time_scale 200 a scaled floor was 10 ms
        timeout = move_timeout_s(target - start, self.speed, cfg.accel, floor_s=0.0) / max(
            cfg.time_scale, 1e-9) + MOVE_TIMEOUT_FLOOR_S
        self._start_move(target)
        self.wait_until_stopped(timeout, command=f"move to {target:.6g}")

    def poll_until(self, done: Callable[[], bool], timeout_s: float, *, command: str,
                   timeout_message: str, stop_on_timeout: bool = True) -> None:
        """Call ``done`` every poll interval until it is true (it raises on a fault).

        Raises ``DeviceTimeoutError`` with ``timeout_message`` after ``timeout_s`` of the
        axis' clock (stopping the axis first unless told not to), ``Cancelled`` when the
        cancel event of ``cancel_on`` is set. The drivers' homing waits are this loop.
        """
        deadline = self.clock.now() + timeout_s
        while True:
            now = self.clock.now()  # before the poll: a late answer is no timeout
            if done():
                return
            if now > deadline:
                if stop_on_timeout:
                    self.stop()
                raise DeviceTimeoutError(timeout_message, device=self.name, port=self.port,
                                         command=command)
            self._wait(command)

    def wait_until_stopped(self, timeout_s: float, command: str = "move") -> AxisStatus:
        """Poll status until not moving; stop and raise on a fault, limit or timeout.

        Each poll's time is taken before its requests are sent: a "still moving" answer
        is then true of that time or later, so a slow link or a busy host can never turn
        a move that finished in time into a timeout or a stall."""
        deadline = self.clock.now() + timeout_s
        last_pos = None
        still_since = self.clock.now()
        while True:
            now = self.clock.now()
            st = self.status()
            if st.stalled or st.fault:
                self.stop()
                raise DeviceFault(f"controller fault during {command}: "
                                  f"{'; '.join(st.messages) or st.raw}",
                                  device=self.name, port=self.port, command=command)
            if st.at_limit:
                self.stop()
                side = "low" if st.limit_low else "high"
                raise LimitError(f"hardware {side} limit switch hit during {command}",
                                 device=self.name, port=self.port, command=command)
            if not st.moving:
                return st
            pos = self.position()
            if last_pos is None or abs(pos - last_pos) > 1e-9:
                still_since = now
            elif now - still_since > self.config.stall_timeout_s / max(self.config.time_scale,
                                                                        1e-9):
                self.stop()
                raise DeviceFault(f"stall: position stuck at {pos:.6g} while moving",
                                  device=self.name, port=self.port, command=command)
            last_pos = pos
            if now > deadline:
                self.stop()
                raise DeviceTimeoutError(f"move did not finish within {timeout_s:.1f} s",
                                         device=self.name, port=self.port, command=command)
            self._wait(command)


def _travel(model: stages.StageModel) -> str:
    if model.travel is None:
        return "continuous"
    return f"{model.travel[0]:g}..{model.travel[1]:g}"
