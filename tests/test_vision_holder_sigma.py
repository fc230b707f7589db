"""The holder's corner_sigma_px is an honest standard error: on seeded corpus scenes the
corner errors over it have an RMS near 1 (the line fits' covariance alone, which counts
every column as independent and leaves out the error common to a whole side, gave ~2.5)."""

from __future__ import annotations

import numpy as np

from alignd.vision.edges import EdgePoints, fit_line, residual_correlation
from alignd.vision.holder import order_corners, track_holder
from alignd.vision.lens import Lens
from drivers.sim.scenes import TOP_CATEGORIES, random_top_scene

SEED, N_PER_CATEGORY = 4711, 3


def _pulls() -> np.ndarray:
    """Per scene: the largest corner error over the reported corner_sigma_px."""
    rng = np.random.default_rng(SEED)
    out = []
    for _ in range(N_PER_CATEGORY):
        for cat in TOP_CATEGORIES:
            sc = random_top_scene(rng, cat)
            lens = Lens(sc.lens[0], sc.lens[1], sc.lens[2]) if sc.lens else None
            det = track_holder(sc.image, expected_size_px=sc.expected_size_px, lens=lens)
            assert det.ok, (cat, det.reason)
            truth = order_corners(sc.corners_px)
            e = np.linalg.norm(order_corners(det.corners_px, truth) - truth, axis=1)
            assert det.fit_sigma_px < det.corner_sigma_px
            out.append(float(e.max()) / det.corner_sigma_px)
    return np.array(out)


def test_corner_sigma_matches_the_corner_errors() -> None:
    pulls = _pulls()
    rms = float(np.sqrt(np.mean(pulls ** 2)))
    assert 0.6 <= rms <= 1.5, pulls.round(2)
    assert pulls.max() < 4.0, pulls.round(2)


def _points(res: np.ndarray) -> EdgePoints:
    x = np.arange(res.size, dtype=float)
    return EdgePoints(np.column_stack([x, 50.0 + 0.01 * x + res]), np.full(res.size, 80.0),
                      False)


def test_residual_correlation_counts_correlated_columns_once() -> None:
    rng = np.random.default_rng(3)
    iid = rng.normal(0.0, 0.05, 400)
    ln = fit_line(_points(iid))
    assert ln is not None
    assert 1.0 <= residual_correlation(ln, _points(iid)) < 1.3
    # errors shared by blocks of 8 columns (JPEG blocks): the fit's variance is too small
    # by about the block length
    blocks = np.repeat(rng.normal(0.0, 0.05, 50), 8) + rng.normal(0.0, 0.01, 400)
    ln = fit_line(_points(blocks))
    assert ln is not None
    assert residual_correlation(ln, _points(blocks)) > 3.0


def test_where_the_two_methods_disagree_the_refined_corners_carry_the_difference() -> None:
    """Corpus seed 2124 #188 at 640 x 480 (a light holder, blur 1.85 px, vignetting 0.40,
    a steep lighting gradient): the profile fit's corners, 0.07 px off, disagree with the
    area method's, which under that light err (0.51 px). The refined corners are
    returned (the area method's were, before), unconfirmed (no side blurs), and their
    stated sigma holds half the two methods' difference."""
    rng = np.random.default_rng(2124)
    for i in range(189):
        sc = random_top_scene(rng, TOP_CATEGORIES[i % len(TOP_CATEGORIES)], (640, 480))
    lens = Lens(sc.lens[0], sc.lens[1], sc.lens[2]) if sc.lens else None
    det = track_holder(sc.image, expected_size_px=sc.expected_size_px, lens=lens)
    assert det.ok, det.reason
    assert det.side_blur_px == ()  # not confirmed by the area method
    truth = order_corners(sc.corners_px)
    e = np.linalg.norm(order_corners(det.corners_px, truth) - truth, axis=1)
    assert e.max() < 0.15, e.round(3)
    assert det.corner_sigma_px > 0.15  # half of the 0.5 px the methods differ by
    assert e.max() / det.corner_sigma_px < 2.0, (e.round(3), det.corner_sigma_px)
