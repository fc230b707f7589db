"""A camera streaming MJPEG (the thesis' UVC webcam) through the whole alignment.

JPEG coding moves the holder's edges by a few hundredths of a pixel in a pattern fixed to
the 8 x 8 blocks, which the holder crosses as it turns; the side camera's tilt carries a
coding bias of its own. ``sim.world.jpeg_quality`` codes the simulated cameras' frames as
such a camera does; the lowest quality the corpus draws (60) still aligns, with the truth
inside the stated uncertainty (sim.yaml decides by simple acceptance, so "aligned" says
the measured offset is within the tolerance, and the truth lies within U of it).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from procedures_support import aligned_by_vision

from alignd.config import AligndConfig, load_config
from alignd.procedures import MemoryRecorder
from alignd.simulated import build_direct_rig
from alignd.vision.jpeg_bias import jpeg_quality

REPO = Path(__file__).resolve().parents[1]


def _config(quality: int) -> AligndConfig:
    cfg = load_config(REPO / "configs" / "sim.yaml")
    assert cfg.sim is not None
    world = cfg.sim.world.model_copy(update={"jpeg_quality": quality})
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"world": world})})


def test_the_simulated_cameras_code_their_frames() -> None:
    rig, _ = build_direct_rig(_config(70), seed=1)
    for role in ("top", "side"):
        cam = rig.camera(role)
        assert cam is not None
        cam.open()
        assert jpeg_quality(cam.grab().gray) == 70, role


@pytest.mark.parametrize("quality", [60])
def test_mjpeg_frames_align(quality: int) -> None:
    cfg = _config(quality)
    rec = MemoryRecorder()
    out = aligned_by_vision(cfg, 2, rec).to_json()
    assert out["tilt_deg"] == pytest.approx(cfg.sim.world.tilt_deg, abs=0.003)  # type: ignore[union-attr]
    assert any(f"JPEG-coded frames, quality {quality}" in e for e in rec.events)
