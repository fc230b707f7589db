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
  way round.
- A holder with a sample strip along one long side and a label inside: the label's edge,
  the strip's outer edge and the short sides frame a rectangle of the holder's size. The
  label's edge stops short of both corners, which no side of the holder does."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from alignd.vision import holder
from alignd.vision.holder import order_corners, track_holder
from alignd.vision.holder_bands import side_bands
from drivers.sim.render import Polygon, Raster, coverage
from drivers.sim.scenes import hard_shadow_scene, random_top_scene, rectangle

_W, _H = 640, 480
_RAS = Raster((_W, _H), 1000.0, (_W / 2, _H / 2), 0.0)
_BOX = (0, 0, _W, _H)
_BIG = rectangle((330.4, 236.2), 215.0, 159.0, 40.0)  # a large light holder


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
    # (and without the refit of unalike opposite sides alike, which the refusal's
    # absence would let run here: the shadowed side is then refused as rough)
    monkeypatch.setattr(holder, "_alike_opposite_blurs", lambda widths: None)
    # the two-step check moves the side beside the 3 px band in to the holder's edge (the
    # 1 px band beside the next side stays merged: 0.36 px) ...
    det = track_holder(_shadowed(150.0), expected_size_px=(124.0, 112.0))
    assert det.ok and _err(det.corners_px, _HOLDER) < 0.5
    # ... without it (and without the second look beside the sides, which now finds the
    # band's outer edge beyond the side too), the shadowed side was taken
    monkeypatch.setattr(holder, "side_bands", lambda *_a, **_k: [])
    monkeypatch.setattr(holder, "neighbour_steps", lambda *_a, **_k: [])
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


def _label_and_strip(angle_deg: float, shift_px: float, seed: int = 0
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A dark 162 x 71 px holder (85 DN) on a bright disc (148 DN) with a sample strip
    (108 DN) ``shift_px`` wide along one long side and a dark label (40 DN, 58 % of the
    holder's length) inside, ``shift_px`` from the other (corpus #937 of seed 5000 at 640
    x 480, JPEG q 72: returned 23.6 px wrong). The frame, the holder's corners and those of
    the rectangle the label's and the strip's edges frame."""
    c, long_, short = np.array([300.3, 240.6]), 162.0, 71.0
    t = math.radians(angle_deg)
    across = np.array([-math.sin(t), math.cos(t)])
    held = rectangle(c, long_, short, angle_deg)
    img = np.full((_H, _W), 148.0)
    # back to front, each over the last: the strip's rectangle runs under the holder, so
    # their shared edge is exact
    for r, level in ((rectangle(c + across * shift_px / 2, long_, short + shift_px,
                                angle_deg), 108.0),
                     (held, 85.0),
                     (rectangle(c - across * (short / 2 - shift_px - 12.0), 0.58 * long_,
                                24.0, angle_deg), 40.0)):
        img += (level - img) * coverage(Polygon(r), _RAS, _BOX)
    return (_noisy(img, 1.2, seed), held,
            rectangle(c + across * shift_px, long_, short, angle_deg))


@pytest.mark.parametrize("angle_deg", [90.0, 131.0])
def test_a_label_edge_does_not_stand_in_for_a_side(angle_deg: float) -> None:
    """Found by search and by tracking from the framed rectangle: the holder itself."""
    img, held, framed = _label_and_strip(angle_deg, 24.0)
    for hint in (None, framed):
        det = track_holder(img, expected_size_px=(162.0, 71.0), hint=hint)
        assert det.ok, det.reason
        assert _err(det.corners_px, held) < 0.3


def test_a_side_bare_at_both_ends_is_refused_with_the_reason() -> None:
    img, held, framed = _label_and_strip(90.0, 24.0)
    corners, sides = holder._locate(img, order_corners(framed), 15.0, 1, None)
    det = holder._finish(img, corners, sides, None, (162.0, 71.0), None, 15.0, 0.6, None,
                         0.12, True)
    assert not det.ok
    assert "short of both corners" in det.reason and "label" in det.reason
    corners, sides = holder._locate(img, order_corners(held), 15.0, 1, None)
    assert holder._finish(img, corners, sides, None, (162.0, 71.0), None, 15.0, 0.6, None,
                          0.12, True).ok


def _holes_by_the_corners(seed: int = 0) -> np.ndarray:
    """A light 215 x 159 px holder (235 DN) on a grey floor (200 DN) with dark floor holes
    (60 DN, 22 px) partly under one side by both its corners: corpus #638 of seed 5000, a
    right holder whose side's crossings stop 56 px short of both corners (the holes'
    edges in the windows)."""
    img = np.full((_H, _W), 200.0)
    img += (235.0 - img) * coverage(Polygon(_BIG), _RAS, _BOX)
    a, b = _BIG[0], _BIG[1]
    out = np.array([b[1] - a[1], a[0] - b[0]]) / np.linalg.norm(b - a)
    if out @ (a - _BIG.mean(axis=0)) < 0:
        out = -out
    holes = np.zeros((_H, _W), np.uint8)
    for t in (0.07, 0.93):
        x, y = a + t * (b - a) - 3.0 * out  # under the holder: a crescent beside it
        cv2.circle(holes, (round(4 * x), round(4 * y)), 44, 255, -1, cv2.LINE_AA, shift=2)
    img += (60.0 - img) * (holes / 255.0)
    img[coverage(Polygon(_BIG), _RAS, _BOX) > 0.999] = 235.0
    return _noisy(img, 0.6, seed)


def test_a_side_whose_ends_are_cluttered_is_kept() -> None:
    """Crossings missing at both ends where the image still steps there: the holder."""
    img = _holes_by_the_corners()
    det = track_holder(img, expected_size_px=(215.0, 159.0))
    assert det.ok, det.reason
    assert _err(det.corners_px, _BIG) < 0.1


_WIDE_W, _WIDE_H = 1280, 720
_WIDE_RAS = Raster((_WIDE_W, _WIDE_H), 1000.0, (_WIDE_W / 2, _WIDE_H / 2), 0.0)


def _hard_shadow(offset_px: float, angle_deg: float, seed: int = 0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A sharp dark holder with its hard cast shadow a few px beside two sides
    (:func:`drivers.sim.scenes.hard_shadow_scene`): the frame and the holder's corners."""
    return hard_shadow_scene(offset_px, angle_deg, seed)


@pytest.mark.parametrize("angle_deg", [-16.8, 20.0])
def test_a_hard_shadow_band_beside_a_side_is_not_taken_for_it(angle_deg: float) -> None:
    """A 5 px band: the side's windows hold both steps, its crossings scatter, the edge
    profiles disagree, and the area method's corners (6 px off) are not returned."""
    img, held = _hard_shadow(5.0, angle_deg)
    det = track_holder(img, expected_size_px=(303.2, 193.0))
    if det.ok:
        assert _err(det.corners_px, held) < 0.3
    else:
        assert "scatters" in det.reason


def test_rough_side_rule() -> None:
    assert holder._rough_side((0.061, 0.436, 0.104, 0.048)).startswith(
        "the edge profiles do not fit and side 1's edge scatters 5.3 times")
    assert holder._rough_side((0.03, 0.13, 0.04, 0.08)) == ""  # a right holder: 2.2 times
    assert holder._rough_side((0.1, float("nan"), 0.1, 0.1)) == ""


def _dark_strip(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A dark 280 x 175 px holder (30 DN) on a bright disc (200 DN) with a sample strip
    13.5 px wide along one long side (62 DN): holder -> strip -> disc steps twice the same
    way, the strip's level near the holder's (0.23 of the strip's step to the disc;
    corpus #996 of seed 7100 at 640 x 480, 0.22: holder + strip, 280 x 189 px, inside
    the size tolerance, was returned 13.5 px off)."""
    held = rectangle((286.0, 260.3), 279.8, 175.2, -67.9)
    t = np.radians(-67.9)
    out = np.array([-np.sin(t), np.cos(t)])  # across the holder
    union = rectangle(np.array([286.0, 260.3]) + out * 13.5 / 2, 279.8, 175.2 + 13.5, -67.9)
    img = (200.0 + (62.0 - 200.0) * coverage(Polygon(union), _RAS, _BOX)
           + (30.0 - 62.0) * coverage(Polygon(held), _RAS, _BOX))
    return _noisy(img, 1.0, seed), held


def test_a_dark_strip_beside_a_dark_holder_is_left_out() -> None:
    img, held = _dark_strip()
    det = track_holder(img, expected_size_px=(279.8, 175.2))
    assert det.ok, det.reason
    assert _err(det.corners_px, held) < 0.1


def test_a_sharp_holders_hard_shadow_band_6px() -> None:
    """A 6 px band: its outer edge is clean and the windows hold it alone, so only the
    levels tell it; they are read 2-3.5 px inside a sharp side (4-7 px is past it)."""
    for angle_deg in (-16.8, 20.0):
        img, held = _hard_shadow(6.0, angle_deg)
        det = track_holder(img, expected_size_px=(303.2, 193.0))
        assert not det.ok or _err(det.corners_px, held) < 0.3


@pytest.mark.parametrize("offset_px", [1.5, 2.0, 3.0, 4.0])
def test_a_hard_shadow_band_is_never_taken_into_a_side(offset_px: float) -> None:
    """Bands 1.5-4 px beside one or two sides, four holder angles: the area method and the
    profile fit put such a side between the band's two steps (1.1-2.7 px off before the
    two-step check, 25 of 40 frames over 1 px). Now a side found between two steps is
    moved in to the inner one: every holder returned is within 1 px (the sub-pixel band
    the shadow's -0.73 px makes beside the third side, unresolved, moves it by 0.5 px)."""
    right = 0
    for angle_deg in (-16.8, 20.0, 3.0, 45.0):
        img, held = _hard_shadow(offset_px, angle_deg)
        det = track_holder(img, expected_size_px=(303.2, 193.0))
        if det.ok:
            err = _err(det.corners_px, held)
            assert err < 1.0, (angle_deg, err)
            right += err < 0.3
    assert right >= {1.5: 2, 2.0: 3, 3.0: 1, 4.0: 1}[offset_px]


@pytest.mark.parametrize("offset_px", [2.0, 3.0])
def test_a_band_nearly_as_dark_as_the_holder_is_not_taken_into_a_side(offset_px: float
                                                                       ) -> None:
    """A hard shadow at 60 DN beside a 30 DN holder on a 200 DN disc: band and holder
    merge and the side is found on the band's outer step (before, 5 of these 6 frames
    were returned 1.35-3.18 px off, one refused). Found there, with the inner step
    resolved and at most 4.5 px in, the side is moved in to it: every holder returned
    is within 1 px, most within 0.3 px."""
    right = 0
    for angle_deg in (-16.8, 20.0, 45.0):
        img, held = hard_shadow_scene(offset_px, angle_deg, 0, (200.0, 60.0, 30.0))
        det = track_holder(img, expected_size_px=(303.2, 193.0))
        if det.ok:
            err = _err(det.corners_px, held)
            assert err < 1.0, (angle_deg, err)
            right += err < 0.3
    assert right >= 2


@pytest.mark.parametrize("angle_deg", [0.0, 90.0])
def test_a_band_beside_a_side_along_the_pixel_rows(angle_deg: float) -> None:
    """A holder square to the pixel grid samples its sides' profiles once a pixel: a
    band there is still read, as it misfits one step by several % of the step (before,
    5 of these 8 frames were 1.46-3.08 px off and 2 refused; now 7 are within 0.61 px),
    while a clean edge whose blur is not quite Gaussian is not taken for two steps
    (tests/test_vision_holder.py at 0 deg)."""
    banded = 0
    for offset_px in (2.0, 3.0):
        for levels in ((210.0, 128.0, 85.0), (200.0, 60.0, 30.0)):
            img, held = hard_shadow_scene(offset_px, angle_deg, 1, levels)
            det = track_holder(img, expected_size_px=(303.2, 193.0))
            if det.ok:
                assert _err(det.corners_px, held) < 0.7, (offset_px, levels)
                banded += det.banded_sides >= 1
    assert banded >= 3


@pytest.mark.parametrize("angle_deg", [0.0, 90.0])
def test_a_narrow_dark_band_along_the_pixel_rows(angle_deg: float) -> None:
    """A 1.5 px band at 60 DN beside a 30 DN holder square to the pixel grid: sampled once
    a pixel, its smaller step reads 11 % of both (under the 15 % a band needs otherwise),
    but two steps fit the side 4600 times better than one (a clean edge's non-Gaussian
    blur, read as two steps on such a side, 8 % at 57 times): the side is moved in. Before,
    both seeds were returned 1.37 px off."""
    for seed in (0, 1):
        img, held = hard_shadow_scene(1.5, angle_deg, seed, (200.0, 60.0, 30.0))
        det = track_holder(img, expected_size_px=(303.2, 193.0))
        assert det.ok and det.banded_sides == 1
        assert _err(det.corners_px, held) < 0.8, seed


def test_side_bands_reads_the_inner_step() -> None:
    """A side found 1 px outside a holder's edge, with a 2 px band beyond the edge: the
    band is reported on that side alone, its inner step 1 px inside (to 0.05 px)."""
    img, held = _hard_shadow(2.0, 3.0)
    t = order_corners(held)
    found = t.copy()
    c = t.mean(axis=0)
    # move the side the band lies beside (the one facing +x) 1 px out
    k = int(np.argmax([(t[i] + t[(i + 1) % 4] - 2 * c)[0] for i in range(4)]))
    n = np.array([t[(k + 1) % 4, 1] - t[k, 1], t[k, 0] - t[(k + 1) % 4, 0]])
    n /= np.linalg.norm(n)
    n *= np.sign(n @ (t[k] - c))
    found[[k, (k + 1) % 4]] += n
    bands = side_bands(img, found)
    assert [b.side for b in bands] == [k]
    assert bands[0].inner_px == pytest.approx(-1.0, abs=0.05)
    assert bands[0].outer_px == pytest.approx(1.0, abs=0.1)
    assert side_bands(img, t) == []  # the holder's own sides: nothing to move


def test_a_band_on_opposite_sides_is_left_alone() -> None:
    """Two opposite sides each 1 px outside a 2 px band: a band on both sides of one face
    is not one shadow (a chamfer, a frame round the face, a plate inside it): nothing is
    reported, wherever the found sides lie (before, with one of them on the inner step,
    the other was reported and moved in: a dark plate 4 px inside a dark holder's long
    sides cut it 4.45 px short)."""
    held = rectangle((492.4, 221.1), 303.2, 193.0, 3.0)
    wider = rectangle((492.4, 221.1), 303.2 + 4.0, 193.0, 3.0)
    img = (210.0 + (128.0 - 210.0) * coverage(Polygon(wider), _WIDE_RAS, (0, 0, _WIDE_W, _WIDE_H))
           + (85.0 - 128.0) * coverage(Polygon(held), _WIDE_RAS, (0, 0, _WIDE_W, _WIDE_H)))
    img = _noisy(img, 0.49, 0)
    found = rectangle((492.4, 221.1), 303.2 + 2.0, 193.0, 3.0)
    assert side_bands(img, found) == []
    axis = np.array([np.cos(np.radians(3.0)), np.sin(np.radians(3.0))])
    one = rectangle(np.array([492.4, 221.1]) + 0.5 * axis, 303.2 + 1.0, 193.0, 3.0)
    assert side_bands(img, one) == []
    # a band along one of them only is reported, the side 1 px out moved in to it
    wider = rectangle(np.array([492.4, 221.1]) + 1.0 * axis, 303.2 + 2.0, 193.0, 3.0)
    img = (210.0 + (128.0 - 210.0) * coverage(Polygon(wider), _WIDE_RAS, (0, 0, _WIDE_W, _WIDE_H))
           + (85.0 - 128.0) * coverage(Polygon(held), _WIDE_RAS, (0, 0, _WIDE_W, _WIDE_H)))
    bands = side_bands(_noisy(img, 0.49, 0), one)
    assert len(bands) == 1
    assert bands[0].inner_px == pytest.approx(-1.0, abs=0.05)


def test_a_banded_holder_is_tracked_off_its_band(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tracking from a detection moved off a band finds the band again (the seed's sides
    lie on the holder's edge, the blended ones 1-2 px out: the sides did not hold); from a
    detection without one, whose sides held, the bands are not looked for again."""
    img, held = _hard_shadow(2.0, -16.8)
    first = track_holder(img, expected_size_px=(303.2, 193.0))
    assert first.ok and first.banded_sides == 1
    again = track_holder(img, expected_size_px=(303.2, 193.0), hint=first)
    assert again.ok and again.banded_sides == 1
    assert _err(again.corners_px, held) < 0.3
    calls: list[int] = []

    def counted(gray: np.ndarray, corners: np.ndarray, lens: object = None,
                profiles: object = None) -> list[object]:
        calls.append(1)
        return []
    clean, _ = _hard_shadow(0.0, -16.8)
    plain = track_holder(clean, expected_size_px=(303.2, 193.0))
    assert plain.ok and plain.banded_sides == 0
    monkeypatch.setattr(holder, "side_bands", counted)
    assert track_holder(clean, expected_size_px=(303.2, 193.0), hint=plain).ok
    assert calls == []
    assert track_holder(img, expected_size_px=(303.2, 193.0), hint=first).ok
    assert calls


@pytest.mark.parametrize("angle_deg", [20.0, 45.0])
def test_a_hard_shadow_band_in_a_jpeg_frame(angle_deg: float) -> None:
    """JPEG q 85 lifts every side's misfit of one step: the banded sides' stood out by
    2.1 times only, under the 3 first asked for before fitting two steps, and the 1.5 px
    band was returned 1.14 px off; now found within 1 px (0.82 and 0.39)."""
    img, held = _hard_shadow(1.5, angle_deg)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    det = track_holder(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), expected_size_px=(303.2, 193.0))
    assert ok and det.ok and det.banded_sides >= 1
    assert _err(det.corners_px, held) < 1.0


def _brushed(angle_deg: float, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A dark 303 x 193 px holder (60 DN) on a bright disc (200 DN) whose face is brushed:
    lines parallel to its short sides, a random profile across them (4 px correlation,
    15 DN rms), one line 4 px inside a short side lighter than the face by a band's share
    of the step. Blur 0.8 px, noise 1 DN, 1280 x 720. The frame and the corners."""
    held = rectangle((640.4, 360.1), 303.2, 193.0, angle_deg)
    yy, xx = np.mgrid[0:_WIDE_H, 0:_WIDE_W].astype(np.float32)
    t = math.radians(angle_deg + 90.0)
    across = -(xx - 640.4) * math.sin(t) + (yy - 360.1) * math.cos(t)
    n = 502
    prof = cv2.resize(np.random.default_rng(7).standard_normal((1, n)).astype(np.float32),
                      (n * 8, 1), interpolation=cv2.INTER_CUBIC)[0]
    prof /= prof.std()
    face = 60.0 + 15.0 * prof[np.clip(((across + 1000.0) / 4.0 * 8).astype(int), 0, n * 8 - 1)]
    cov = coverage(Polygon(held), _WIDE_RAS, (0, 0, _WIDE_W, _WIDE_H))
    img = cv2.GaussianBlur((200.0 * (1.0 - cov) + face * cov).astype(np.float32), (0, 0), 0.8)
    img += np.random.default_rng(seed).normal(0.0, 1.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), held


@pytest.mark.parametrize("angle_deg", [7.0, 30.0])
def test_a_brushed_faces_line_by_a_side_is_not_taken_for_its_edge(angle_deg: float) -> None:
    """The line 4 px inside the short side made a second step there like a shadow band's
    inner one, and the side was moved onto it: corners 3.7-3.9 px off at every angle. A
    band's holder face is flat beyond its inner step; this face varies by half the band's
    step within 12 px, so the side stays on its edge."""
    img, held = _brushed(angle_deg)
    det = track_holder(img, expected_size_px=(303.2, 193.0))
    assert det.ok, det.reason
    assert _err(det.corners_px, held) < 0.35


def test_opposite_widths_held_alike_rule() -> None:
    held = holder._alike_opposite_blurs(np.array([1.90, 1.91, 1.80, 2.62]))
    assert held is not None and np.allclose(held, [1.90, 1.91, 1.80, 1.91])
    assert holder._alike_opposite_blurs(np.array([1.9, 2.1, 1.8, 2.2])) is None
    assert holder._alike_opposite_blurs(np.array([0.5, 0.6, 0.5, 0.6])) is None
    # sharp edges' widths are ill-determined (a faint holder's, 13 DN steps): left alone
    assert holder._alike_opposite_blurs(np.array([0.61, 0.79, 1.12, 0.49])) is None


# the random generator's state just before corpus scene #979 of seed 71100 at 800 x 600
# ("everything": a dark holder on a grainy floor, a cast shadow, a label, cables, blur
# 1.86 px, JPEG q 82), so that one scene is drawn without the 979 before it
_SCENE_979 = {"bit_generator": "PCG64",
              "state": {"state": 233373525945409774648780502837178388398,
                        "inc": 5986232713851900319654404466589941687},
              "has_uint32": 0, "uinteger": 2206818695}


def test_a_side_fitted_softer_than_its_opposite_is_fitted_again_alike(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Corpus #979 of seed 71100: one side's edge was fitted 2.62 px wide against 1.91
    opposite (something beside it taken into the blur), the profile fit agreed with the
    area method within its allowance, and the corners were 0.83 px off at a stated sigma
    of 0.11. Fitted again with the sharper side's width, 0.33 px."""
    rng = np.random.default_rng()
    rng.bit_generator.state = _SCENE_979
    sc = random_top_scene(rng, "everything", (800, 600))
    det = track_holder(sc.image, expected_size_px=sc.expected_size_px)
    assert det.ok, det.reason
    blur = det.side_blur_px
    assert len(blur) == 4 and abs(blur[0] - blur[2]) <= 0.4 and abs(blur[1] - blur[3]) <= 0.4
    assert _err(det.corners_px, sc.corners_px) < 0.45
    # without the rule, and without the band check, which now reads that side as a soft
    # band beside the holder on its own (0.24 px off; test_vision_holder_soft_band.py)
    monkeypatch.setattr(holder, "_alike_opposite_blurs", lambda widths: None)
    monkeypatch.setattr(holder, "_off_the_bands", lambda gray, det, *args, **kw: det)
    before = track_holder(sc.image, expected_size_px=sc.expected_size_px)
    assert before.ok and _err(before.corners_px, sc.corners_px) > 0.7
