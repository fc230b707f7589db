"""The rim through a wide lens (``cameras[].lens``): a round turntable seen straight down
is a circle only in the undistorted image; in the frame the lens squashes its far side
more than its near one, and the pre-check read the camera as tilted."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from alignd.vision import Lens
from alignd.vision.rim import fit_rim

LENS = Lens(1000.0, (640.0, 360.0), -0.08)  # a webcam's (73 deg across the diagonal)


def _disc(centre: tuple[float, float], a: float, b: float, theta_deg: float,
          seed: int) -> np.ndarray:
    """A bright disc (its outline the ellipse a, b, theta about ``centre`` in the
    undistorted image) on a darker floor, drawn through LENS: each pixel's 4 x 4
    sub-points are undistorted and tested against the ellipse; blur 0.8 px, 1 DN noise."""
    h, w, n = 720, 1280, 4
    sub = (np.arange(n) + 0.5) / n - 0.5
    yy, xx = np.mgrid[0:h, 0:w]
    cover = np.zeros((h, w))
    t = math.radians(theta_deg)
    for dy in sub:
        for dx in sub:
            p = LENS.undistort(np.column_stack([(xx + dx).ravel(), (yy + dy).ravel()]))
            u = (p[:, 0] - centre[0]) * math.cos(t) + (p[:, 1] - centre[1]) * math.sin(t)
            v = -(p[:, 0] - centre[0]) * math.sin(t) + (p[:, 1] - centre[1]) * math.cos(t)
            cover += ((u / a) ** 2 + (v / b) ** 2 <= 1.0).reshape(h, w)
    img = 60.0 + 120.0 * cover / (n * n)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    img += np.random.default_rng(seed).normal(0.0, 1.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize(("centre", "e_true"), [((760.0, 380.0), 0.02), ((560.0, 330.0), 0.1)])
def test_a_configured_lens_gives_the_rims_own_eccentricity(
        centre: tuple[float, float], e_true: float) -> None:
    a = 300.0
    b = a * math.sqrt(1.0 - e_true**2)
    img = _disc(centre, a, b, 25.0, seed=3)
    seen = fit_rim(img, None, None)
    fit = fit_rim(img, None, None, lens=LENS)
    # in the frame the lens alone reads as a tilt (a round rim 120 px off the principal
    # point: e 0.07), or moves the tilt's own
    assert abs(seen.eccentricity - e_true) > 0.01
    assert fit.eccentricity == pytest.approx(e_true, abs=max(0.003, 3 * fit.eccentricity_std))
    np.testing.assert_allclose(fit.center_px, centre, atol=0.05)
    assert fit.rms_px < 0.1


def test_analyze_rim_takes_the_lens(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``alignctl analyze rim --k1 --focal-px --principal`` (or ``--config`` with
    ``cameras[].lens``) fits the rim undistorted, one frame or the mean of several."""
    from alignd.cli import main

    img = _disc((760.0, 380.0), 300.0, 300.0 * math.sqrt(1 - 0.1**2), 25.0, seed=4)
    f = tmp_path / "rim.png"
    cv2.imwrite(str(f), img)
    lens = ["--k1", "-0.08", "--focal-px", "1000", "--principal", "640,360"]
    for extra in ([], ["--mean"]):
        assert main(["analyze", "rim", str(f), str(f), *extra, *lens, "--json"]) == 0
        objs = [json.loads(line) for line in capsys.readouterr().out.splitlines()
                if line.startswith("{")]
        assert objs and all(o["eccentricity"] == pytest.approx(0.1, abs=0.003) for o in objs)
    assert main(["analyze", "rim", str(f), "--json"]) == 0
    plain = json.loads(capsys.readouterr().out.splitlines()[0])
    assert abs(plain["eccentricity"] - 0.1) > 0.01
