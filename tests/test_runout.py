"""The turntable error-motion map: fitted from a wide sweep, recovers the simulated bearing."""

from __future__ import annotations

import numpy as np
import pytest

from alignd.errors import SolveError
from alignd.procedures.runout import RunoutMap, fit_runout
from drivers.config import SimWorldConfig
from drivers.sim.world import World, rot2

PIXEL_MM = 0.160


def _world(wobble_um: float, seed: int = 3) -> World:
    return World(SimWorldConfig(wobble_um=wobble_um), {}, np.random.default_rng(seed))


def _sweep(world: World, angles: np.ndarray, noise_px: float, sign: int = 1,
           seed: int = 0) -> np.ndarray:
    """Image positions (px) of a point 12 mm off the axis, as the top camera sees it."""
    rng = np.random.default_rng(seed)
    arm = np.array([9.0, -8.0])
    axis_px = np.array([652.3, 347.8])
    pts = [axis_px + (rot2(sign * a) @ arm + world.wobble_mm(a)) / PIXEL_MM for a in angles]
    return np.asarray(pts) + rng.normal(0, noise_px, (len(angles), 2))


def test_full_turn_recovers_the_simulated_error_motion() -> None:
    world = _world(wobble_um=8.0)
    angles = np.arange(-180.0, 180.0, 5.0)
    # 0.002 px of noise at 160 um/px is 0.32 um per coordinate; each map value carries
    # about sqrt(8 / 72) of that (8 coefficients per coordinate over 72 angles): 0.1 um
    m = fit_runout(angles, _sweep(world, angles, noise_px=0.002), PIXEL_MM)
    truth = np.array([world.wobble_mm(a) for a in angles])
    err_um = np.abs(m.offset_mm - truth).max() * 1000
    assert err_um < 0.5, err_um
    assert m.amplitude_um == pytest.approx(np.hypot(*truth.T).max() * 1000, abs=0.5)
    assert 0.25 < m.residual_um < 0.4
    # between the measured angles and across the wrap the map follows the bearing
    for q in (2.5, 177.5, 181.0, -182.0, 400.0):
        assert np.abs(m.at(q) - world.wobble_mm(q)).max() * 1000 < 1.0, q


def test_turning_sense_is_a_parameter() -> None:
    world = _world(wobble_um=5.0, seed=8)
    angles = np.linspace(-180.0, 175.0, 72)
    pts = _sweep(world, angles, noise_px=0.002, sign=-1)
    good = fit_runout(angles, pts, PIXEL_MM, sign=-1)
    wrong = fit_runout(angles, pts, PIXEL_MM, sign=1)
    truth = np.array([world.wobble_mm(a) for a in angles])
    assert np.abs(good.offset_mm - truth).max() * 1000 < 0.5
    # the wrong sense leaves the whole arm unexplained: mm, not um
    assert wrong.residual_um > 1000 * good.residual_um


def test_no_error_motion_gives_a_flat_map() -> None:
    world = _world(wobble_um=0.0)
    angles = np.arange(-180.0, 180.0, 5.0)
    m = fit_runout(angles, _sweep(world, angles, noise_px=0.01, seed=4), PIXEL_MM)
    # noise alone (1.6 um per coordinate): no harmonic passes the significance test, so
    # the map is flat instead of carrying ~0.5 um of noise per value into later sweeps
    assert m.amplitude_um < 1e-9
    assert m.residual_um == pytest.approx(1.6, rel=0.2)


def test_partial_sweep_map_is_what_a_rigid_fit_leaves() -> None:
    world = _world(wobble_um=8.0, seed=5)
    angles = np.linspace(-60.0, 60.0, 41)
    pts = _sweep(world, angles, noise_px=0.0)
    m = fit_runout(angles, pts, PIXEL_MM)
    # the truth with the rigid part of the same range projected out
    from alignd.procedures.runout import _rigid_columns

    w = np.array([world.wobble_mm(a) for a in angles]).reshape(-1)
    R = _rigid_columns(np.radians(angles), 1)
    w = (w - R @ np.linalg.lstsq(R, w, rcond=None)[0]).reshape(-1, 2)
    assert np.abs(m.offset_mm - w).max() * 1000 < 0.3
    assert not m.full_turn
    np.testing.assert_allclose(m.at(100.0), m.offset_mm[-1])  # clamped outside the range


def test_correcting_a_sweep_removes_the_bias_of_the_centre() -> None:
    """What the map is for: a narrow sweep's centre fit, before and after the correction."""
    world = _world(wobble_um=10.0, seed=11)
    wide = np.arange(-180.0, 180.0, 5.0)
    m = fit_runout(wide, _sweep(world, wide, noise_px=0.0), PIXEL_MM)
    narrow = np.linspace(-10.0, 10.0, 21)
    pts = _sweep(world, narrow, noise_px=0.0)
    from alignd.procedures.runout import _rigid_columns

    R = _rigid_columns(np.radians(narrow), 1)

    def centre_err_um(p: np.ndarray) -> float:
        c = np.linalg.lstsq(R, (p * PIXEL_MM).reshape(-1), rcond=None)[0][:2]
        return float(np.hypot(*(c - np.array([652.3, 347.8]) * PIXEL_MM)) * 1000)

    before = centre_err_um(pts)
    after = centre_err_um(m.correct_px(narrow, pts, PIXEL_MM))
    assert before > 20.0  # a 10 um bearing moves a +-10 deg centre by tens of um
    assert after < 0.05 * before, (before, after)


def test_json_round_trip_and_malformed_records() -> None:
    world = _world(wobble_um=4.0)
    angles = np.arange(-180.0, 180.0, 15.0)
    m = fit_runout(angles, _sweep(world, angles, noise_px=0.01), PIXEL_MM)
    back = RunoutMap.from_json(m.to_json())
    np.testing.assert_allclose(back.offset_mm, m.offset_mm, atol=1e-12)
    np.testing.assert_allclose(back.angles_deg, m.angles_deg)
    assert back.residual_um == m.residual_um
    with pytest.raises(ValueError, match="malformed runout map"):
        RunoutMap.from_json({"angles_deg": [1, 2]})
    with pytest.raises(ValueError, match="strictly increasing"):
        RunoutMap(np.array([0.0, 0.0]), np.zeros((2, 2)), 0.0)


def test_too_narrow_or_too_few_frames_is_refused() -> None:
    world = _world(wobble_um=4.0)
    narrow = np.linspace(-10.0, 10.0, 21)
    with pytest.raises(SolveError, match="wide sweep"):
        fit_runout(narrow, _sweep(world, narrow, 0.01), PIXEL_MM)
    few = np.linspace(-90.0, 90.0, 5)
    with pytest.raises(SolveError, match="at least 8"):
        fit_runout(few, _sweep(world, few, 0.01), PIXEL_MM)
    angles = np.arange(-180.0, 180.0, 15.0)
    pts = _sweep(world, angles, 0.01)
    pts[::2] = np.nan  # missed detections are skipped, not fitted
    assert len(fit_runout(angles, pts, PIXEL_MM).angles_deg) == len(angles) // 2
