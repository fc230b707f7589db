"""bench/vision_bounds.py: the Cramer-Rao bounds of the holder's corners and of a side
edge's angle are bounds the vision comes near on frames drawn exactly as its models assume
(so the corpus tables' ratios read as distance from what the pixels allow)."""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np
import pytest
from bench_modules import load_bench
from scipy.special import ndtr

from alignd.vision import holder
from alignd.vision.edge_profile import fit_vertical_edge
from alignd.vision.holder import order_corners, track_holder


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_bench("vision_bounds")


def _rectangle(blur: float, angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """A lighter rectangle (180 DN on 60) of 260 x 150 px, turned by ``angle_deg``,
    blurred by a Gaussian of ``blur`` px (with the pixel's footprint): the noise-free
    frame and its corners."""
    h, w = 360, 480
    ctr = np.array([241.3, 178.6])
    th = math.radians(angle_deg)
    u, v = np.array([math.cos(th), math.sin(th)]), np.array([-math.sin(th), math.cos(th)])
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    du = (xx - ctr[0]) * u[0] + (yy - ctr[1]) * u[1]
    dv = (xx - ctr[0]) * v[0] + (yy - ctr[1]) * v[1]
    se = math.sqrt(blur ** 2 + 1.0 / 12.0)
    a, b = 130.0, 75.0
    inside = (ndtr((du + a) / se) - ndtr((du - a) / se)) * (ndtr((dv + b) / se)
                                                            - ndtr((dv - b) / se))
    corners = np.array([ctr + su * a * u + sv * b * v
                        for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    return 60.0 + 120.0 * inside, corners


@pytest.mark.parametrize("model", ["quadrilateral", "rectangle"])
@pytest.mark.parametrize("blur, angle", [(0.7, 17.0), (1.6, -38.0)])
def test_tracker_corners_scatter_near_the_bound(bench: ModuleType, blur: float,
                                                angle: float, model: str,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """Four free sides come near the quadrilateral's bound; sharing one direction where
    they agree with a rectangle (alignd.vision.holder_square), as they do here, they
    come near the rectangle's, which is 0.6 of it (measured: free 1.05 / 1.32 times the
    quadrilateral's bound at a blur of 0.7 / 1.6 px, square 1.08 / 1.29 times the
    rectangle's)."""
    if model == "quadrilateral":
        monkeypatch.setattr(holder, "square_sides", lambda lines, _points: lines)
    mean, truth = _rectangle(blur, angle)
    var = bench.pixel_variance(mean, 2.0, 40.0)
    bound = bench.corner_bound(mean, truth, blur, var, model)
    assert np.all(np.isfinite(bound)) and np.all(bound > 0)
    rng = np.random.default_rng(11)
    errs = []
    for _ in range(16):
        frame = np.clip(np.rint(mean + rng.standard_normal(mean.shape) * np.sqrt(var)),
                        0, 255).astype(np.uint8)
        det = track_holder(frame, expected_size_px=(260.0, 150.0))
        assert det.ok, det.reason
        errs.append(order_corners(det.corners_px, truth) - truth)
    e = np.array(errs)
    scatter = np.sqrt(((e - e.mean(axis=0)) ** 2).sum(axis=2).mean())
    ratio = scatter / math.sqrt(float(np.mean(bound ** 2)))
    # the bound holds (within the 16 draws' own scatter) and the tracker is near it
    assert 0.85 < ratio < 1.5, (scatter, bound)


def test_a_rectangle_is_bounded_tighter_than_a_quadrilateral(bench: ModuleType) -> None:
    """One direction for four sides: each corner's bound falls (about 0.6 here: at a
    line's end three quarters of the variance is its direction's)."""
    mean, truth = _rectangle(0.7, 17.0)
    var = bench.pixel_variance(mean, 2.0, 40.0)
    quad = bench.corner_bound(mean, truth, 0.7, var)
    rect = bench.corner_bound(mean, truth, 0.7, var, "rectangle")
    assert np.all(rect < 0.8 * quad) and np.all(rect > 0.4 * quad), (rect, quad)


def test_bound_scales_with_the_noise_and_grows_with_the_blur(bench: ModuleType) -> None:
    mean, truth = _rectangle(0.7, 17.0)
    var = np.full(mean.shape, 4.0)
    b1 = bench.corner_bound(mean, truth, 0.7, var)
    b2 = bench.corner_bound(mean, truth, 0.7, 4.0 * var)
    assert np.allclose(b2, 2.0 * b1, rtol=1e-6)
    soft, _ = _rectangle(1.6, 17.0)
    assert np.all(bench.corner_bound(soft, truth, 1.6, var) > 1.2 * b1)


def test_side_edge_angle_scatters_near_its_bound(bench: ModuleType) -> None:
    """A near-vertical edge (0.3 deg, blur 1 px, 120 DN) over 400 rows: the side's profile
    fit (each row's levels and slopes free) against the bound with the slopes free."""
    h, w, blur, angle = 400, 48, 1.0, 0.3
    y_mid = (h - 1) / 2
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    x_line = 23.4 - (yy - y_mid) * math.tan(math.radians(angle))
    se = math.sqrt(blur ** 2 + 1.0 / 12.0)
    mean = 60.0 + 120.0 * ndtr((xx - x_line) / se)
    var = bench.pixel_variance(mean, 2.0, 40.0)
    free = bench.edge_angle_bound(mean, var, 23.4, y_mid, angle, (0, h - 1), blur)
    known = bench.edge_angle_bound(mean, var, 23.4, y_mid, angle, (0, h - 1), blur,
                                   free_slopes=False)
    assert 0 < known < free < math.inf
    rng = np.random.default_rng(5)
    angles = []
    for _ in range(16):
        frame = mean + rng.standard_normal(mean.shape) * np.sqrt(var)
        fit = fit_vertical_edge(frame, 23.4, 0.0, y_mid, np.arange(h), blur0=1.2)
        assert fit is not None
        angles.append(fit.angle_deg)
    assert abs(float(np.mean(angles)) - angle) < 3 * free  # the fit finds the edge
    ratio = float(np.std(angles, ddof=1)) / free
    assert 0.7 < ratio < 1.5, (np.std(angles, ddof=1), free)
