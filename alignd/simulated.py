"""The simulated rig, for alignd: the one module that reaches into ``drivers.sim``.

``open_sim_rig`` starts what a ``port: sim`` / ``source: sim`` config asks for (emulators on
loopback ports, rendered cameras); ``alignd.hardware.open_rig`` calls it. ``build_direct_rig``
wraps direct simulated axes (no bytes) in a procedures ``Rig`` for the closed-loop tests and
benchmark. Runtime code outside this module never imports the simulator (an import-linter
contract in ``make test`` holds it to that).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from alignd.config import AligndConfig
from alignd.procedures.rig import Rig
from alignd.procedures.tools import Corners, SideInfo, Tools, as_corners
from drivers.camera import Frame
from drivers.config import SimConfig
from drivers.sim.clock import Clock
from drivers.sim.direct import DirectParts, build_direct_axes, scene_tracker
from drivers.sim.rig import SimRig
from drivers.sim.world import World

if TYPE_CHECKING:  # the renderer loads when a camera renders
    from alignd.solve.result import CentreResult
    from drivers.sim.render import RenderOptions

__all__ = ["DirectRig", "SimRig", "build_direct_rig", "open_sim_rig", "standin_tools"]


def open_sim_rig(cfg: AligndConfig, *, seed: int | None = None,
                 transport: Literal["tcp", "pty", "both"] | None = None) -> SimRig:
    """Start the emulators and cameras of every ``sim`` device of ``cfg`` (it has a ``sim:``
    section: the config checks that)."""
    if cfg.sim is None:
        raise ValueError("the config has no 'sim:' section")
    sim_rig = SimRig(cfg.controllers, cfg.cameras, cfg.sim, seed=seed, transport=transport)
    return sim_rig.start()


@dataclass
class DirectRig(Rig):
    """A procedures ``Rig`` over direct simulated axes; ``sim_parts`` lets a test reach the
    models (inject a stall, read the targets a stage received)."""

    sim_parts: DirectParts | None = None


def build_direct_rig(cfg: AligndConfig, seed: int | None = None, *,
                     clock: Clock | None = None, homed: bool = True,
                     camera_kind: Literal["render", "scene"] = "render",
                     render_opts: RenderOptions | None = None) -> tuple[DirectRig, World]:
    """A procedures ``Rig`` over direct simulated axes for an instrument config.

    ``seed`` defaults to ``cfg.sim.seed``; ``clock`` to a ``ManualClock`` (fast and
    deterministic; pass ``ScaledClock(cfg.sim.time_scale)`` for wall-clock pacing).
    """
    sim = cfg.sim or SimConfig()
    used_seed = sim.seed if seed is None else seed
    # the top camera exposes for the continuous sweep's exposure time (frames during
    # motion smear over it); stop-and-go frames are instantaneous, as before
    p = cfg.procedure
    exposure = p.continuous.exposure_s if p.sweep_mode == "continuous" else 0.0
    parts = build_direct_axes(list(cfg.controllers), list(cfg.cameras), sim, used_seed,
                              clock=clock, homed=homed, camera_kind=camera_kind,
                              render_opts=render_opts, exposure_s=exposure)
    rig = DirectRig(axes=dict(parts.axes), cameras=parts.cameras, truth=parts.world.truth,
                    name=f"{cfg.name} (direct sim, seed {used_seed})", sim_parts=parts)
    return rig, parts.world


def standin_tools(rng: np.random.Generator, sigma_px: float,
                  name: str | None = None) -> Tools:
    """Measuring tools for ``SceneCamera`` frames (the commissioning tests and benchmark):
    the world's projected corners + N(0, ``sigma_px``) in the real tracker's image order
    (top-left first, clockwise), the real solver, and the side view from the scene's
    geometry."""
    from alignd import solve as solver
    from alignd.vision.holder import order_corners

    tracker = scene_tracker(sigma_px, rng)

    def track(frame: Frame) -> Corners:
        det = as_corners(tracker(frame))
        return Corners(order_corners(det.corners_px), det.ok)

    def solve(angles: np.ndarray, points: np.ndarray, px: float | None) -> CentreResult:
        return solver.solve_centre(solver.Sweep(np.asarray(angles), np.asarray(points), px))

    def side(frame: Frame) -> SideInfo:
        m = frame.metadata
        return SideInfo(float(m["tilt_deg"]), float(m["tilt_deg"]), 0.0,
                        float(m["sample_x_px"]), float(m["pole_x_px"]))

    return Tools(track=track, solve=solve, tilt=lambda f: float(f.metadata["tilt_deg"]),
                 side=side, names={"track": name} if name else None)
