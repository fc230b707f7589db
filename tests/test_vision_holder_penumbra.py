"""A holder's own soft shadow: a penumbra that reaches its edge.

A holder on a lit surface casts a shadow around itself; under broad light its edge is a
penumbra several px wide that starts at the holder's edge or even under it (a contact
shadow). Its slope at the edge moves a blurred edge: the camera blurs the floor's level
with the step, so a floor rising by f' DN/px at the edge shifts the crossing by about
f' (s^2 + footprint) / D (D the step, s the blur), and its shoulder bends the floor
inside the window, which tails' slopes do not follow. Before the penumbra was fitted
together with the edge these holders came out 0.05-0.13 px off or were not found at
all."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from alignd.vision.edges import edge_points
from alignd.vision.holder import order_corners, track_holder
from alignd.vision.profile_fit import _JointModel, fit_crossings
from drivers.sim.render import Polygon, Raster, coverage
from drivers.sim.scenes import soft_band_scene

_W, _H = 1280, 720


def _holder_with_shadow(offset: tuple[float, float], shadow_blur: float, seed: int = 0,
                        gradient: tuple[float, float] = (0.0, 0.0)
                        ) -> tuple[np.ndarray, np.ndarray]:
    """A dark 330 x 320 px holder at 22 deg on a 187 DN floor, its shadow (the holder's
    outline shifted by ``offset`` px, blurred ``shadow_blur`` px, 40 % deep) on the
    floor, lit with a ``gradient`` (the light's change across the frame's width and
    height, a fraction of its mean), the frame blurred 0.86 px with 1 DN of noise: the
    8-bit frame and the corners (exact pixel-area coverage)."""
    ras = Raster((_W, _H), 1000.0, (_W / 2, _H / 2), 0.0)
    c = np.array([640.3, 360.7])
    a = math.radians(22.0)
    t, n = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    corners = np.array([c - 165 * t - 160 * n, c + 165 * t - 160 * n,
                        c + 165 * t + 160 * n, c - 165 * t + 160 * n])
    region = (0, 0, _W, _H)
    holder = coverage(Polygon(corners), ras, region).astype(np.float32)
    shadow = coverage(Polygon(corners + np.array(offset)), ras, region).astype(np.float32)
    img = 187.0 * (1.0 - 0.4 * cv2.GaussianBlur(shadow, (0, 0), shadow_blur))
    img = img * (1.0 - holder) + 72.0 * holder
    yy, xx = np.mgrid[0:_H, 0:_W].astype(np.float32)
    img *= 1.0 + gradient[0] * (xx / _W - 0.5) + gradient[1] * (yy / _H - 0.5)
    img = cv2.GaussianBlur(img, (0, 0), 0.86)
    img += np.random.default_rng(seed).normal(0.0, 1.0, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), corners


def _corner_errors(found: np.ndarray, truth: np.ndarray) -> np.ndarray:
    t = order_corners(truth)
    return np.linalg.norm(order_corners(found, t) - t, axis=1)


@pytest.mark.parametrize(("offset", "shadow_blur", "bound"), [
    ((0.0, 0.0), 4.0, 0.03),  # a contact shadow: the penumbra's middle at the edge
    ((0.0, 0.0), 7.0, 0.03),
    ((10.9, -9.1), 4.0, 0.03),  # a lamp's offset: a band with a soft outer edge
    # a small offset: on two sides the penumbra's middle lies 2.7 px under the holder,
    # and the floor beyond the window shows too little of it to be told from a slope
    ((3.0, -3.0), 4.0, 0.07),
])
def test_a_holder_in_its_own_soft_shadow(offset: tuple[float, float], shadow_blur: float,
                                         bound: float) -> None:
    """Found, and every corner within the bound (measured 0.014, 0.014, 0.020 and 0.050
    px; before: 0.085, 0.053, not found, 0.125)."""
    img, corners = _holder_with_shadow(offset, shadow_blur)
    det = track_holder(img, expected_size_px=(330.0, 320.0))
    assert det.ok, det.reason
    assert float(_corner_errors(det.corners_px, corners).max()) < bound


@pytest.mark.parametrize(("offset", "shadow_blur", "bound"), [
    ((0.0, 0.0), 3.0, 0.04), ((0.0, 0.0), 5.0, 0.04),
    ((1.0, -1.0), 5.0, 0.04), ((1.0, -1.0), 3.0, 0.07)])
def test_a_contact_shadow_under_uneven_light(offset: tuple[float, float], shadow_blur: float,
                                             bound: float) -> None:
    """A contact shadow under light 40 % / 30 % stronger at one side of the frame than the
    other. The floor beyond the window shows only the penumbra's outer half, which a
    narrow step near the tails fits as well as the wide one centred at the edge; the
    narrow one barely reaches into the window, and the joint fit with the edge (which
    tells the two apart) was not tried for it: two sides kept the penumbra in their blur
    (1.15 px for 0.86). Measured 0.025, 0.022, 0.022 and 0.050 px; before, 0.17, 0.09,
    0.07 and 0.36 px (and 0.36, 0.08, 0.02, 0.05 with the grid's noise taken about each
    row's level but the joint fit tried from 0.5 DN only)."""
    img, corners = _holder_with_shadow(offset, shadow_blur, gradient=(0.4, 0.3))
    det = track_holder(img, expected_size_px=(330.0, 320.0))
    assert det.ok, det.reason
    assert float(_corner_errors(det.corners_px, corners).max()) < bound


def test_a_narrow_shadow_band_is_not_passed_off_as_blur() -> None:
    """A 2 px penumbra 3-4 px beside two sides reads, in the blur's fit, as a side
    blurred 2.2 px instead of 0.86: its penumbra cannot then be told from the edge. The
    holder must not come out ok on such sides with corners tenths of a px off (it did,
    0.6 px, while the penumbra's fit was trusted without checking it with the edge)."""
    img, corners = _holder_with_shadow((3.0, -3.0), 2.0)
    det = track_holder(img, expected_size_px=(330.0, 320.0))
    assert not det.ok or float(_corner_errors(det.corners_px, corners).max()) < 0.1


def _sloped_floor_offset(slope: float, blur: float, seed: int) -> float:
    """The mean offset (px, along the normal) of the fitted crossings of a straight
    edge at 17 deg, 40 DN over a 60 DN holder, blurred ``blur`` px, whose floor alone
    rises ``slope`` DN/px away from the edge (a penumbra's flank, a lamp's fall-off), with
    1 DN of noise."""
    w, h = 300, 240
    ras = Raster((w, h), 120.0, (w / 2, h / 2), 0.0)
    a = math.radians(17.0)
    u, v = np.array([math.cos(a), math.sin(a)]), np.array([-math.sin(a), math.cos(a)])
    c = np.array([150.3, 119.6])
    poly = np.array([c - 400 * u, c + 400 * u, c + 400 * u + 400 * v, c - 400 * u + 400 * v])
    cov = coverage(Polygon(poly), ras, (0, 0, w, h)).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    d = (xx - c[0]) * v[0] + (yy - c[1]) * v[1]
    img = 60.0 + cov * (40.0 + np.float32(slope) * d)
    img = cv2.GaussianBlur(img, (0, 0), blur)
    img += np.random.default_rng(seed).normal(0.0, 1.0, img.shape).astype(np.float32)
    pts = edge_points(img, c - 100 * u, c + 100 * u, half_width=5, margin_px=0.0)
    fine = fit_crossings(img, [pts])[0]
    return float(((fine.xy - c) @ v).mean())


def test_a_floor_slope_at_the_edge_does_not_move_it() -> None:
    """The blur spreads the floor's slope across the step: a step model of the local
    height alone read the edge moved by about slope (s^2 + 1/12) / D toward the holder
    (0.031 px at 0.3 DN/px, a 2 px blur and 40 DN; measured 0.023 over 4 noise
    realisations). The fit models that spread: measured 0.009."""
    off = [_sloped_floor_offset(0.3, 2.0, seed) for seed in range(4)]
    assert abs(float(np.mean(off))) < 0.015


@pytest.mark.parametrize(("angle_deg", "seed"), [(20.0, 1), (-15.0, 3)])
def test_a_penumbra_across_the_sides_in_a_defocused_frame(angle_deg: float,
                                                          seed: int) -> None:
    """The holder's shadow right under it, blurred 3 px, in a frame blurred 1.6 px (the
    bench's "penumbra across the sides"): each side's penumbra is centred on it. The
    joint fit's width sat at its bound (1.5 times the columns' blur, which the penumbra
    widens) and crawled along it until out of evaluations, and those sides read 0.28 px
    out; it is now fitted once more with the bound written into the width. Within 0.15
    px (measured 0.11 and 0.10; before 0.28 and 0.29)."""
    img, corners = soft_band_scene(0.0, 3.0, angle_deg, seed=seed, blur_px=1.6)
    det = track_holder(img, expected_size_px=(260.0, 160.0))
    assert det.ok, det.reason
    assert float(_corner_errors(det.corners_px, corners).max()) < 0.15


@pytest.mark.parametrize("side", [0, 1])
@pytest.mark.parametrize("width", [3.0, 1.0])
def test_the_joint_fits_jacobian_is_its_residuals_derivative(side: int, width: float) -> None:
    """The joint fit of an edge and a penumbra (``profile_fit._JointModel``) is given its
    Jacobian, the linear levels projected out exactly (Golub and Pereyra), where a
    finite-difference one cost four more evaluations of the residuals an iteration.
    Against central differences of the residuals: within 1e-5 of each column's largest
    entry, with the penumbra's width inside its range (3 px) and below its bound (1 px,
    held there by the penalty: the model's part of that column is zero)."""
    sgn = 1.0 if side else -1.0
    db = sgn * np.arange(-5.0, 20.0, 0.25)
    rng = np.random.default_rng(11)
    w = np.sqrt(rng.integers(2, 9, db.size).astype(float))
    level = 60.0 + 140.0 * (sgn * db > 0) - 50.0 * (sgn * db > 6.0) + rng.normal(0, 2, db.size)
    model = _JointModel(db, w[:, None], level * w, side, 0.9, 0.15, 1.8)
    q = np.array([0.2, 1.1, 5.0, width])
    J = model.jac(q)
    num = np.empty_like(J)
    for k in range(4):
        h = 1e-6 * max(abs(float(q[k])), 1.0)
        up, dn = q.copy(), q.copy()
        up[k] += h
        dn[k] -= h
        num[:, k] = (model.resid(up) - model.resid(dn)) / (2 * h)
    scale = np.abs(num).max(axis=0)
    assert np.all(np.abs(J - num).max(axis=0) <= 1e-5 * scale)
    assert (J[:-4, 3] == 0.0).all() == (width < 1.8)
