"""A cast shadow wider than the coarse side search (corpus scene #695 of seed 2024): a dark
holder on a bright disc, its shadow a 16 px band beyond one short side. The rectangle
holder + band is straight, of the right polarity and 10 % too long, inside the size
tolerance: it passed every check and was returned ok, 16 px wrong at two corners. A true
side has the holder's own level just inside it; the band's outer edge has the band's."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from alignd.vision import holder
from alignd.vision.holder import order_corners, track_holder
from alignd.vision.holder_steps import inner_step
from drivers.sim.render import Polygon, Raster, coverage

_L, _S, _ANGLE, _BAND = 168.0, 76.0, -80.0, 16.0
_HOLDER, _SHADOW, _DISC = 88.0, 130.0, 200.0


def _rect(ctr: np.ndarray, u: np.ndarray, v: np.ndarray, lo: float, hi: float,
          half_s: float) -> np.ndarray:
    """Corners of the rectangle from lo to hi along u, +-half_s along v."""
    return np.array([ctr + lo * u - half_s * v, ctr + hi * u - half_s * v,
                     ctr + hi * u + half_s * v, ctr + lo * u + half_s * v])


def _scene(label: bool = False, across: bool = False
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, holder corners, holder + band corners): blur 0.7 px, noise 2 DN; the band's
    outer edge is a penumbra (3 px). ``label``: instead of the band, a darker strip inside
    the holder 12-22 px from that side over half its length (no shadow). ``across``:
    instead, a shadow's soft edge (3 px) crosses the holder and the disc parallel to that
    side, 16 px inside it, the side's end in the shadow, and the holder is the light one
    (corpus scene #947 of the bench's --seed 4900: the levels step twice the same way, as
    at a band)."""
    w, h = 400, 320
    t = math.radians(_ANGLE)
    u, v = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
    ctr = np.array([201.3, 158.7])
    c = _rect(ctr, u, v, -_L / 2, _L / 2, _S / 2)
    wide = _rect(ctr, u, v, -_L / 2, _L / 2 + _BAND, _S / 2)
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    region = (0, 0, w, h)
    disc, hold = (_HOLDER, _DISC) if across else (_DISC, _HOLDER)
    img = np.full((h, w), disc, np.float32)
    if not (label or across):
        shadow = coverage(Polygon(wide), ras, region).astype(np.float32)
        img += (_SHADOW - img) * cv2.GaussianBlur(shadow, (0, 0), 3.0)
    img += (hold - img) * coverage(Polygon(c), ras, region)
    if across:
        beyond = _rect(ctr, u, v, _L / 2 - _BAND, 1000.0, 1000.0)
        shade = cv2.GaussianBlur(coverage(Polygon(beyond), ras, region).astype(np.float32),
                                 (0, 0), 3.0)
        img *= 1.0 - 0.35 * shade
    if label:
        strip = _rect(ctr, u, v, _L / 2 - 22.0, _L / 2 - 12.0, _S / 4)
        img += (40.0 - img) * coverage(Polygon(strip), ras, region)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    img += np.random.default_rng(5).normal(0.0, 2.0, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), c, wide


def _corner_error(found: np.ndarray, truth: np.ndarray) -> float:
    t = order_corners(truth)
    return float(np.linalg.norm(order_corners(found, t) - t, axis=1).max())


def test_the_band_edge_is_flagged_at_the_band_width() -> None:
    img, c, wide = _scene()
    step = inner_step(img, order_corners(wide))
    assert step is not None
    # the side across the band's end (corners 1-2 of the unordered rectangle)
    ordered = order_corners(wide)
    a, b = ordered[step.side], ordered[(step.side + 1) % 4]
    assert {tuple(np.round(a, 6)), tuple(np.round(b, 6))} == {tuple(np.round(wide[1], 6)),
                                                              tuple(np.round(wide[2], 6))}
    assert step.depth_px == pytest.approx(_BAND, abs=2.0)
    assert step.ratio > 0.6
    assert inner_step(img, order_corners(c)) is None  # the holder itself is not flagged


@pytest.mark.parametrize("hinted", [False, True])
def test_the_holder_is_found_not_the_holder_and_its_shadow(hinted: bool) -> None:
    img, c, wide = _scene()
    det = track_holder(img, expected_size_px=(_L, _S), hint=wide if hinted else None)
    assert det.ok, det.reason
    assert _corner_error(det.corners_px, c) < 0.3


def test_without_the_check_the_band_was_taken(monkeypatch: pytest.MonkeyPatch) -> None:
    """The scene does reproduce the fault: with the check off, the tracker seeded at the
    band's edge keeps it (this test guards the other two against a scene that is too easy)."""
    monkeypatch.setattr(holder, "inner_step", lambda *_a: None)
    img, c, wide = _scene()
    det = track_holder(img, expected_size_px=(_L, _S), hint=wide)
    assert det.ok and _corner_error(det.corners_px, c) > 10.0


def test_a_shadow_edge_across_the_holder_keeps_the_side() -> None:
    """The levels alone flag the side (a step the same way 16 px in); the expected size
    says the side is right, and the holder is returned as measured."""
    img, c, _wide = _scene(across=True)
    assert inner_step(img, order_corners(c)) is not None
    det = track_holder(img, expected_size_px=(_L, _S))
    assert det.ok, det.reason
    assert _corner_error(det.corners_px, c) < 0.3


def test_a_dark_label_near_a_side_is_not_a_shadow() -> None:
    img, c, _wide = _scene(label=True)
    assert inner_step(img, order_corners(c)) is None
    det = track_holder(img, expected_size_px=(_L, _S))
    assert det.ok, det.reason
    assert _corner_error(det.corners_px, c) < 0.3


@pytest.mark.parametrize("angle_deg", [-12.0, 7.0, 31.0])
def test_a_strip_darker_than_the_holder_along_a_side_is_not_taken_into_it(
        angle_deg: float) -> None:
    """A thin sample darker than a dark holder (20 against 60 DN, on a 190 DN disc),
    standing flush along its long side, seen from above as an 8 px strip: holder and strip
    make one dark rectangle 4 % too wide, inside the size tolerance, and it was returned
    ok, 8 px wrong. The band just inside that side steps away from the outside's level,
    not toward it, and is flagged all the same; the size puts the side at the inner step,
    where the holder's edge is lighter than the strip (the other polarity). That was
    refused; beyond the strip the image steps back to the disc's level, which makes the
    holder and its strip one outline, and the holder is measured with that side at the
    inner step (tests/test_vision_holder_between.py)."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    t = math.radians(angle_deg)
    u, v = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
    ctr = np.array([640.4, 360.1])
    held = _rect(ctr, u, v, -151.6, 151.6, 96.5)
    strip = _rect(ctr - 100.5 * v, u, v, -151.6, 151.6, 4.0)
    box = (0, 0, w, h)
    ch, cs = coverage(Polygon(held), ras, box), coverage(Polygon(strip), ras, box)
    img = 190.0 * np.clip(1.0 - ch - cs, 0.0, 1.0) + 60.0 * ch + 20.0 * cs
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7)
    img += np.random.default_rng(1).normal(0.0, 1.0, img.shape).astype(np.float32)
    det = track_holder(np.clip(np.rint(img), 0, 255).astype(np.uint8),
                       expected_size_px=(303.2, 193.0))
    assert det.ok, det.reason
    assert _corner_error(det.corners_px, held) < 0.3
