"""The simulated rig: one world, its simulated axes, emulated controllers on ports, cameras.

Built from the same controller/camera config the instrument uses; a controller whose
``port`` is ``sim`` is served by its protocol's emulator on a loopback TCP port or a pty.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from typing import TYPE_CHECKING, Literal, Self

import numpy as np

from drivers import registry, stages
from drivers.config import AxisConfig, CameraConfig, ControllerConfig, SimConfig
from drivers.sim.clock import Clock, ScaledClock
from drivers.sim.emulator import Emulator, TargetLog
from drivers.sim.kinematics import AxisPhysics, SimAxis
from drivers.sim.server import EmulatorServer
from drivers.sim.world import World

if TYPE_CHECKING:
    from drivers.sim.sim_camera import SimCamera

log = logging.getLogger(__name__)

def _simulated(protocol: str) -> tuple[registry.EmulatorFactory, registry.PhysicsFactory]:
    """A protocol's emulator and physics from the registry (an error if it has none)."""
    proto = registry.get(protocol)
    if proto.emulator is None or proto.physics is None:
        raise ValueError(f"protocol {protocol!r} has no emulator: it cannot be 'port: sim'")
    return proto.emulator(), proto.physics()


def physics_for(protocol: str, axis: AxisConfig, sim: SimConfig) -> AxisPhysics:
    """The stage's mechanics as its emulator models them, imperfections from the world."""
    phys = _simulated(protocol)[1](axis)
    w = sim.world
    if axis.units == "deg":
        return dataclasses.replace(phys, backlash=w.turntable_backlash_deg)
    return dataclasses.replace(phys, backlash=w.backlash_mm,
                               repeatability=w.stage_repeatability_um / 1000.0)


def _identity_kwargs(ctl: ControllerConfig) -> dict[str, object]:
    """What each emulator reports as its stage: the model the config names (a simulated
    controller answers ``ID?`` / device id / stage id as the configured stage would)."""
    named = {ax.address: stages.resolve(ctl.protocol, ax.stage, ax.units) for ax in ctl.axes}
    if ctl.protocol == "smc100":
        return {"stage": {a: m.name for a, m in named.items() if m is not None}}
    if ctl.protocol == "zaber":
        return {"models": {a: m.name for a, m in named.items() if m is not None}}
    first = named[min(named)]
    return {"stage": first.name} if first is not None else {}


class SimRig:
    """Everything simulated, started and stopped together."""

    def __init__(self, controllers: list[ControllerConfig], cameras: list[CameraConfig],
                 sim: SimConfig, *, seed: int | None = None, clock: Clock | None = None,
                 transport: Literal["tcp", "pty", "both"] | None = None) -> None:
        self.sim = sim
        self.seed = sim.seed if seed is None else seed
        self.clock = clock or ScaledClock(sim.time_scale)
        self.transport = transport or sim.transport
        rng = np.random.default_rng(self.seed)
        streams = rng.spawn(8)
        self.axes: dict[str, SimAxis] = {}
        self.emulators: dict[str, Emulator] = {}
        for ctl in controllers:
            if ctl.port != "sim":
                continue
            emulator, _ = _simulated(ctl.protocol)
            by_address: dict[int, SimAxis] = {}
            for ax in ctl.axes:
                phys = physics_for(ctl.protocol, ax, sim)
                # power-on: somewhere near mid-travel, not referenced
                mid = (phys.travel_min + phys.travel_max) / 2
                if ax.units == "deg":
                    mid = 0.0
                start = mid + float(streams[0].normal(0, 0.2))
                sim_axis = SimAxis(ax.role, phys, self.clock, streams[1], start=start)
                by_address[ax.address] = sim_axis
                self.axes[ax.role] = sim_axis
            self.emulators[ctl.name] = emulator(ctl.name, by_address, self.clock,
                                                **_identity_kwargs(ctl))
        self.world = World(sim.world, self.axes, streams[2])
        self.lock = threading.Lock()
        self.camera_configs = {c.role: c for c in cameras if c.source == "sim"}
        self.servers: dict[str, EmulatorServer] = {}
        self.target_log: TargetLog | None = None
        self._camera_seed = int(streams[3].integers(2**31))

    def start(self) -> Self:
        if self.sim.target_log and self.target_log is None:
            self.target_log = TargetLog(self.sim.target_log)
            for emu in self.emulators.values():
                emu.target_log = self.target_log
        for i, (name, emu) in enumerate(self.emulators.items()):
            srv = EmulatorServer(emu, self.transport, faults=list(self.sim.faults),
                                 pace_serial=self.sim.pace_serial,
                                 seed=self.seed + i)
            self.servers[name] = srv.start()
        return self

    def stop(self) -> None:
        for srv in self.servers.values():
            srv.stop()
        self.servers.clear()
        if self.target_log is not None:  # where every axis was left, and whether it moves
            for role, ax in self.axes.items():
                self.target_log.write(event="final", axis=role, moving=ax.moving,
                                      position=ax.motor_position(), homed=ax.homed)
            self.target_log.close()
            self.target_log = None
            for emu in self.emulators.values():
                emu.target_log = None

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def url(self, controller: str) -> str:
        return self.servers[controller].url

    def endpoints(self) -> list[dict[str, str | None]]:
        return [srv.endpoint() for srv in self.servers.values()]

    def camera(self, role: Literal["top", "side"]) -> SimCamera:
        from drivers.sim.sim_camera import SimCamera  # the renderer is only loaded when used

        cc = self.camera_configs.get(role)
        return SimCamera(self.world, role, seed=self._camera_seed + (role == "side"),
                         gamma=cc.gamma if cc is not None else 1.0)

    def truth(self) -> dict[str, object]:
        """Ground truth from the simulator (never read by the alignment loop)."""
        return self.world.truth()
