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
from alignd.procedures import run_alignment
from alignd.procedures.angles import reference_order
from alignd.procedures.commission import run_commission
from alignd.procedures.sweep import holder_pose
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
