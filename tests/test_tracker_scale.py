"""The daemon's tracker on the reference simulated rig: the expected holder size comes from
``holder.size_mm`` and the top camera's ``pixel_size_um``, which is only as good as the
config. ``configs/sim.yaml`` said 160 um/px, the scale at the turntable plane; the holder's
face is 30 mm nearer the 800 mm camera, so the holder was 3.9 % larger in the image than
the config predicted (commissioning measures 154 um/px and passes 160: under 5 %). The
config now says 154; the tracker must still find the holder with the plane's 160.

The expected-size vote used to pair opposite sides only within 1 px at 1/4 scale (about
2 %): on this scene it proposed only wrong boxes, they used up the candidates, and the
precheck failed "holder not found" on some poses (a check passed, the next one faulted).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from alignd.config import AligndConfig, load_config
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


def plane_scale_config() -> AligndConfig:
    """The reference config with the turntable plane's pixel size (160 um/px), 3.9 % off
    the holder face's."""
    cfg = load_config(REPO / "configs" / "sim.yaml")
    cams = [c.model_copy(update={"pixel_size_um": 160.0}) if c.role == "top" else c
            for c in cfg.cameras]
    return cfg.model_copy(update={"cameras": cams})


def test_the_reference_config_gives_the_holder_faces_scale(
        reference_frames: list[Frame]) -> None:
    free = track_holder(reference_frames[0].gray)  # no size given: the ladder finds it
    assert free.ok
    expected = expected_holder_px(load_config(REPO / "configs" / "sim.yaml"))
    assert expected is not None
    assert max(free.size_px) / expected[0] == pytest.approx(1.0, abs=0.003)
    assert min(free.size_px) / expected[1] == pytest.approx(1.0, abs=0.003)
    plane = expected_holder_px(plane_scale_config())
    assert plane is not None
    # 800 / (800 - 30): the holder's face is nearer the camera than the turntable plane
    assert max(free.size_px) / plane[0] == pytest.approx(800 / 770, abs=0.002)


@pytest.mark.parametrize("which", ["holder face", "turntable plane"])
def test_the_daemons_tracker_finds_the_holder_on_the_reference_scene(
        reference_frames: list[Frame], which: str) -> None:
    cfg = (load_config(REPO / "configs" / "sim.yaml") if which == "holder face"
           else plane_scale_config())
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
