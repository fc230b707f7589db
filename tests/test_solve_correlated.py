"""The rigid fit's covariance where the features' errors are not independent.

Corners of a holder are found as crossings of its sides, so two corners on one side share
that side's error (alignd.solve.rigid._translation_sigma); a texture, a shadow or clutter
under one corner's path biases that corner as the holder turns across it, smoothly with
the angle, which no residual shows, only that corner's own centre leaving the others'
(alignd.solve.rigid._features_excess)."""

from __future__ import annotations

import numpy as np

from alignd.solve import Sweep, solve_centre
from alignd.solve.synthetic import make_sweep

CHI2_2_95 = 5.991464547107979


def _side_errors(points: np.ndarray, sd: float, rng: np.random.Generator) -> np.ndarray:
    """Each frame's four sides offset by their own error, each corner moved by its two
    sides' (the holder nearly square to the axes: corners 0-3 clockwise from top-left)."""
    out = points.copy()
    for f in range(points.shape[0]):
        top, right, bottom, left = rng.normal(0.0, sd, 4)
        out[f, 0] += (left, top)
        out[f, 1] += (right, top)
        out[f, 2] += (right, bottom)
        out[f, 3] += (left, bottom)
    return out


def _nse(res_cov: np.ndarray, e: np.ndarray) -> float:
    return float(e @ np.linalg.solve(res_cov, e))


def test_corners_sharing_sides_widen_the_covariance() -> None:
    """With the corners' errors from their sides, all residuals' scatter understates the
    centre's (each side's offset moves two corners alike); the frames' mean residual
    shows it. Over 60 seeded sweeps the normalised squared error's mean is near its 2
    (about 4 from the residuals' scale alone, which the extra keeps)."""
    nse, plain = [], []
    for s in range(60):
        sw, tr = make_sweep(n_frames=11, noise_px=0.0, seed=s)
        pts = _side_errors(sw.points, 0.03, np.random.default_rng(s))
        res = solve_centre(Sweep(sw.angles_deg, pts), "rigid")
        e = res.center_px - tr.center_px
        nse.append(_nse(res.cov_px2, e))
        plain.append(_nse(res.extra["cov_independent_px2"], e))
        assert res.extra["sigma_translation_px"] > 0.0
    assert float(np.mean(plain)) > 3.2
    assert 1.4 < float(np.mean(nse)) < 3.0
    assert np.mean(np.asarray(nse) <= CHI2_2_95) >= 0.85


def test_error_motion_is_left_to_the_floor() -> None:
    """A turntable's error motion moves every feature alike too, but smoothly with the
    angle: the frame-to-frame scale leaves it out (a 0.2 px wobble over the sweep against
    0.03 px of noise), so the covariance is not widened by what the runout map and the
    floor count, and sweeps that disagree with a stale map still show it."""
    ratios = []
    for s in range(20):
        sw, _ = make_sweep(n_frames=21, noise_px=0.03, seed=300 + s)
        a = np.deg2rad(sw.angles_deg)
        wobble = 0.2 * np.stack([np.cos(3 * a + s), np.sin(2 * a + s)], axis=-1)
        pts = sw.points + wobble[:, None, :]
        res = solve_centre(Sweep(sw.angles_deg, pts), "rigid")
        ratios.append(res.extra["sigma_translation_px"] / res.extra["sigma_px"])
    assert float(np.median(ratios)) < 1.15


def test_one_corner_biased_along_the_sweep_adds_the_excess() -> None:
    """A corner whose error grows with the angle (clutter under its path: 0.3 px from end
    to end of the sweep, against 0.03 px of noise) shifts the fitted centre by more than
    the noise allows (22 of 30 centres outside their 95 % ellipse); its own centre then
    leaves the others' and the excess covers the shift."""
    inside_old, inside_new, excess = 0, 0, []
    for s in range(30):
        sw, tr = make_sweep(n_frames=11, noise_px=0.03, seed=100 + s)
        pts = sw.points.copy()
        pts[:, 0, 0] += 0.3 * sw.angles_deg / 20.0
        res = solve_centre(Sweep(sw.angles_deg, pts), "rigid")
        e = res.center_px - tr.center_px
        inside_old += _nse(res.extra["cov_independent_px2"], e) <= CHI2_2_95
        inside_new += _nse(res.cov_px2, e) <= CHI2_2_95
        excess.append(float(np.trace(res.extra["features_excess_px2"])))
    assert inside_old <= 12
    assert inside_new >= 28
    assert min(excess) > 0.0


def test_independent_noise_keeps_the_covariance() -> None:
    """With independent noise the frames' mean residual scales as one residual (the ratio
    near 1, the covariance widened only by its scatter) and the features' centres agree
    within their noise: no excess in at least 90 % of sweeps (the test's level is 95 %)."""
    no_excess, ratio2 = 0, []
    for s in range(60):
        sw, _ = make_sweep(n_frames=21, noise_px=0.3, seed=500 + s)
        res = solve_centre(sw, "rigid")
        no_excess += not np.any(res.extra["features_excess_px2"])
        r2 = (res.extra["sigma_translation_px"] / res.extra["sigma_px"]) ** 2
        ratio2.append(r2)
        np.testing.assert_allclose(res.cov_px2 - res.extra["features_excess_px2"],
                                   res.extra["cov_independent_px2"] * max(1.0, r2))
    assert no_excess >= 54
    assert 0.85 < float(np.mean(ratio2)) < 1.15
