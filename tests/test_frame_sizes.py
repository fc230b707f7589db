"""Top cameras other than the thesis' 1280 x 720 webcam, through the whole alignment.

A lab's camera may be a 640 x 480 UVC webcam, which needs a coarser pixel (250 um/px at
the turntable) to see the 50 mm rim, or a 1920 x 1080 one at a finer pixel (100 um/px).
The simulated world draws either (``sim.world.top_frame_px``); the vision, the centre fit,
the report's picture and the rim pre-check take the frame as it comes.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from procedures_support import aligned_by_vision

from alignd.config import AligndConfig, load_config
from alignd.procedures import MemoryRecorder
from drivers.config import SimWorldConfig

REPO = Path(__file__).resolve().parents[1]
SIDE_SHAPE = (720, 1280)  # the side camera stays as it is
FACE = 770.0 / 800.0  # the holder's face is 30 mm above the turntable, seen from 800 mm


def _config(frame: tuple[int, int], um_per_px: float) -> AligndConfig:
    cfg = load_config(REPO / "configs" / "sim.yaml")
    assert cfg.sim is not None
    world = cfg.sim.world.model_copy(update={
        "top_frame_px": frame, "pixel_size_um": um_per_px,
        "axis_px": (frame[0] / 2 - 1.6, frame[1] / 2 + 3.7)})
    cams = [c.model_copy(update={"pixel_size_um": um_per_px * FACE}) if c.role == "top"
            else c for c in cfg.cameras]
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"world": world}),
                                  "cameras": cams})


@pytest.mark.parametrize(("frame", "um_per_px"), [((640, 480), 250.0), ((1920, 1080), 100.0)])
def test_another_frame_size_aligns_with_the_truth_inside_u(frame: tuple[int, int],
                                                          um_per_px: float) -> None:
    rec = MemoryRecorder(keep_images=True)
    out = aligned_by_vision(_config(frame, um_per_px), 1, rec).to_json()
    # the frames were the camera's size, and the rim pre-check measured the disc in them
    assert rec.images and {im.shape for im in rec.images.values()} <= {
        (frame[1], frame[0]), SIDE_SHAPE}
    assert (frame[1], frame[0]) in {im.shape for im in rec.images.values()}
    assert 0.0 < out["eccentricity"] < 0.02 and out["eccentricity_u"] < 0.002


def test_an_axis_outside_the_frame_is_a_clear_config_error() -> None:
    with pytest.raises(ValueError, match=r"axis_px \(652.3, 347.8\) outside the 640 x 480"):
        SimWorldConfig(top_frame_px=(640, 480))
