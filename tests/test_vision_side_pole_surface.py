"""The side camera's pole as a real rod shows it: lit from one side (a cylinder's shading, a
step 50 DN larger at one edge than at the other), shiny (a highlight along it, a bright
stripe with edges of its own), and casting its shadow on the wall behind. Before: the
automatic mode took the stripe, or the gap beside the pole, for the pole, or the pole's own
far edge for the sample's (tilts of -0.22 to +0.10 deg against -0.30), or found no pole;
with regions, a fit across the highlight ran off its windows and raised numpy's
LinAlgError; the shadow was taken for the pole or the sample (0.6 deg off)."""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import pytest

from alignd.errors import VisionError
from alignd.vision import side
from alignd.vision.edge_profile import Highlight
from alignd.vision.side import NARROW_HALF_WIDTH, measure_tilt, measure_tilt_frames
from drivers.sim.render import Polygon, Raster, coverage
from drivers.sim.scenes import random_side_scene

_W, _H, _SS = 1280, 720, 8  # the frame; sub-columns a pixel is drawn from
_POLE_W, _GAP, _SAMPLE_W = 40.0, 120.0, 300.0


def _view(levels: tuple[float, float, float], highlight: float, at: float, shade: float,
          pole_right: bool) -> tuple[np.ndarray, float, float]:
    """Background, pole and sample levels. A vertical pole whose level across it (s from -1
    to 1) is pole + shade s + a highlight of ``highlight`` DN centred at s = ``at``; the gap;
    a sample leaning 0.3 deg (its top toward -x); mirrored with ``pole_right``. Drawn on 8
    sub-columns a pixel, blur 0.8 px, noise 1 DN. The frame, the pole's x and the sample's
    near edge's x (middle row)."""
    bg, pole, sample = levels
    px = 800.0 if pole_right else 400.0
    sx = px - _GAP - _SAMPLE_W if pole_right else px + _POLE_W + _GAP
    xs = (np.arange(_W * _SS) + 0.5) / _SS
    img = np.full((_H, _W * _SS), bg, np.float32)
    s = (xs - px) / _POLE_W * 2.0 - 1.0
    on = np.abs(s) <= 1.0
    img[:, on] = (pole + shade * s + highlight * np.exp(-(((s - at) / 0.08) ** 2)))[on]
    left = sx + (np.arange(_H)[:, None] + 0.5 - _H / 2) * math.tan(math.radians(0.3))
    img[(xs[None, :] >= left) & (xs[None, :] < left + _SAMPLE_W)] = sample
    img = cv2.GaussianBlur(img.reshape(_H, _W, _SS).mean(axis=2), (0, 0), 0.8)
    img += np.random.default_rng(1).normal(0.0, 1.0, img.shape).astype(np.float32)
    near = sx + _SAMPLE_W if pole_right else sx
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), px + _POLE_W / 2, near


@pytest.mark.parametrize(("levels", "highlight", "at", "shade"), [
    ((120.0, 30.0, 230.0), 150.0, -0.5, 0.0),  # the stripe was the pole: -0.22 / -0.0005
    ((60.0, 200.0, 180.0), 150.0, 0.4, 0.0),  # the gap was the pole, the stripe the sample
    ((60.0, 200.0, 180.0), 0.0, 0.0, 25.0),  # shaded: the gap was the pole (+0.03)
    ((200.0, 40.0, 70.0), 0.0, 0.0, 25.0),  # shaded: no pole found
    ((220.0, 60.0, 30.0), 150.0, 0.4, 25.0),  # both: no pole found
])
@pytest.mark.parametrize("pole_right", [False, True])
def test_a_shaded_shiny_pole_is_found_whole_in_the_automatic_mode(
        levels: tuple[float, float, float], highlight: float, at: float, shade: float,
        pole_right: bool) -> None:
    img, pole_x, near_x = _view(levels, highlight, at, shade, pole_right)
    m = measure_tilt(img)
    xs = sorted(e.x_mid_px for e in m.pole_edges)
    assert xs == pytest.approx([pole_x - _POLE_W / 2, pole_x + _POLE_W / 2], abs=1.0)
    assert m.sample_edges[0].x_mid_px == pytest.approx(near_x, abs=1.0)
    assert m.tilt_deg == pytest.approx(-0.3, abs=0.005)


def test_a_highlight_beside_the_pole_edge_in_its_region_is_measured_not_a_numpy_error() -> None:
    """With regions, the profile fit of an edge with a highlight a few px inside it ran
    thousands of px off until its per-row solve was singular; such a fit now fails alone
    and the edge keeps its first measurement."""
    img, pole_x, near_x = _view((200.0, 40.0, 70.0), 60.0, 0.0, 25.0, False)
    x0 = int(pole_x - _POLE_W / 2)
    m = measure_tilt(img, pole_roi_px=(x0 - 20, 0, x0 + int(_POLE_W) + 20, _H),
                     sample_roi_px=(int(near_x) - 20, 0, int(near_x) + 20, _H))
    assert m.tilt_deg == pytest.approx(-0.3, abs=0.005)


def _with_shadow(width_px: float, offset_px: float, penumbra_px: float) -> np.ndarray:
    """A 30 px pole at x 600 (background 200, pole 40 DN), a sample (70 DN, 300 px) 120 px to
    its left leaning 0.3 deg, and the pole's shadow on the wall behind, ``offset_px`` to its
    right: ``width_px`` wide, leaning 0.6 deg, 60 % deep, its edges blurred by
    ``penumbra_px``; blur 0.8 px, noise 1 DN."""
    ras = Raster((_W, _H), 1000.0, (_W / 2, _H / 2), 0.0)
    box = (0, 0, _W, _H)

    def bar(left: float, width: float, angle_deg: float) -> Polygon:
        t = math.tan(math.radians(angle_deg))
        y0, y1, yc = -50.0, _H + 50.0, _H / 2
        return Polygon(np.array([[left + (y0 - yc) * t, y0], [left + width + (y0 - yc) * t, y0],
                                 [left + width + (y1 - yc) * t, y1], [left + (y1 - yc) * t, y1]]))

    img = np.full((_H, _W), 200.0)
    shade = coverage(bar(630.0 + offset_px, width_px, 0.6), ras, box).astype(np.float32)
    img *= 1.0 - 0.6 * cv2.GaussianBlur(shade, (0, 0), penumbra_px)
    img += (40.0 - img) * coverage(bar(600.0, 30.0, 0.0), ras, box)
    img += (70.0 - img) * coverage(bar(180.0, 300.0, 0.3), ras, box)
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.8)
    img += np.random.default_rng(1).normal(0.0, 1.0, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize(("width_px", "offset_px", "penumbra_px"),
                         [(20.0, 40.0, 4.0), (30.0, 100.0, 1.5), (45.0, 40.0, 1.5)])
def test_the_poles_shadow_beside_it_is_ambiguous_not_measured(
        width_px: float, offset_px: float, penumbra_px: float) -> None:
    """A pole lit from the front casts its shadow on the wall behind: a second full-height
    bar beside it, leaning as the light and the wall make it. Before: taken for the pole
    (the narrower) or for the sample's edge (the nearer), a tilt 0.6 deg off. Nothing tells
    the two bars apart in one frame: refused, naming the regions. (The first: a line fitted
    through pieces of the shadow's penumbra stood between the bars until only straight
    edges counted.)"""
    with pytest.raises(VisionError, match=r"ambiguous.*pole_roi_px"):
        measure_tilt(_with_shadow(width_px, offset_px, penumbra_px))


def test_a_pole_region_holding_the_poles_shadow_too_is_refused() -> None:
    """The regions mode looks for the pole in its region as the automatic mode does: a
    region drawn round the pole and its shadow had the shadow, the narrower, taken for the
    pole (+0.29 deg against -0.30). Refused, asking for a narrower region; drawn round
    the pole alone, the tilt is measured."""
    img = _with_shadow(20.0, 40.0, 4.0)
    with pytest.raises(VisionError, match=r"ambiguous.*narrow side_camera.pole_roi_px"):
        measure_tilt(img, pole_roi_px=(560, 0, 800, _H), sample_roi_px=(440, 0, 520, _H))
    m = measure_tilt(img, pole_roi_px=(570, 0, 660, _H), sample_roi_px=(440, 0, 520, _H))
    assert m.tilt_deg == pytest.approx(-0.3, abs=0.005)


@pytest.mark.parametrize(("levels", "highlight", "at"), [
    ((200.0, 40.0, 70.0), 150.0, -0.85),  # a dark pole, its highlight 3 px inside its left
    ((200.0, 40.0, 70.0), 150.0, 0.85),  # ... and right edge
    ((60.0, 160.0, 180.0), 60.0, -0.8),  # a light pole, 4 px inside
])
@pytest.mark.parametrize("pole_right", [False, True])
def test_a_highlight_a_few_px_inside_the_poles_edge_is_fitted_with_it(
        levels: tuple[float, float, float], highlight: float, at: float,
        pole_right: bool) -> None:
    """A polished rod lit from far to the side has its highlight near an edge, inside the
    area method's window there: that edge was measured in a sixth of the rows, 0.6 px
    apart, so it did not run through the image and the automatic mode found no pole; with
    regions the tilt was 0.0033 deg off. The edge is now fitted as a step with a line
    beside it (edge_profile.Highlight), in both modes."""
    img, pole_x, near_x = _view(levels, highlight, at, 0.0, pole_right)
    x0 = int(pole_x - _POLE_W / 2)
    regions = {"pole_roi_px": (x0 - 20, 0, x0 + int(_POLE_W) + 20, _H),
               "sample_roi_px": (int(near_x) - 20, 0, int(near_x) + 20, _H)}
    # _view's pixel k spans [k, k + 1); alignd's spans k -+ 1/2
    pole_x, near_x = pole_x - 0.5, near_x - 0.5
    for kw in ({}, regions):
        m = measure_tilt(img, **kw)
        xs = sorted(e.x_mid_px for e in m.pole_edges)
        assert xs == pytest.approx([pole_x - _POLE_W / 2, pole_x + _POLE_W / 2], abs=0.1)
        near_edge = min(m.pole_edges, key=lambda e: abs(
            e.x_mid_px - (pole_x + at * _POLE_W / 2)))
        assert near_edge.highlight is not None
        assert abs(near_edge.highlight.offset_px) == pytest.approx(
            (1 - abs(at)) * _POLE_W / 2, abs=0.2)
        # a rod's surface is shaded on a curve: its edges keep the narrow window (wider,
        # the bench's polished poles erred by up to 0.0033 deg, 0.0017 in the narrow one)
        assert near_edge.half_width is not None
        assert near_edge.half_width <= NARROW_HALF_WIDTH
        assert m.sample_edges[0].x_mid_px == pytest.approx(near_x, abs=0.2)
        assert m.tilt_deg == pytest.approx(-0.3, abs=0.002)


@pytest.mark.parametrize(("seed", "category"), [
    (11, "uneven light"), (16, "full-height sample")])
def test_a_polished_poles_highlight_is_never_taken_for_an_edge_of_the_pole(
        seed: int, category: str) -> None:
    """Corpus views with a polished pole (random_side_scene(..., polished=True)) on which
    the automatic mode measured the tilt on a wrong edge: the highlight's flank (a level
    as bright as the background beyond it) was taken for the pole's far edge, and that
    edge for the sample's. A region between two edges narrower than 12 px is now a line,
    not a level: the pole and the sample are the right ones."""
    sc = random_side_scene(np.random.default_rng(seed), category, polished=True)
    m = measure_tilt(sc.image)
    assert min(abs(m.sample_edges[0].x_mid_px - x) for x in sc.sample_x_px) < 0.5
    assert m.tilt_deg == pytest.approx(sc.tilt_deg, abs=0.01)


def test_a_pole_lost_beside_a_narrow_full_height_sample_is_refused_not_swapped() -> None:
    """Seed 20's first view: a faint pole (36 DN), defocused 1.4 px, its highlight 5 px
    inside its near edge, which only the second, fainter edge search finds; the sample, a
    full-height bar under a tenth of the frame wide, was the only narrow bar the first
    found, so it was taken for the pole (tilt -0.018 deg against +0.023). The fainter
    search's edges hold a narrower bar: refused as ambiguous, naming the regions; with
    them, measured."""
    sc = random_side_scene(np.random.default_rng(20), "full-height sample", polished=True)
    with pytest.raises(VisionError, match=r"ambiguous.*narrower.*pole_roi_px"):
        measure_tilt(sc.image)
    m = measure_tilt(sc.image, pole_roi_px=sc.pole_roi_px, sample_roi_px=sc.sample_roi_px)
    assert m.tilt_deg == pytest.approx(sc.tilt_deg, abs=0.01)


def test_a_faint_pole_edge_in_its_region_is_not_hidden_by_a_line_through_its_shading(
        ) -> None:
    """Seed 77's third view: a pole 20 px wide with a faint near edge (30 DN) and a
    cylinder's shading beside it. The region's first edge search fitted a line through
    pieces of the edge and the shading (1.1 px rms, 2.4 deg off, 5 px inside); the fainter
    search's straight edge was dropped as the same one, and the shading was taken for the
    pole's edge: 0.0208 deg off. Now the straighter edge measured in more rows is kept."""
    rng = np.random.default_rng(77)
    sc = [random_side_scene(rng, c, polished=True)
          for c in ("full-height sample", "sample on holder", "uneven light")][-1]
    m = measure_tilt(sc.image, pole_roi_px=sc.pole_roi_px, sample_roi_px=sc.sample_roi_px)
    # the pole's edge, not the shading 10 px inside it (its window narrowed to 4 px by the
    # edges the region holds, the faint edge reads 0.7 px out; its angle is what counts)
    left = min(e.x_mid_px for e in m.pole_edges)
    assert left == pytest.approx(sc.pole_x_px - sc.params["wp"] / 2, abs=1.0)
    assert m.tilt_deg == pytest.approx(sc.tilt_deg, abs=0.004)


def test_the_pre_checks_later_frames_keep_the_first_frames_model(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A later frame of the view is fitted with the first frame's model, a line beside the
    edge (started from the first frame's) or none: frames that took the line and frames
    that did not scattered a corpus view's pre-check (its error 0.0011 -> 0.0025 deg, 16
    -> 64 frames)."""
    img, _, _ = _view((200.0, 40.0, 70.0), 150.0, -0.85, 0.0, False)
    rng = np.random.default_rng(3)
    frames = [np.clip(np.rint(img + rng.normal(0.0, 1.0, img.shape)), 0, 255).astype(np.uint8)
              for _ in range(4)]
    asked: list[object] = []
    real = side.fit_vertical_edge

    def spy(*args: Any, **kwargs: Any) -> Any:
        asked.append(kwargs.get("line"))
        return real(*args, **kwargs)

    monkeypatch.setattr(side, "fit_vertical_edge", spy)
    first = measure_tilt(frames[0])
    n_first = len(asked)
    asked.clear()
    av = measure_tilt_frames(frames)
    lit = [e.highlight for e in first.pole_edges if e.highlight is not None]
    assert len(lit) == 1
    # the first frame is measured as measure_tilt measures it; each later frame fits every
    # edge once, with the first frame's model
    later = asked[n_first:]
    n_edges = len(first.pole_edges) + len(first.sample_edges)
    assert len(later) == 3 * n_edges
    assert [a for a in later if isinstance(a, Highlight)] == lit * 3
    assert sum(a is False for a in later) == 3 * (n_edges - 1)
    for f in av.frames:
        near = min(f.pole_edges, key=lambda e: e.x_mid_px)
        assert near.highlight is not None
        assert near.highlight.offset_px == pytest.approx(lit[0].offset_px, abs=0.1)
    assert av.tilt_deg == pytest.approx(-0.3, abs=0.001)
