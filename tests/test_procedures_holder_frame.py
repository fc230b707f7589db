"""The holder frame's corner order where the holder's diagonal lies level in the top image.

The tracker numbers corners from the top-left (docs/configure.md). A 40 x 25 mm holder
turned 32 deg in the image has a corner straight left of its centre: there noise alone
decides which corner is first, u runs along the short side in half the frames, and the
alignment ended "not converged" (centre uncertainty 2 mm). Near the diagonal the config's
holder.size_mm now decides; clear of it a config whose u and v are the other way round is
refused before anything moves, naming the config that fits.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest
from procedures_support import commanded, scene_rig, sim_config

from alignd.config import AligndConfig, HolderConfig
from alignd.errors import ConfigError
from alignd.procedures import run_alignment
from alignd.procedures.angles import reference_order
from alignd.procedures.commission import run_commission
from alignd.procedures.holder_geometry import holder_pose
from alignd.procedures.tools import Tools
from alignd.simulated import standin_tools
from alignd.vision.holder import order_corners
from drivers.sim.scenes import rectangle


def _holder(yaw_deg: float, size: tuple[float, float] = (40.0, 25.0)) -> np.ndarray:
    """The corners in the holder frame's order (u along the first size, pointing right)."""
    return rectangle((640.0, 360.0), size[0] * 6.5, size[1] * 6.5, yaw_deg)


@pytest.mark.parametrize("yaw", [20.0, 31.9, 32.0, 32.1, 36.0, -31.99, -32.02, -36.0])
def test_near_the_diagonal_the_order_is_the_one_holder_size_gives(yaw: float) -> None:
    truth = _holder(yaw)
    seen = order_corners(truth)  # the tracker's order
    if abs(yaw) > 32.01:
        assert not np.allclose(seen, truth)  # the image's order has turned a corner on
    got = reference_order(seen, (40.0, 25.0))
    assert not got.swapped
    np.testing.assert_allclose(got.corners, truth)


@pytest.mark.parametrize("yaw, turn", [(40.0, 1), (-40.0, 3), (75.0, 1)])
def test_clear_of_the_diagonal_a_swapped_config_is_named_with_the_same_target(
        yaw: float, turn: int) -> None:
    truth = _holder(yaw)
    got = reference_order(order_corners(truth), (40.0, 25.0))
    assert got.swapped and got.turn == turn
    # the suggested target, with the lengths in the image's order, is the config's point
    want = holder_pose(truth, HolderConfig(size_mm=(40.0, 25.0), target_mm=(3.0, -17.5)))
    tu, tv = got.image_target_mm((3.0, -17.5))
    seen = holder_pose(got.corners, HolderConfig(size_mm=(25.0, 40.0), target_mm=(tu, tv)))
    np.testing.assert_allclose(seen.target_px, want.target_px, atol=1e-9)


def test_a_square_holder_keeps_the_image_order() -> None:
    seen = order_corners(_holder(40.0, (30.0, 30.0)))
    got = reference_order(seen, (30.0, 30.0))
    assert not got.swapped
    np.testing.assert_allclose(got.corners, seen)


def _yawed(yaw_deg: float, world_holder_mm: tuple[float, float] | None = None,
           **holder: Any) -> AligndConfig:
    cfg = sim_config()
    world = cfg.sim.world.model_copy(update={  # type: ignore[union-attr]
        "yaw_deg": yaw_deg, **({"holder_size_mm": world_holder_mm} if world_holder_mm else {})})
    return cfg.model_copy(update={
        "sim": cfg.sim.model_copy(update={"world": world}),  # type: ignore[union-attr]
        "holder": cfg.holder.model_copy(update=holder)})


def _tools(seed: int) -> Tools:
    """The world's corners + noise, numbered as the real tracker numbers them."""
    return standin_tools(np.random.default_rng(seed + 1000), 0.01)


@pytest.mark.parametrize("yaw", [32.0, 34.0])
def test_a_holder_with_its_diagonal_level_in_the_image_aligns(yaw: float) -> None:
    cfg = _yawed(yaw)
    rig, world = scene_rig(cfg, 3)
    res = run_alignment(rig, cfg, tools=_tools(3))
    assert res.verdict == "aligned", res.reason
    assert world.truth()["offset_norm_um"] <= cfg.procedure.tolerance_um


def test_a_camera_turned_past_the_diagonal_is_refused_with_the_config_that_fits() -> None:
    cfg = _yawed(40.0)
    rig, world = scene_rig(cfg, 4)
    start = world.truth()["offset_norm_um"]
    res = run_alignment(rig, cfg, tools=_tools(4))
    assert res.verdict == "fault" and res.exit_code == 2
    assert "holder frame swapped" in res.reason
    assert "holder.size_mm: [25, 40] and holder.target_mm: [17.5, 0]" in res.reason
    assert "no stage was moved" in res.reason
    # no correction move: only the calibration's, back where they started
    assert world.truth()["offset_norm_um"] == pytest.approx(start, abs=5.0)
    # the config it names aligns the same holder
    fixed = _yawed(40.0, size_mm=(25.0, 40.0), target_mm=(17.5, 0.0))
    rig, world = scene_rig(fixed, 4)
    res = run_alignment(rig, fixed, tools=_tools(4))
    assert res.verdict == "aligned", res.reason
    assert world.truth()["offset_norm_um"] <= fixed.procedure.tolerance_um
    assert commanded(rig, "x")  # (it moved)


@pytest.mark.parametrize("yaw", [34.0, 40.0])
def test_commission_names_a_swapped_holder_frame_only_clear_of_the_diagonal(
        yaw: float) -> None:
    cfg = _yawed(yaw)
    rig, _ = scene_rig(cfg, 2)
    rec = run_commission(rig, cfg, tools=_tools(2), abort=threading.Event())
    f = rec.finding("holder.size")
    assert f is not None, rec.reason
    if yaw < 36.0:  # within NEAR_DIAGONAL_DEG: the config's order
        assert f.verdict == "pass", f.message
        assert rec.holder_size_mm == pytest.approx((40.0, 25.0), rel=0.01)
    else:
        assert f.verdict == "fail" and f.name == "u and v swapped", f.message
        assert f.config_fix == {"holder.size_mm": [25.0, 40.0],
                                "holder.target_mm": [17.5, 0.0]}


def test_a_square_holder_at_its_diagonal_is_refused_before_it_moves() -> None:
    """A square holder with its diagonal level in the image: no numbering is better than
    the noise's, and a run chased a target turning round the holder (22 mm off after 4
    moves). It is refused on the first sweep, asking for the camera or holder turned."""
    cfg = _yawed(45.0, (30.0, 30.0), size_mm=(30.0, 30.0), target_mm=(0.0, -20.0))
    rig, world = scene_rig(cfg, 5)
    start = world.truth()["offset_norm_um"]
    res = run_alignment(rig, cfg, tools=_tools(5))
    assert res.verdict == "fault" and res.exit_code == 2, res.reason
    assert "holder frame ambiguous" in res.reason and "turn the top camera" in res.reason
    assert world.truth()["offset_norm_um"] == pytest.approx(start, abs=5.0)
    # turned 20 deg off its diagonal, the same holder aligns
    cfg = _yawed(25.0, (30.0, 30.0), size_mm=(30.0, 30.0), target_mm=(0.0, -20.0))
    rig, world = scene_rig(cfg, 5)
    res = run_alignment(rig, cfg, tools=_tools(5))
    assert res.verdict == "aligned", res.reason
    assert world.truth()["offset_norm_um"] <= cfg.procedure.tolerance_um


def test_commission_names_a_square_holder_at_its_diagonal() -> None:
    cfg = _yawed(45.0, (30.0, 30.0), size_mm=(30.0, 30.0), target_mm=(0.0, -20.0))
    rig, _ = scene_rig(cfg, 2)
    rec = run_commission(rig, cfg, tools=_tools(2), abort=threading.Event())
    f = rec.finding("holder.frame")
    assert f is not None and f.verdict == "fail" and f.name == "ambiguous", rec.reason
    assert rec.verdict == "failed" and "turn the top camera or the holder" in f.message


def _turned(rotation_deg: int, world_holder_mm: tuple[float, float] | None = None,
            **holder: Any) -> AligndConfig:
    """The reference rig with its top camera turned about its optical axis."""
    cfg = _yawed(1.2, world_holder_mm, **holder)
    world = cfg.sim.world.model_copy(  # type: ignore[union-attr]
        update={"camera_rotation_deg": rotation_deg})
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(  # type: ignore[union-attr]
        update={"world": world})})


def _refused_before_moving(cfg: AligndConfig, seed: int) -> tuple[str, dict[str, Any]]:
    rig, world = scene_rig(cfg, seed)
    start = world.truth()["offset_norm_um"]
    res = run_alignment(rig, cfg, tools=_tools(seed))
    assert res.verdict == "fault" and res.exit_code == 2, res.reason
    assert "no stage was moved" in res.reason
    assert world.truth()["offset_norm_um"] == pytest.approx(start, abs=5.0)
    return res.reason, res.details


def _aligns(cfg: AligndConfig, seed: int) -> None:
    rig, world = scene_rig(cfg, seed)
    res = run_alignment(rig, cfg, tools=_tools(seed))
    assert res.verdict == "aligned", res.reason
    assert world.truth()["offset_norm_um"] <= cfg.procedure.tolerance_um


def test_a_camera_turned_180_deg_is_refused_with_the_target_on_the_sample_side() -> None:
    """The config written for an upright camera puts the target on the holder's far side
    when the camera is turned 180 deg. A run chased that point 35 mm off the axis, 5 mm a
    move, and ended "not converged"; the first sweep now finds the point opposite it near
    the axis and refuses, naming it."""
    reason, details = _refused_before_moving(_turned(180), 6)
    assert "target on the other side" in reason
    assert "set holder.target_mm: [0, 17.5]" in reason and "180 deg" in reason
    # what the run's picture draws: the configured target 35 mm off, the named one near
    drawn = {t["role"]: t for t in details["holder_frame_refused"]["targets"]}
    assert drawn["config"]["offset_mm"] == pytest.approx(35.0, abs=3.0)
    assert drawn["fix"]["offset_mm"] < 5.0 and drawn["fix"]["target_mm"] == [0.0, 17.5]
    _aligns(_turned(180, target_mm=(0.0, 17.5)), 6)


@pytest.mark.parametrize(("rotation", "target"), [(90, (-17.5, 0.0)), (270, (17.5, 0.0))])
def test_a_swapped_frame_names_the_target_the_axis_is_near(
        rotation: int, target: tuple[float, float]) -> None:
    """A camera turned 90 or 270 deg: the same lengths, the same image, the targets of the
    two turns opposite each other. The sample was put near the axis, so the sweep names its
    side (the fix used to assume u had pointed right, wrong for 270 deg)."""
    reason, _ = _refused_before_moving(_turned(rotation), 7)
    assert "holder frame swapped" in reason
    assert f"holder.target_mm: [{target[0]:g}, {target[1]:g}] (the point the sample is at" \
        in reason
    _aligns(_turned(rotation, size_mm=(25.0, 40.0), target_mm=target), 7)


def test_a_square_holder_turned_a_quarter_is_refused_with_the_turned_target() -> None:
    cfg = _turned(90, (30.0, 30.0), size_mm=(30.0, 30.0), target_mm=(0.0, -20.0))
    reason, _ = _refused_before_moving(cfg, 8)
    assert "target on the other side" in reason and "a quarter turn" in reason
    assert "set holder.target_mm: [-20, 0]" in reason, reason


def test_a_sample_far_off_the_axis_with_no_turned_target_near_it_is_not_refused() -> None:
    """Only a turned target near the axis names the config wrong: a sample put 6 mm off
    the axis by hand is moved there as before."""
    from alignd.procedures.holder_geometry import rot
    from alignd.procedures.target_side import MIN_TARGET_MM, check_target_side

    holder = HolderConfig(size_mm=(40.0, 25.0), target_mm=(0.0, -17.5))
    base = _holder(1.2) - np.array([640.0, 360.0])
    angles = np.linspace(-10.0, 10.0, 11)

    def sweep(axis_from_target_mm: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        target = holder_pose(base, holder).target_px
        axis = target + 6.5 * np.asarray(axis_from_target_mm)
        return np.array([(base - axis) @ rot(a).T + axis for a in angles]), axis

    for off in [(6.0, 0.0), (0.0, 12.0), (0.0, 24.0)]:  # the opposite point 11 mm off
        check_target_side(*_with_angles(sweep(off), angles), holder)
    with pytest.raises(ConfigError, match=r"target on the other side.*\[0, 17.5\]"):
        check_target_side(*_with_angles(sweep((0.5, 35.0)), angles), holder)
    near = holder.model_copy(update={"target_mm": (0.0, -0.9 * MIN_TARGET_MM)})
    pts, axis = sweep((0.0, 1.8 * MIN_TARGET_MM))
    check_target_side(pts, angles, axis, near)


def _with_angles(sweep: tuple[np.ndarray, np.ndarray], angles: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return sweep[0], angles, sweep[1]


@pytest.mark.parametrize(("rotation", "target"), [(270, [17.5, 0.0]), (180, [0.0, 17.5])])
def test_commission_takes_the_targets_side_from_the_translator(
        rotation: int, target: list[float]) -> None:
    """The translator moves towards the target (docs/configure.md): a swapped frame's fix
    takes that side, and a translator moving away from the target names both causes."""
    cfg = _turned(rotation)
    rig, _ = scene_rig(cfg, 2)
    rec = run_commission(rig, cfg, tools=_tools(2), abort=threading.Event())
    if rotation == 270:
        f = rec.finding("holder.size")
        assert f is not None and f.name == "u and v swapped", rec.reason
        assert f.config_fix == {"holder.size_mm": [25.0, 40.0], "holder.target_mm": target}
        assert "the side the translator moves towards" in f.message
        # the turntable measured in the image's own frame: rectified onto the config's
        # lengths, the turn read as a 1.2 deg angle error and 207 um of error motion
        runout, angle = rec.finding("turntable.runout"), rec.finding("turntable.angle_error")
        assert runout is not None and runout.verdict == "pass" and runout.value < 10.0
        assert angle is not None and angle.verdict == "pass" and angle.value < 0.01
    else:
        f = rec.finding("axis.translator.direction")
        assert f is not None and f.name == "away from the target", rec.reason
        assert f.config_fix == {"holder.target_mm": target}
        assert "the translator's direction is reversed" in f.message
        # x and y inverted too: the three together name the camera, not the stages
        turned = rec.finding("top.turned_half")
        assert turned is not None and turned.name == "camera turned 180 deg", rec.reason
        assert turned.config_fix == {"holder.target_mm": target}
