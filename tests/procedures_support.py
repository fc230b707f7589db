"""Shared set-up of the procedure tests: the reference config, a direct simulated rig, and
stand-in measuring tools (the world's projected corners plus seeded noise, real solver)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from alignd import solve as solver
from alignd.config import AligndConfig, load_config
from alignd.procedures import MemoryRecorder, Rig, RunResult, Tools, run_alignment
from alignd.procedures.runout import RunoutMap
from alignd.procedures.sweep import sweep_runout
from alignd.procedures.tools import Corners, as_corners, default_tools
from alignd.simulated import build_direct_rig
from drivers.camera import Frame
from drivers.sim.direct import scene_tracker
from drivers.sim.world import World

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "sim.yaml"


def sim_config(**procedure: Any) -> AligndConfig:
    cfg = load_config(CONFIG)
    if procedure:
        cfg = cfg.model_copy(update={"procedure": cfg.procedure.model_copy(update=procedure)})
    return cfg


def aligned_by_vision(cfg: AligndConfig, seed: int,
                      recorder: MemoryRecorder | None = None) -> RunResult:
    """A whole alignment with the real vision on the rendered rig: it must end "aligned"
    with the simulator's truth within U of the measured offset."""
    rig, _ = build_direct_rig(cfg, seed=seed)
    res = run_alignment(rig, cfg, tools=default_tools(cfg), recorder=recorder)
    assert res.verdict == "aligned", res.reason
    out = res.to_json()
    truth = out["truth"]["offset_um"]
    assert math.hypot(out["offset_um"][0] - truth[0], out["offset_um"][1] - truth[1]) \
        <= out["U_um"]
    return res


def scene_rig(cfg: AligndConfig, seed: int, **kw: Any) -> tuple[Rig, World]:
    return build_direct_rig(cfg, seed, camera_kind="scene", **kw)


def full_turn_config(**procedure: Any) -> AligndConfig:
    """The reference config with the turntable free to its cable wrap (+-169 deg), for a
    runout map over nearly a full turn."""
    cfg = sim_config(**procedure)
    ctls = []
    for c in cfg.controllers:
        axes = [a.model_copy(update={"soft_limits": a.soft_limits.model_copy(
            update={"min": -169.0, "max": 169.0})}) if a.role == "turntable" else a
            for a in c.axes]
        ctls.append(c.model_copy(update={"axes": axes}))
    return cfg.model_copy(update={"controllers": ctls})


def commissioned(rig: Rig, cfg: AligndConfig, seed: int) -> RunoutMap:
    """The rig's runout map from a full-turn sweep (what commissioning measures)."""
    rig.connect()
    return sweep_runout(rig, cfg, standin_tools(seed + 500, sigma_px=0.005), half_deg=165.0,
                        step_deg=10.0,
                        frames_per_step=4)


def standin_tools(seed: int, sigma_px: float = 0.01, track: Any = None) -> Tools:
    """Tracker: true corners + N(0, sigma_px); solver: the real ``alignd.solve``."""
    tracker = scene_tracker(sigma_px, np.random.default_rng(seed + 1000))

    def track_fn(frame: Frame) -> Corners:
        return as_corners(tracker(frame))

    def solve_fn(angles: np.ndarray, points: np.ndarray, px: float | None) -> Any:
        return solver.solve_centre(solver.Sweep(np.asarray(angles), np.asarray(points), px))

    def tilt_fn(frame: Frame) -> float:
        return float(frame.metadata["tilt_deg"])

    return Tools(track=track or track_fn, solve=solve_fn, tilt=tilt_fn, eccentricity=None)


def commanded(rig: Rig, role: str) -> list[float]:
    """Every target the simulated axis of ``role`` was ever commanded."""
    return list(rig.sim_parts.sim_axes[role].targets)  # type: ignore[attr-defined]
