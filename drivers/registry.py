"""The stage protocols alignd speaks: one registry, one entry per protocol.

An entry names the protocol (the config's ``controllers[].protocol``) and how to load its
driver factory, its emulator and its stage physics. Loaders are functions, so nothing is
imported before it is used: a real rig never loads the simulator, and the simulator
(``drivers.sim.rig``, reached from ``port: sim``) loads only the emulators it serves.

A new stage is one module plus one registration. A third-party package registers a
``StageProtocol`` through the entry-point group ``alignd.protocols``::

    [project.entry-points."alignd.protocols"]
    acme = "acme_alignd:PROTOCOL"

Entry points are read the first time the registry is asked for a name.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import TYPE_CHECKING, Protocol

from drivers.axis import Axis
from drivers.clock import Clock
from drivers.config import AxisConfig, ControllerConfig

if TYPE_CHECKING:
    from drivers.sim.emulator import Emulator
    from drivers.sim.kinematics import AxisPhysics, SimAxis

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "alignd.protocols"


class AxesFactory(Protocol):
    """A driver module's ``make_axes``: the axes of one controller, sharing its port."""

    def __call__(self, controller: ControllerConfig, time_scale: float = 1.0, *,
                 clock: Clock | None = None) -> Sequence[Axis]: ...


class EmulatorFactory(Protocol):
    """An emulator class: the firmware behind one port, over simulated axes by address."""

    def __call__(self, name: str, axes: dict[int, SimAxis], clock: Clock) -> Emulator: ...


PhysicsFactory = Callable[[AxisConfig], "AxisPhysics"]


@dataclass(frozen=True)
class StageProtocol:
    """One protocol: its driver and, when it can be simulated, its emulator and physics."""

    name: str
    driver: Callable[[], AxesFactory]
    emulator: Callable[[], EmulatorFactory] | None = None
    physics: Callable[[], PhysicsFactory] | None = None
    description: str = ""

    @property
    def simulated(self) -> bool:
        return self.emulator is not None and self.physics is not None


class UnknownProtocolError(KeyError):
    """No registered protocol of that name (the message lists the known ones)."""

    def __str__(self) -> str:
        return str(self.args[0])


# ---- the built-in protocols -----------------------------------------------------------
def _smc100_driver() -> AxesFactory:
    from drivers.newport_smc100 import make_axes

    return make_axes


def _smc100_emulator() -> EmulatorFactory:
    from drivers.sim.smc100_emu import Smc100Emulator

    return Smc100Emulator


def _smc100_physics() -> PhysicsFactory:
    from drivers.sim.smc100_emu import physics_for

    return physics_for


def _apt_driver() -> AxesFactory:
    from drivers.thorlabs_apt import make_axes

    return make_axes


def _apt_emulator() -> EmulatorFactory:
    from drivers.sim.apt_emu import AptEmulator

    return AptEmulator


def _apt_physics() -> PhysicsFactory:
    from drivers.sim.apt_emu import physics_for

    return physics_for


def _zaber_driver() -> AxesFactory:
    from drivers.zaber_ascii import make_axes

    return make_axes


def _zaber_emulator() -> EmulatorFactory:
    from drivers.sim.zaber_emu import ZaberEmulator

    return ZaberEmulator


def _zaber_physics() -> PhysicsFactory:
    from drivers.sim.zaber_emu import physics_for

    return physics_for


BUILTIN: tuple[StageProtocol, ...] = (
    StageProtocol("smc100", _smc100_driver, _smc100_emulator, _smc100_physics,
                  "Newport SMC100CC/PP (and CONEX-CC), ASCII"),
    StageProtocol("apt", _apt_driver, _apt_emulator, _apt_physics,
                  "Thorlabs APT (KDC101, K10CR1), binary"),
    StageProtocol("zaber", _zaber_driver, _zaber_emulator, _zaber_physics,
                  "Zaber ASCII (X-LSM daisy chains)"),
)

_lock = threading.Lock()
_registry: dict[str, StageProtocol] = {p.name: p for p in BUILTIN}
_entry_points_loaded = False


def register(protocol: StageProtocol, *, replace: bool = False) -> None:
    """Add a protocol. A name already taken is refused unless ``replace``."""
    if not protocol.name or not protocol.name.isidentifier():
        raise ValueError(f"protocol name {protocol.name!r} must be a plain identifier")
    with _lock:
        if protocol.name in _registry and not replace:
            raise ValueError(f"protocol {protocol.name!r} is already registered")
        _registry[protocol.name] = protocol


def unregister(name: str) -> None:
    """Remove a protocol (tests that register a fake one clean up with this)."""
    with _lock:
        _registry.pop(name, None)


def _load_entry_points() -> None:
    global _entry_points_loaded
    with _lock:
        if _entry_points_loaded:
            return
        _entry_points_loaded = True
    load_entry_points()


def load_entry_points() -> list[str]:
    """Register the protocols of the ``alignd.protocols`` entry points not registered yet;
    return their names. A plug-in that fails to load is logged and skipped."""
    added = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
        except Exception as exc:  # a broken plug-in must not take the built-ins down
            log.error("protocol entry point %s (%s) failed to load: %s", ep.name, ep.value,
                      exc)
            continue
        if not isinstance(obj, StageProtocol):
            log.error("protocol entry point %s (%s) is a %s, not a drivers.registry."
                      "StageProtocol; ignored", ep.name, ep.value, type(obj).__name__)
            continue
        if _registry.get(obj.name) is obj:  # loaded before
            continue
        try:
            register(obj)
        except ValueError as exc:
            log.error("protocol entry point %s: %s; ignored", ep.name, exc)
            continue
        log.info("protocol %s registered by %s", obj.name, ep.value)
        added.append(obj.name)
    return added


def names() -> tuple[str, ...]:
    """Every registered protocol name (built-ins first)."""
    _load_entry_points()
    with _lock:
        return tuple(_registry)


def get(name: str) -> StageProtocol:
    """The protocol called ``name``; ``UnknownProtocolError`` names the known ones."""
    _load_entry_points()
    with _lock:
        proto = _registry.get(name)
    if proto is None:
        raise UnknownProtocolError(f"unknown protocol {name!r} (known: "
                                   f"{', '.join(names())})")
    return proto


def make_axes(controller: ControllerConfig, time_scale: float = 1.0, *,
              clock: Clock | None = None) -> list[Axis]:
    """The axes of one controller config, from its protocol's driver."""
    factory = get(controller.protocol).driver()
    return list(factory(controller, time_scale, clock=clock))


__all__ = ["BUILTIN", "ENTRY_POINT_GROUP", "AxesFactory", "EmulatorFactory", "PhysicsFactory",
           "StageProtocol", "UnknownProtocolError", "get", "load_entry_points", "make_axes",
           "names", "register", "unregister"]
