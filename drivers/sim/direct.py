"""A simulated rig without bytes: ``Axis`` objects straight over ``SimAxis`` models.

The byte-faithful emulators (``drivers.sim.rig``) are what the drivers are tested against;
the closed-loop procedure does not care about bytes, so its tests and the closed-loop
benchmark run on this direct rig: same world, same kinematics (trapezoidal profile,
backlash, repeatability, encoder counts), no serial round trips. With a ``ManualClock`` the
axes advance simulated time instead of sleeping, so a run is fast and deterministic.

``alignd.simulated.build_direct_rig`` wraps these parts in a procedures ``Rig``.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from drivers.axis import Axis, AxisStatus, Identity
from drivers.camera import Camera, Frame
from drivers.clock import SYSTEM_CLOCK
from drivers.config import AxisConfig, CameraConfig, ControllerConfig, SimConfig
from drivers.errors import TransportError
from drivers.sim.clock import Clock, ManualClock, ScaledClock
from drivers.sim.kinematics import SimAxis
from drivers.sim.rig import physics_for
from drivers.sim.world import World

if TYPE_CHECKING:
    from drivers.sim.render import RenderOptions

log = logging.getLogger(__name__)

class DirectSimAxis(Axis):
    """An ``Axis`` over a ``SimAxis``: statuses from its flags, no protocol in between.

    With a ``ManualClock`` the polling sleeps advance the clock (and timeouts are measured
    on it); with a ``ScaledClock`` the axis polls in wall time and the config's
    ``time_scale`` shortens the timeouts, as for an emulator on a port.
    """

    def __init__(self, config: AxisConfig, sim: SimAxis, clock: Clock,
                 name: str | None = None, serial: str | None = None) -> None:
        # the axis waits on a manual clock itself; under a scaled clock it polls in wall
        # time (the config's time_scale shortens its timeouts)
        super().__init__(config, name,
                         clock=clock if isinstance(clock, ManualClock) else SYSTEM_CLOCK)
        self.sim = sim
        self.sim_clock = clock
        self.serial = serial or f"SIM-{config.role.upper()}"
        self.connected = False
        self.lock = threading.RLock()

    @property
    def port(self) -> str:
        return f"direct:{self.name}"

    def _require(self, command: str) -> None:
        if not self.connected:
            raise TransportError("axis not connected", device=self.name, port=self.port,
                                 command=command)

    def connect(self) -> None:
        self.connected = True

    def close(self) -> None:
        if self.connected:
            self.connected = False
            self.position_known = False

    def identify(self) -> Identity:
        self._require("identify")
        return Identity(vendor="alignd-sim", model=f"direct {self.config.units} axis",
                        serial=self.serial, firmware="direct-1", stage=self.config.stage)

    def home(self) -> None:
        self._require("home")
        with self.lock:
            self.sim.home()

        def homed() -> bool:
            with self.lock:
                moving = self.sim.moving  # refreshes the model: sets homed on arrival
                return self.sim.homed and not moving

        self.poll_until(homed, self.config.home_timeout_s / max(self.config.time_scale, 1e-9),
                        command="home", timeout_message=f"homing did not finish within "
                        f"{self.config.home_timeout_s:g} s")
        self.position_known = True

    def _start_move(self, target: float) -> None:
        self._require(f"move to {target:.6g}")
        with self.lock:
            self.sim.move_to(target, speed=self.speed)

    def _send_speed(self, speed: float) -> None:
        self._require("set velocity")

    def stop(self) -> None:
        with self.lock:
            self.sim.stop()

    def position(self) -> float:
        self._require("position")
        with self.lock:
            return self.sim.encoder_position()

    def status(self) -> AxisStatus:
        self._require("status")
        with self.lock:
            s = self.sim
            moving = s.moving or s.homing or not s.settled
            msgs = []
            if s.stalled:
                msgs.append("stalled")
            if s.limit_low or s.limit_high:
                msgs.append("limit switch")
            return AxisStatus(moving=moving, homed=s.homed, limit_low=s.limit_low,
                              limit_high=s.limit_high, stalled=s.stalled,
                              raw=f"moving={moving} homed={s.homed}", messages=tuple(msgs))


# ---- cameras ---------------------------------------------------------------------------
class SceneCamera(Camera):
    """A camera that does not render: its frames carry the world's projected geometry.

    For fast procedure tests with a stand-in tracker (``scene_tracker``); the image is a
    tiny placeholder. The real renderer is ``drivers.sim.sim_camera.SimCamera``.
    """

    def __init__(self, world: World, role: Literal["top", "side"], *,
                 clock: Clock | None = None) -> None:
        super().__init__(f"{role}-scene-camera", f"sim-scene:{role}")
        self.clock = clock or SYSTEM_CLOCK
        self.world = world
        self.role = role
        self._seq = 0

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        self._seq += 1
        meta: dict[str, Any] = {"source": self.source}
        if self.role == "top":
            scene = self.world.top_scene()
            cam = self.world.top_camera
            meta["corners_px"] = cam.project(scene.holder_corners_mm)
            meta["target_px"] = cam.project(scene.target_mm[None, :])[0]
            meta["turntable_deg_true"] = scene.turntable_deg
        else:
            side = self.world.side_scene()
            meta["tilt_deg"] = side.sample_edge_angle_deg - side.pole_angle_deg
            from drivers.sim.render import RenderOptions, side_x_px
            from drivers.sim.sim_camera import framed

            opts = framed(RenderOptions(), self.world.cfg, "side")
            meta["sample_x_px"] = side_x_px(side.sample_x_mm, opts)
            meta["pole_x_px"] = side_x_px(side.pole_x_mm, opts)
        img = np.full((8, 8), self._seq % 251, np.uint8)
        return Frame(img, self.clock.now(), self._seq, meta)


@dataclass
class SceneDetection:
    """A detection with the fields of ``alignd.vision.HolderDetection`` the procedures read
    (``alignd.procedures.tools.Detection``)."""

    corners_px: np.ndarray
    ok: bool = True
    quality: float = 1.0
    center_px: np.ndarray = field(default_factory=lambda: np.zeros(2))
    angle_deg: float = 0.0
    reason: str = ""


def scene_tracker(sigma_px: float, rng: np.random.Generator,
                  miss_rate: float = 0.0) -> Callable[[Frame], SceneDetection]:
    """A stand-in tracker for ``SceneCamera`` frames: true corners plus Gaussian noise."""

    def track(frame: Frame) -> SceneDetection:
        c = np.asarray(frame.metadata["corners_px"], float)
        if miss_rate and rng.uniform() < miss_rate:
            return SceneDetection(np.full((4, 2), np.nan), ok=False, quality=0.0)
        c = c + rng.normal(0.0, sigma_px, c.shape)
        return SceneDetection(c, True, 1.0, c.mean(axis=0))

    return track


# ---- the rig ---------------------------------------------------------------------------
@dataclass
class DirectParts:
    """What ``build_direct_axes`` makes: axes by role, the world, cameras, the clock."""

    axes: dict[str, DirectSimAxis]
    sim_axes: dict[str, SimAxis]
    world: World
    cameras: dict[str, Camera]
    clock: Clock


def build_direct_axes(controllers: list[ControllerConfig], cameras: list[CameraConfig],
                      sim: SimConfig, seed: int, *, clock: Clock | None = None,
                      homed: bool = True, camera_kind: Literal["render", "scene"] = "render",
                      render_opts: RenderOptions | None = None,
                      exposure_s: float = 0.0) -> DirectParts:
    """Simulated axes and cameras for a controller/camera config, seeded.

    ``exposure_s`` is the top camera's exposure (frames grabbed during motion are smeared
    over it). ``homed=True`` models an instrument referenced since power-on, its linear stages at
    mid-travel (where the world's initial misalignment is defined); ``homed=False`` starts
    near there, unreferenced, like ``SimRig``.
    """
    clock = clock or ManualClock()
    scale = clock.scale if isinstance(clock, ScaledClock) else 1.0
    rng = np.random.default_rng(seed)
    streams = rng.spawn(4)
    sim_axes: dict[str, SimAxis] = {}
    axes: dict[str, DirectSimAxis] = {}
    for ctl in controllers:
        for ax_cfg in ctl.axes:
            phys = physics_for(ctl.protocol, ax_cfg, sim)
            mid = 0.0 if ax_cfg.units == "deg" else (phys.travel_min + phys.travel_max) / 2
            start = mid if homed else mid + float(streams[0].normal(0, 0.2))
            s_axis = SimAxis(ax_cfg.role, phys, clock, streams[1].spawn(1)[0], start=start)
            s_axis.homed = homed or not phys.requires_homing
            sim_axes[ax_cfg.role] = s_axis
            cfg = ax_cfg.model_copy(update={"time_scale": scale})
            axes[ax_cfg.role] = DirectSimAxis(cfg, s_axis, clock, name=f"{ctl.name}.{ax_cfg.role}")
    world = World(sim.world, sim_axes, streams[2])
    cams: dict[str, Camera] = {}
    cam_seed = int(streams[3].integers(2**31))
    # frames are stamped on the clock the axes wait on: the manual clock, or the machine's
    cam_clock: Clock = clock if isinstance(clock, ManualClock) else SYSTEM_CLOCK
    for cc in cameras:
        if cc.source not in ("sim", "sim-direct"):
            continue
        if camera_kind == "scene":
            cams[cc.role] = SceneCamera(world, cc.role, clock=cam_clock)
        else:
            from drivers.sim.sim_camera import SimCamera

            cams[cc.role] = SimCamera(world, cc.role, opts=render_opts,
                                      seed=cam_seed + (cc.role == "side"), clock=cam_clock,
                                      exposure_s=exposure_s if cc.role == "top" else 0.0,
                                      gamma=cc.gamma)
    return DirectParts(axes, sim_axes, world, cams, clock)


__all__ = ["DirectParts", "DirectSimAxis", "SceneCamera", "SceneDetection",
           "build_direct_axes", "physics_for", "scene_tracker"]
