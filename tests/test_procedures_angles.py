"""Every sweep checks that the images turn as the turntable's read-back says: a reversed or
mis-scaled turntable stops the run with a message naming it and the fix."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from procedures_support import scene_rig, sim_config, standin_tools

from alignd.config import AligndConfig
from alignd.procedures import run_alignment
from alignd.procedures.angles import fit_slope, holder_image_angles


def _world(cfg: AligndConfig, **world: object) -> AligndConfig:
    assert cfg.sim is not None
    sim = cfg.sim.model_copy(update={"world": cfg.sim.world.model_copy(update=world)})
    return cfg.model_copy(update={"sim": sim})


def test_reversed_turntable_stops_the_run_naming_it_and_the_fix() -> None:
    cfg = _world(sim_config(), turntable_direction=-1)
    rig, _ = scene_rig(cfg, 3)
    res = run_alignment(rig, cfg, tools=standin_tools(3), abort=threading.Event())
    assert res.verdict == "fault"
    assert "turntable reversed" in res.reason
    assert "alignctl commission" in res.reason and "turntable_direction: -1" in res.reason
    assert res.exit_code == 2  # a config error, not a hardware fault
    assert res.iterations == 0 and res.sweeps == 1  # the first sweep, before any move


def test_the_configured_direction_makes_a_reversed_turntable_align() -> None:
    cfg = _world(sim_config(turntable_direction=-1), turntable_direction=-1)
    rig, _ = scene_rig(cfg, 3)
    res = run_alignment(rig, cfg, tools=standin_tools(3), abort=threading.Event())
    assert res.verdict == "aligned", res.reason
    assert res.truth is not None
    assert float(res.truth["offset_norm_um"]) <= cfg.procedure.tolerance_um  # type: ignore[arg-type]


def test_mis_scaled_turntable_stops_the_run() -> None:
    cfg = _world(sim_config(), turntable_scale=1.03)
    rig, _ = scene_rig(cfg, 5)
    res = run_alignment(rig, cfg, tools=standin_tools(5), abort=threading.Event())
    assert res.verdict == "fault"
    assert "angle scale wrong" in res.reason and "+3.0" in res.reason


@pytest.mark.parametrize("start", [0, 1, 2, 3])
def test_holder_angle_survives_a_corner_order_that_restarts(start: int) -> None:
    """Over a full turn a tracker's corner order restarts at another corner: the edge
    direction is taken modulo 90 deg and unwrapped."""
    a = np.arange(-180.0, 180.0, 5.0)
    local = np.array([[-20.0, -12.5], [20.0, -12.5], [20.0, 12.5], [-20.0, 12.5]])
    pts = []
    for i, ang in enumerate(a):
        r = np.radians(ang)
        R = np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]])
        pts.append(np.roll(local @ R.T, -((start + i // 17) % 4), axis=0))
    fit = fit_slope(a, holder_image_angles(np.asarray(pts)))
    assert fit.slope == pytest.approx(1.0, abs=1e-9)
