"""The hardware a procedure runs on: axes and cameras by role, and the safety helpers.

The procedures only see the ``Axis`` and ``Camera`` interfaces: a ``Rig`` of real drivers
and one of simulated axes look the same. ``truth`` is set only on a simulated rig and is
read once, after a run, for the labelled truth block; the loop never calls it.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from alignd.errors import AligndError, ConfigError, StateError
from alignd.textfmt import identity_text
from drivers.axis import Axis, Identity
from drivers.camera import Camera
from drivers.errors import Cancelled

log = logging.getLogger(__name__)


class AbortRequested(AligndError):
    """Raised inside a procedure when the operator's abort event is set."""


class AbortEvent(threading.Event):
    """An abort flag that carries its reason (the daemon's; the procedures report it)."""

    reason: str | None = None

    def request(self, reason: str) -> None:
        if not self.is_set():
            self.reason = reason
            self.set()


def abort_reason(abort: threading.Event | None) -> str:
    """The reason an abort event carries (an ``AbortEvent``'s, or one a caller attached to
    a plain ``threading.Event``), or a default."""
    reason = getattr(abort, "reason", None)
    return str(reason) if reason else "abort requested"


def check_abort(abort: threading.Event | None) -> None:
    if abort is not None and abort.is_set():
        raise AbortRequested(abort_reason(abort))


@dataclass
class Rig:
    """Axes by role (turntable, translator, x, y, z), cameras by role (top, side)."""

    axes: dict[str, Axis]
    cameras: dict[str, Camera]
    truth: Callable[[], dict[str, Any]] | None = None
    name: str = "rig"
    identities: dict[str, Identity] = field(default_factory=dict)
    on_close: list[Callable[[], None]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)  # identity doubts found at connect

    # ---- lookup --------------------------------------------------------------------
    def axis(self, role: str) -> Axis:
        try:
            return self.axes[role]
        except KeyError:
            raise ConfigError(f"rig {self.name!r} has no axis with role {role!r} "
                              f"(has: {sorted(self.axes)})") from None

    def camera(self, role: str) -> Camera | None:
        return self.cameras.get(role)

    # ---- life cycle ------------------------------------------------------------------
    def connect(self) -> dict[str, Identity]:
        """Connect every axis and open every camera; identify the axes (kept per run).

        Each axis' identity and the limits its controller reports are checked against
        the config: a mismatch that changes units or travel raises
        ``ConfigMismatchError``, a lesser one is logged and kept in ``warnings``.
        """
        self.warnings.clear()
        for role, ax in self.axes.items():
            ax.connect()
            self.identities[role] = ax.identify()
            self.warnings += ax.check_identity(self.identities[role])
            log.info("%s: %s on %s", role, identity_text(vars(self.identities[role])),
                     ax.port)
        for cam in self.cameras.values():
            cam.open()
        return dict(self.identities)

    def close(self) -> None:
        """Close everything; errors are logged, not raised (this runs on the way out)."""
        for cam in self.cameras.values():
            try:
                cam.close()
            except Exception:  # closing must reach every device
                log.exception("closing camera %s failed", cam.name)
        for role, ax in self.axes.items():
            try:
                ax.close()
            except Exception:
                log.exception("closing axis %s failed", role)
        for fn in self.on_close:
            fn()

    def stop_all(self) -> list[str]:
        """Stop every axis, never raising: the errors are returned (and logged)."""
        errors = []
        for role, ax in self.axes.items():
            try:
                ax.stop()
            except Exception as exc:  # a failing stop must not skip the others
                log.error("stopping %s failed: %s", role, exc)
                errors.append(f"{role}: {exc}")
        return errors

    def home_where_required(self, roles: list[str] | None = None,
                            abort: threading.Event | None = None,
                            park_mid: bool = True) -> list[str]:
        """Home the axes that report not homed; park homed linear axes at mid soft-limits.

        A linear stage's home switch is at one end of its travel; the sample was placed
        with the stage near the middle, so after homing it returns there (the rotary
        turntable homes to its zero and stays).
        """
        homed = []
        for role in roles if roles is not None else list(self.axes):
            ax = self.axis(role)
            check_abort(abort)
            if not ax.status().homed:
                log.info("homing %s on %s", role, ax.port)
                ax.home()
                homed.append(role)
                if park_mid and ax.config.units == "mm":
                    lim = ax.config.soft_limits
                    ax.move_to((lim.min + lim.max) / 2)
        return homed

    @contextlib.contextmanager
    def abort_guard(self, abort: threading.Event | None) -> Iterator[None]:
        """Make a set ``abort`` interrupt a move in progress, not just between moves.

        Every axis waits with ``abort`` as its cancel event (``Axis.cancel_on``); a wait it
        ends raises ``AbortRequested`` here. The caller stops the axes.
        """
        if abort is None:
            yield
            return
        with contextlib.ExitStack() as stack:
            for ax in self.axes.values():
                stack.enter_context(ax.cancel_on(abort))
            try:
                yield
            except Cancelled as exc:
                raise AbortRequested(abort_reason(abort)) from exc


def validate_rig(rig: Rig, correction_axes: tuple[str, ...], need_side: bool = False) -> None:
    """Refuse to start on a rig that cannot do the procedure (missing roles, bad limits)."""
    tt = rig.axis("turntable")
    if tt.config.units != "deg":
        raise ConfigError(f"turntable axis must be in degrees, is in {tt.config.units}")
    for role in correction_axes:
        ax = rig.axis(role)
        if ax.config.units != "mm":
            raise ConfigError(f"correction axis {role!r} must be linear (mm)")
    for role, ax in rig.axes.items():
        lim = ax.config.soft_limits
        if lim is None or not lim.min < lim.max:
            raise ConfigError(f"axis {role!r}: soft_limits missing or empty")
    if rig.camera("top") is None:
        raise ConfigError(f"rig {rig.name!r} has no top camera")
    if need_side and rig.camera("side") is None:
        raise StateError("the side camera is required but missing")
