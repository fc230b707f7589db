"""Side camera: sample/pole angles and tilt against the renderer's truth; failures."""

from __future__ import annotations

import numpy as np
import pytest

from alignd.errors import VisionError
from alignd.vision.side import baseline_tilt, measure_tilt
from drivers.config import SimWorldConfig
from drivers.sim.render import RenderOptions, posed_world, render_side, side_truth


def _side(tilt: float, opts: RenderOptions, seed: int = 1):
    w = posed_world(SimWorldConfig(tilt_deg=tilt), seed=seed)
    sc = w.side_scene()
    return render_side(sc, opts, np.random.default_rng(seed)), side_truth(sc, opts)


@pytest.mark.parametrize(("tilt", "roll", "grad"), [
    (0.3, 0.0, (0.0, 0.0)),
    (0.3, 0.0, (0.3, 0.2)),
    (-0.12, 0.8, (0.3, 0.2)),
    (0.0, -0.6, (-0.2, 0.3)),
])
def test_tilt_to_two_thousandths_of_a_degree(tilt: float, roll: float, grad) -> None:
    img, truth = _side(tilt, RenderOptions(gradient=grad, side_roll_deg=roll))
    m = measure_tilt(img)
    assert m.tilt_deg == pytest.approx(truth["tilt_deg"], abs=0.002)
    assert m.sample_angle_deg == pytest.approx(truth["sample_angle_deg"], abs=0.002)
    assert m.pole_angle_deg == pytest.approx(truth["pole_angle_deg"], abs=0.002)
    assert len(m.pole_edges) == 2 and len(m.sample_edges) == 2
    assert 0 < m.sigma_deg < 0.002
    assert m.pole_edges[0].x_mid_px == pytest.approx(truth["pole_x_px"], abs=0.3)


def test_light_on_dark_polarity() -> None:
    opts = RenderOptions(side_background_dn=40.0, side_sample_dn=190.0, pole_dn=210.0,
                         gradient=(0.2, 0.0))
    img, truth = _side(0.25, opts, seed=4)
    assert measure_tilt(img).tilt_deg == pytest.approx(truth["tilt_deg"], abs=0.002)


def test_baseline_hough_is_coarser_but_sane() -> None:
    img, truth = _side(0.3, RenderOptions())
    _s, _p, t = baseline_tilt(img, truth["pole_x_px"], truth["sample_x_px"])
    assert t == pytest.approx(truth["tilt_deg"], abs=0.2)


def test_missing_targets_raise() -> None:
    with pytest.raises(VisionError, match="blank"):
        measure_tilt(np.full((720, 1280), 90, np.uint8))
    # only the pole: no sample edge
    img = np.full((720, 1280), 200, np.uint8)
    img[:, 300:400] = 50
    with pytest.raises(VisionError, match="sample edge not found"):
        measure_tilt(img)
    # only a short object: no pole
    img = np.full((720, 1280), 200, np.uint8)
    img[100:600, 800:880] = 60
    with pytest.raises(VisionError, match="pole not found"):
        measure_tilt(img)
