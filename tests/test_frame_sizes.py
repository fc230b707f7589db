"""Cameras other than the thesis' 1280 x 720 webcams, through the whole alignment.

A lab's cameras may be 640 x 480 UVC webcams, the top one needing a coarser pixel (250
um/px at the turntable) to see the 50 mm rim and the side one (120 um/px) to hold the pole
and the sample, or 1920 x 1080 ones at finer pixels (100 and 40 um/px). The simulated world
draws either (``sim.world.top_frame_px``, ``side_frame_px``, ``side_pixel_size_um``); the
vision, the centre fit, the rim and tilt pre-checks take the frames as they come.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from procedures_support import aligned_by_vision

from alignd.config import AligndConfig, load_config
from alignd.procedures import MemoryRecorder
from alignd.simulated import build_direct_rig
from drivers.config import SimWorldConfig

REPO = Path(__file__).resolve().parents[1]
FACE = 770.0 / 800.0  # the holder's face is 30 mm above the turntable, seen from 800 mm


def _config(frame: tuple[int, int], um_per_px: float, side_um_per_px: float
            ) -> AligndConfig:
    cfg = load_config(REPO / "configs" / "sim.yaml")
    assert cfg.sim is not None
    world = cfg.sim.world.model_copy(update={
        "top_frame_px": frame, "pixel_size_um": um_per_px,
        "axis_px": (frame[0] / 2 - 1.6, frame[1] / 2 + 3.7),
        "side_frame_px": frame, "side_pixel_size_um": side_um_per_px})
    cams = [c.model_copy(update={"pixel_size_um": um_per_px * FACE}) if c.role == "top"
            else c for c in cfg.cameras]
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"world": world}),
                                  "cameras": cams})


@pytest.mark.parametrize(("frame", "um_per_px", "side_um_per_px"),
                         [((640, 480), 250.0, 120.0), ((1920, 1080), 100.0, 40.0)])
def test_other_frame_sizes_align_with_the_truth_inside_u(
        frame: tuple[int, int], um_per_px: float, side_um_per_px: float) -> None:
    cfg = _config(frame, um_per_px, side_um_per_px)
    rec = MemoryRecorder(keep_images=True)
    out = aligned_by_vision(cfg, 1, rec).to_json()
    # the frames were the cameras' size, and the pre-checks measured the disc and the tilt
    assert rec.images and {im.shape for im in rec.images.values()} == {(frame[1], frame[0])}
    rig, _ = build_direct_rig(cfg, seed=1)
    side = rig.camera("side")
    assert side is not None
    side.open()
    assert side.grab().gray.shape == (frame[1], frame[0])
    assert 0.0 < out["eccentricity"] < 0.02 and out["eccentricity_u"] < 0.002
    assert cfg.sim is not None
    assert abs(out["tilt_deg"] - cfg.sim.world.tilt_deg) <= 2 * out["tilt_u_deg"] + 0.001


def test_an_axis_outside_the_frame_is_a_clear_config_error() -> None:
    with pytest.raises(ValueError, match=r"axis_px \(652.3, 347.8\) outside the 640 x 480"):
        SimWorldConfig(top_frame_px=(640, 480))
