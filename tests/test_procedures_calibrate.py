"""Calibration of the stage-to-image mapping, and the direct simulated axes it runs on."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from procedures_support import scene_rig, sim_config, standin_tools

from alignd.procedures import CalibrationError, MemoryRecorder
from alignd.procedures.calibrate import calibrate, check_calibration
from alignd.procedures.events import no_progress
from alignd.procedures.holder_geometry import holder_pose
from drivers.errors import DeviceFault, LimitError


def _angle(v: np.ndarray) -> float:
    return math.degrees(math.atan2(v[1], v[0]))


@pytest.mark.parametrize("seed", [3, 11])
def test_calibration_recovers_skewed_stage_directions(seed: int) -> None:
    cfg = sim_config()
    rig, world = scene_rig(cfg, seed)
    rig.connect()
    x0 = rig.axis("x").position()
    rec = MemoryRecorder()
    cal = calibrate(rig, cfg, standin_tools(seed), abort=threading.Event(),
                    progress=no_progress, recorder=rec)
    dirs = world.stage_directions()  # turntable frame, never seen by the procedure
    for k, role in enumerate(("x", "y")):
        assert abs(cal.axis_angles_deg[k] - _angle(dirs[role])) < 0.1, role
    # non-square by the world's skew (1.5 deg) and turned by its mount angle
    assert abs(abs(cal.skew_deg) - world.cfg.stage_skew_deg) < 0.15
    # the holder's face is 30 mm nearer the 800 mm high camera than the turntable plane
    expected_um = world.cfg.pixel_size_um * (800.0 - world.HOLDER_TOP_Z_MM) / 800.0
    assert cal.pixel_size_um == pytest.approx(expected_um, rel=0.005)
    # the stages are back where they started, and the raw moves were recorded
    assert rig.axis("x").position() == pytest.approx(x0, abs=0.001)
    assert [s.kind for s in rec.sweeps] == ["calibration"]
    assert len(rec.sweeps[0].readback) == 16


def test_calibration_maps_a_stage_move_to_the_observed_image_shift() -> None:
    cfg = sim_config()
    rig, _world = scene_rig(cfg, 5)
    rig.connect()
    tools = standin_tools(5, sigma_px=0.0)
    cal = calibrate(rig, cfg, tools, abort=None, progress=no_progress,
                    recorder=MemoryRecorder())
    cam = rig.camera("top")
    before = holder_pose(tools.track(cam.grab()).corners_px, cfg.holder).center_px
    x0, y0 = rig.axis("x").position(), rig.axis("y").position()
    rig.axis("x").move_to(x0 + 1.0)
    rig.axis("y").move_to(y0 - 0.5)
    after = holder_pose(tools.track(cam.grab()).corners_px, cfg.holder).center_px
    predicted = cal.predict(np.array([1.0, -0.5]))  # turntable angle 0 = image frame
    assert np.hypot(*(after - before - predicted)) < 0.02  # px, of a ~7 px shift


def test_calibration_refuses_a_wrong_pixel_size() -> None:
    cfg = sim_config()
    rig, _ = scene_rig(cfg, 2)
    rig.connect()
    cal = calibrate(rig, cfg, standin_tools(2), abort=None, progress=no_progress,
                    recorder=MemoryRecorder())
    check_calibration(cal, 160.0, 0.15)
    with pytest.raises(CalibrationError, match=r"axis x gives 15\d\.\d um/px.*250 um/px"):
        check_calibration(cal, 250.0, 0.15)


def test_calibration_refuses_parallel_axes() -> None:
    cfg = sim_config()
    rig, _ = scene_rig(cfg, 2)
    rig.connect()
    cal = calibrate(rig, cfg, standin_tools(2), abort=None, progress=no_progress,
                    recorder=MemoryRecorder())
    cal.J = np.column_stack([cal.J[:, 0], cal.J[:, 0] * 1.01])
    with pytest.raises(CalibrationError, match="nearly the same direction"):
        check_calibration(cal, 160.0, 0.15)


def test_direct_axis_moves_homes_and_reports_status() -> None:
    cfg = sim_config()
    rig, _ = scene_rig(cfg, 1, homed=False)
    rig.connect()
    x = rig.axis("x")
    assert x.needs_homing
    x.home()
    assert x.position() == pytest.approx(0.0, abs=1e-3)  # X-LSM home switch at travel min
    assert x.move_to(12.3456) == pytest.approx(12.3456, abs=x.config.deadband)
    st = x.status()
    assert st.homed and not st.moving and not st.at_limit
    with pytest.raises(LimitError, match="outside soft limits"):
        x.move_to(60.0)
    y = rig.axis("y")
    y.home()
    rig.sim_parts.sim_axes["y"].inject_stall()
    with pytest.raises(DeviceFault, match="stall"):
        y.move_to(10.0)
    assert not rig.sim_parts.sim_axes["y"].moving  # the base class stopped it
    assert y.position() < 10.0  # it never got there
