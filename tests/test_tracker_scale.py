"""The daemon's tracker on the reference simulated rig: the expected holder size comes from
``holder.size_mm`` and the top camera's ``pixel_size_um``, which is only as good as the
config. ``configs/sim.yaml`` says 160 um/px, the scale at the turntable plane; the holder's
face is 30 mm nearer the 800 mm camera, so the holder is 3.9 % larger in the image than
the config predicts (commissioning measures 154 um/px and passes it: under 5 %).

The expected-size vote used to pair opposite sides only within 1 px at 1/4 scale (about
2 %): on this scene it proposed only wrong boxes, they used up the candidates, and the
precheck failed "holder not found" on some poses (a check passed, the next one faulted).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from alignd.config import load_config
from alignd.procedures.tools import default_tools, expected_holder_px
from alignd.simulated import build_direct_rig
from alignd.vision import order_corners, track_holder
from drivers.camera import Frame

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def reference_frames() -> list[Frame]:
    """Three top frames of the reference rig, world seed 3 (the pose that failed)."""
    cfg = load_config(REPO / "configs" / "sim.yaml")
    rig, _world = build_direct_rig(cfg, seed=3)
    top = rig.camera("top")
    assert top is not None
    return [top.grab() for _ in range(3)]


def test_the_reference_config_expects_a_smaller_holder_than_the_camera_sees(
        reference_frames: list[Frame]) -> None:
    cfg = load_config(REPO / "configs" / "sim.yaml")
    free = track_holder(reference_frames[0].gray)  # no size given: the ladder finds it
    assert free.ok
    expected = expected_holder_px(cfg)
    assert expected is not None
    # 800 / (800 - 30): the holder's face is nearer the camera than the turntable plane
    assert max(free.size_px) / expected[0] == pytest.approx(800 / 770, abs=0.002)
    assert min(free.size_px) / expected[1] == pytest.approx(800 / 770, abs=0.002)


def test_the_daemons_tracker_finds_the_holder_on_the_reference_scene(
        reference_frames: list[Frame]) -> None:
    cfg = load_config(REPO / "configs" / "sim.yaml")
    for frame in reference_frames:
        tools = default_tools(cfg)  # a fresh tracker: the precheck's full search, no seed
        got = tools.track(frame)
        assert got.ok, got.reason
        free = track_holder(frame.gray)
        np.testing.assert_allclose(got.corners_px, order_corners(free.corners_px), atol=0.05)


@pytest.mark.parametrize("error", [-0.10, -0.06, -0.04, 0.04, 0.06, 0.10])
def test_an_expected_size_a_few_percent_off_still_finds_the_holder(
        reference_frames: list[Frame], error: float) -> None:
    """Within the size tolerance (12 %) the search finds the holder, at the same corners as
    a search that is not told the size."""
    g = reference_frames[1].gray
    free = track_holder(g)
    size = (max(free.size_px) * (1 + error), min(free.size_px) * (1 + error))
    det = track_holder(g, expected_size_px=size)
    assert det.ok, det.reason
    np.testing.assert_allclose(order_corners(det.corners_px),
                               order_corners(free.corners_px), atol=0.05)


def test_a_holder_beyond_the_size_tolerance_is_still_refused(
        reference_frames: list[Frame]) -> None:
    from alignd.errors import VisionError

    g = reference_frames[2].gray
    free = track_holder(g)
    size = (max(free.size_px) * 1.25, min(free.size_px) * 1.25)
    try:
        det = track_holder(g, expected_size_px=size)
    except VisionError:
        return
    assert not det.ok and np.all(np.isnan(det.corners_px))
