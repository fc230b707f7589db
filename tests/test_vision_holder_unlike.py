"""Holders that only look like the configured one, found on the corpus drawn at 640 x 480
px (`bench/vision.py --size 640x480`): before these checks such frames were returned ok
and 1.4-73 px wrong.

- A sharp holder with a cast shadow a few px beside two sides: the profile fit merged the
  band into the side's step (2 px wide there, 0.2 px on the opposite side) and moved it
  outward by 1-2 px. Opposite sides of one flat face are blurred alike, so such a
  detection is refused with the reason.
- A nearly square holder with a plate along one side: holder + plate is as close to the
  configured size as the holder itself, with the long side the plate's way. The shadow
  check's inner step (the plate's edge with the holder) now wins by the size's fit either
  way round."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from alignd.vision import holder
from alignd.vision.holder import order_corners, track_holder
from drivers.sim.render import Polygon, Raster, coverage
from drivers.sim.scenes import rectangle

_W, _H = 640, 480
_RAS = Raster((_W, _H), 1000.0, (_W / 2, _H / 2), 0.0)
_BOX = (0, 0, _W, _H)


def _noisy(img: np.ndarray, blur: float, seed: int) -> np.ndarray:
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur)
    rng = np.random.default_rng(seed)
    return np.clip(np.rint(img + rng.normal(0, 2.0, img.shape)), 0, 255).astype(np.uint8)


def _err(found: np.ndarray, truth: np.ndarray) -> float:
    t = order_corners(truth)
    return float(np.max(np.linalg.norm(order_corners(found, t) - t, axis=1)))


_HOLDER = rectangle((300.3, 240.6), 124.0, 112.0, 4.0)


def _shadowed(floor: float, seed: int = 0) -> np.ndarray:
    """A dark holder (20 DN, sharp: blur 0.35 px) on a floor, its shadow (0.6 of the floor)
    offset by (-3, -1) px: a 3 px band beside one side, 1 px beside the next. The areas
    are exact: the band is the shadow's outline less the holder's."""
    sh = _HOLDER + np.array([-3.0, -1.0])
    _, inter = cv2.intersectConvexConvex(sh.astype(np.float32), _HOLDER.astype(np.float32))
    c_h = coverage(Polygon(_HOLDER), _RAS, _BOX)
    c_union = (coverage(Polygon(sh), _RAS, _BOX) + c_h
               - coverage(Polygon(inter[:, 0].astype(float)), _RAS, _BOX))
    img = floor + (0.6 * floor - floor) * (c_union - c_h) + (20.0 - floor) * c_h
    return _noisy(img, 0.35, seed)


@pytest.mark.parametrize("floor", [80.0, 150.0])
def test_a_shadow_band_merged_into_a_side_is_refused(floor: float) -> None:
    det = track_holder(_shadowed(floor), expected_size_px=(124.0, 112.0))
    if det.ok:  # found otherwise, it must be right
        assert _err(det.corners_px, _HOLDER) < 1.0
    else:
        assert "blurs both alike" in det.reason


def test_without_the_blur_check_the_shadowed_side_was_taken(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(holder, "_unlike_opposite_blurs", lambda blur: "")
    det = track_holder(_shadowed(150.0), expected_size_px=(124.0, 112.0))
    assert det.ok and _err(det.corners_px, _HOLDER) > 1.0


def test_opposite_blurs_rule() -> None:
    assert holder._unlike_opposite_blurs((0.6, 0.7, 0.9, 0.5)) == ""
    assert holder._unlike_opposite_blurs((1.9, 1.6, 1.5, 2.0)) == ""  # defocus: all soft
    assert holder._unlike_opposite_blurs(()) == ""
    assert "sides 1 and 3" in holder._unlike_opposite_blurs((0.5, 0.31, 0.4, 1.93))
    assert "sides 0 and 2" in holder._unlike_opposite_blurs((2.54, 0.23, 0.15, 2.11))


def _plated(seed: int = 0) -> np.ndarray:
    """A dark 124 x 112 px holder (20 DN) with a 17 px plate (60 DN) along its top side, on
    a bright disc (150 DN): holder + plate is 124 x 129 px."""
    t = np.radians(4.0)
    out = np.array([np.sin(t), -np.cos(t)])
    union = np.array([_HOLDER[0] + 17 * out, _HOLDER[1] + 17 * out, _HOLDER[2], _HOLDER[3]])
    img = (150.0 + (60.0 - 150.0) * coverage(Polygon(union), _RAS, _BOX)
           + (20.0 - 60.0) * coverage(Polygon(_HOLDER), _RAS, _BOX))
    return _noisy(img, 0.6, seed)


@pytest.mark.parametrize("hinted", [False, True])
def test_a_square_holder_is_found_without_its_plate(hinted: bool) -> None:
    img = _plated()
    det = track_holder(img, expected_size_px=(124.0, 112.0),
                       hint=_HOLDER + np.array([1.5, -1.0]) if hinted else None)
    assert det.ok, det.reason
    assert _err(det.corners_px, _HOLDER) < 0.05


def test_size_misfit_matches_long_side_to_long_side() -> None:
    # holder + plate: 129 to the long 124 (+4 %), 124 to the short 112 (+10.7 %)
    assert holder._size_misfit((124.0, 129.0), (124.0, 112.0)) == pytest.approx(124 / 112 - 1)
    assert holder._size_misfit((124.0, 112.0), (112.0, 124.0)) == pytest.approx(0.0)
    assert (holder._size_misfit((124.0, 112.0), (124.0, 112.0))
            < holder._size_misfit((124.0, 129.0), (124.0, 112.0)))
