"""Side camera: the sample edge, the vertical reference pole, and the tilt between them.

Angles are from the image vertical, positive when the line's top leans toward +x: on screen
(y down) that is a clockwise turn, the same sense as the top camera's angles ("x toward
y"). The tilt is sample minus pole, so a rolled camera (which turns both lines) does not
change it; a positive tilt means the sample's top leans further toward +x than the pole's.

Method: Canny + Hough finds the near-vertical edges coarsely; each is then measured in every
row it crosses with the area method (:mod:`alignd.vision.edges`) and fitted as a line
x = a + b y. Edges spanning most of the image height belong to the pole (a rod seen from
the side: two edges of opposite polarity); the shorter ones to the sample. The chosen pole
and sample edges are measured again as blurred steps over all their rows
(:mod:`alignd.vision.edge_profile`), free of the area method's bias under defocus. The
thesis' Canny + Hough angle (0.01 deg accumulator bins) is kept as :func:`baseline_tilt`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np

from alignd.errors import VisionError
from alignd.vision.edge_profile import Highlight, Spread, fit_vertical_edge, window_profile
from alignd.vision.edges import (
    EdgePoints,
    Line,
    as_gray,
    check_usable,
    coarse_edge,
    despeckle,
    edge_points,
    fit_line,
    linearise,
)
from alignd.vision.jpeg_bias import EdgeBias, edge_angle_bias, jpeg_quality
from drivers.config import ToneCurve
from drivers.tone_curves import is_linear

SIGN_CONVENTION = ("angles in deg from the image vertical, positive when the line's top leans "
                   "toward +x (clockwise on screen, the top camera's x-toward-y sense); "
                   "tilt = sample - pole")

__all__ = ["SIGN_CONVENTION", "SideEdge", "SideMeasurement", "TiltAverage", "baseline_tilt",
           "find_vertical_edges", "measure_tilt", "measure_tilt_frames"]


# levels within this share of a pair's smaller step count as one (the background's on both
# sides of a pole, or inside a gap: see _pole_runs)
_BACKGROUND_LEVEL = 0.3


@dataclass(frozen=True)
class SideEdge:
    """One near-vertical edge: its angle, position, extent and fit."""

    angle_deg: float
    sigma_deg: float
    x_mid_px: float  # x at the middle of its extent
    rows: tuple[int, int]
    contrast: float  # right level minus left level (DN)
    line: Line
    spread: Spread | None = None  # the blur model of the profile fit (None: area method)
    half_width: int | None = None  # of the profile fit's windows (px)
    blur_px: float | None = None  # the profile fit's blur width
    # the profile fit's row bands and each one's share of the angle's error (deg); see
    # :class:`alignd.vision.edge_profile.ProfileFit`
    bands: np.ndarray | None = None
    band_angle_deg: np.ndarray | None = None
    rms_dn: float | None = None  # the profile fit's residual (DN)
    highlight: Highlight | None = None  # a line fitted along the edge (a polished rod's)


@dataclass(frozen=True)
class SideMeasurement:
    """Sample and pole angles (deg from vertical) and the tilt (sample - pole)."""

    sample_angle_deg: float
    pole_angle_deg: float
    tilt_deg: float
    sigma_deg: float  # standard error of the tilt from the line fits
    sample_edges: tuple[SideEdge, ...]
    pole_edges: tuple[SideEdge, ...]
    mode: str = "auto"  # "roi": found in the configured regions; "auto": found unaided
    rois: tuple[tuple[int, int, int, int] | None, tuple[int, int, int, int] | None] = (None,
                                                                                      None)
    # the libjpeg quality the frame was coded at, as measure_tilt read it (None: not coded,
    # or not read); measure_tilt_frames' bias step uses it rather than reading it again
    coded_quality: int | None = None

    def to_json(self) -> dict[str, object]:
        return {"sample_angle_deg": self.sample_angle_deg, "pole_angle_deg": self.pole_angle_deg,
                "tilt_deg": self.tilt_deg, "sigma_deg": self.sigma_deg,
                "sign_convention": SIGN_CONVENTION, "mode": self.mode,
                "sample_x_px": [round(e.x_mid_px, 3) for e in self.sample_edges],
                "pole_x_px": [round(e.x_mid_px, 3) for e in self.pole_edges]}


def _angle_of(line: Line) -> tuple[float, float]:
    """Angle from vertical (top toward +x positive) and its standard error, in degrees."""
    b = -line.n[1] / line.n[0]  # x = a + b y
    sb = math.sqrt(max(line.cov_ab[1, 1], 0.0))
    return math.degrees(math.atan(-b)), math.degrees(sb / (1 + b * b))


def _hough_vertical(gray: np.ndarray, theta_step_deg: float, max_angle_deg: float,
                    threshold: int, canny: tuple[int, int] = (30, 90)
                    ) -> list[tuple[float, float, float]]:
    """Near-vertical Hough lines as (angle_deg, x at mid-height, -votes)."""
    u8 = np.clip(gray, 0, 255).astype(np.uint8)
    blur = cv2.GaussianBlur(u8, (0, 0), 1.0)
    edges = cv2.Canny(blur, *canny)
    h = gray.shape[0]
    out = []
    step = math.radians(theta_step_deg)
    amax = math.radians(max_angle_deg)
    for lo, hi in ((0.0, amax), (math.pi - amax, math.pi)):
        lines = cv2.HoughLinesWithAccumulator(edges, 1, step, threshold, min_theta=lo,
                                              max_theta=hi)
        if lines is None:
            continue
        for rho, theta, votes in np.asarray(lines).reshape(-1, 3):
            ang = theta if theta < math.pi / 2 else theta - math.pi
            x_mid = (rho - (h - 1) / 2 * math.sin(theta)) / math.cos(theta)
            out.append((math.degrees(ang), float(x_mid), -float(votes)))
    return out


def find_vertical_edges(image: np.ndarray, *, min_contrast: float = 15.0,
                        max_angle_deg: float = 8.0, min_rows: int = 60,
                        end_trim_rows: int = 6, canny: tuple[int, int] = (30, 90)
                        ) -> list[SideEdge]:
    """All near-vertical straight edges, sub-pixel, sorted by x. ``canny``: the edge
    detector's hysteresis thresholds for the coarse search (lower finds fainter edges: a
    defocused step of 30 DN does not reach the default 90)."""
    gray = as_gray(image, "side image")
    check_usable(gray, min_contrast, "side image")
    h = gray.shape[0]
    seeds = _hough_vertical(gray, 0.25, max_angle_deg, max(min_rows // 2, 20), canny)
    seeds.sort(key=lambda s: s[2])
    taken: list[float] = []
    edges: list[SideEdge] = []
    for ang, x_mid, _ in seeds:
        if any(abs(x_mid - t) < 6.0 for t in taken):
            continue
        taken.append(x_mid)
        tb = math.tan(math.radians(ang))
        # x(y) = x_mid - (y - ymid) * tan(angle)
        p0 = np.array([x_mid + (h - 1) / 2 * tb, 0.0])
        p1 = np.array([x_mid - (h - 1) / 2 * tb, h - 1.0])
        c = coarse_edge(gray, p0, p1, search_px=6, margin_px=2.0, min_step=min_contrast / 2)
        if c is None:
            continue
        found = _refine(gray, c, h, min_contrast, min_rows, end_trim_rows)
        if found is not None:  # second pass: windows re-centred on the first fit
            found = _refine(gray, found[0], h, min_contrast, min_rows, end_trim_rows)
        if (found is None or found[0].rms_px > _UNREAD_RMS_PX
                or found[0].n_used < _TALL * h):
            # the area method could not read the edge (a pole's?) in most rows: a
            # highlight along it, in its window?
            lit = _with_highlight(gray, c if found is None else found[0], min_contrast,
                                  min_rows, math.inf if found is None else found[0].rms_px)
            if lit is not None:
                edges.append(lit)
                continue
        if found is None:
            continue
        ln, pts = found
        a, sa = _angle_of(ln)
        rows = (int(pts.xy[:, 1].min()) - end_trim_rows, int(pts.xy[:, 1].max()) + end_trim_rows)
        ymid = (rows[0] + rows[1]) / 2
        edges.append(SideEdge(a, sa, float(ln.minor_at(ymid)), rows, ln.contrast, ln))
    # drop duplicates that converged onto the same edge
    edges.sort(key=lambda e: e.x_mid_px)
    uniq: list[SideEdge] = []
    for e in edges:
        if uniq and abs(e.x_mid_px - uniq[-1].x_mid_px) < 6.0:
            if e.line.n_used > uniq[-1].line.n_used:
                uniq[-1] = e
            continue
        uniq.append(e)
    return uniq


def _refine(gray: np.ndarray, seed: Line, h: int, min_contrast: float, min_rows: int,
            end_trim_rows: int) -> tuple[Line, EdgePoints] | None:
    """Area-method points along ``seed`` (rows), one polarity, ends trimmed; the line."""
    q0 = np.array([seed.minor_at(0.0), 0.0])
    q1 = np.array([seed.minor_at(h - 1.0), h - 1.0])
    pts = edge_points(gray, q0, q1, half_width=5, margin_px=2.0, min_contrast=min_contrast,
                      vertical=True)
    if pts.xy.shape[0] < min_rows:
        return None
    # keep one polarity (the dominant) so a crossing edge cannot pollute the line
    sgn = np.sign(np.median(pts.contrast))
    keep = np.sign(pts.contrast) == sgn
    # rows next to the edge's ends see the end face too: keep away from them
    if keep.sum() > 2 * end_trim_rows:
        ys = pts.xy[keep, 1]
        keep &= (pts.xy[:, 1] > ys.min() + end_trim_rows) & (
            pts.xy[:, 1] < ys.max() - end_trim_rows)
    pts = EdgePoints(pts.xy[keep], pts.contrast[keep], True)
    ln = fit_line(pts)
    if ln is None or ln.n_used < min_rows:
        return None
    return ln, pts


# an edge is looked at again as a step with a line beside it (a polished pole's edge runs
# through the image) where its area-method crossings scatter more than _UNREAD_RMS_PX (a
# straight edge's scatter 0.05-0.15 px; a pole's edge with its highlight 3 px inside, in
# the area method's window, 0.6 px over a sixth of its rows) or cover less than _TALL of
# the image's rows (a highlight's flank, 0.28 px over 520 of 720), and where its mean
# profile turns back (:func:`_with_highlight`: that test is what keeps the look cheap; a
# holder's or a shadow's edges, each fitted again, cost 0.1 s and were never a pole's)
_UNREAD_RMS_PX = 0.3
_TALL = 0.8
# the half-width of its windows (px): room for the edge 7 px from where it was seen (on a
# highlight's flank)
_HIGHLIGHT_HW = 9


def _with_highlight(gray: np.ndarray, seed: Line, min_contrast: float, min_rows: int,
                    area_rms_px: float) -> SideEdge | None:
    """The edge near ``seed`` fitted as a blurred step with a line along it
    (:func:`alignd.vision.edge_profile.fit_vertical_edge`) over the image's height (every
    second row: this finds the edge, :func:`_profiled` measures it); None
    unless that found such a line and a step of ``min_contrast`` in ``min_rows`` rows. Its
    line keeps the area method's scatter (``area_rms_px``, inf where it found too few
    rows), so the sample's straightness rule (:func:`_auto_sample`) reads it as before:
    such an edge is taken for the pole's, never for the sample's."""
    h = gray.shape[0]
    y_mid = (h - 1) / 2
    b = -float(seed.n[1] / seed.n[0])
    a, rows = float(seed.minor_at(y_mid)), np.arange(0, h, 2)
    # a step alone rises or falls across the window; one with a line beside it turns back
    got = window_profile(gray, a, b, y_mid, rows, _HIGHLIGHT_HW)
    if got is None or np.sum(np.abs(np.diff(got[0]))) - abs(got[0][-1] - got[0][0]) < (
            min_contrast):
        return None
    fit = fit_vertical_edge(gray, a, b, y_mid, rows, half_width=_HIGHLIGHT_HW,
                            min_rows=min_rows // 2)
    if fit is None or fit.highlight is None or abs(fit.contrast) < min_contrast:
        return None
    # every second row was read: the rows it was measured in are twice those read
    ln = replace(fit.line(), rms_px=area_rms_px, n_used=2 * int(fit.rows.size),
                 n_points=2 * int(fit.rows.size))
    span = (int(fit.rows.min()), int(fit.rows.max()))
    angle, sa = _angle_of(ln)
    return SideEdge(angle, sa, float(ln.minor_at((span[0] + span[1]) / 2)), span,
                    fit.contrast, ln, highlight=fit.highlight)


def _spans(e: SideEdge, h: int, fraction: float) -> bool:
    """Does the edge run (nearly) from the image top to its bottom, as the pole does?"""
    gap = (1.0 - fraction) * (h - 1) / 2
    return e.rows[0] <= gap and e.rows[1] >= h - 1 - gap


def _combine(edges: list[SideEdge]) -> tuple[float, float]:
    w = np.array([1.0 / max(e.sigma_deg, 1e-6) ** 2 for e in edges])
    a = np.array([e.angle_deg for e in edges])
    return float(w @ a / w.sum()), float(1.0 / math.sqrt(w.sum()))


def _length(e: SideEdge) -> int:
    """Rows the edge was measured in (not its span: a fit through pieces of several
    collinear edges spans far but uses few rows)."""
    return e.line.n_used


def _shifted(e: SideEdge, dx: int, dy: int) -> SideEdge:
    """An edge measured in a crop, in full-image coordinates."""
    off = np.array([dx, dy], float)
    ln = replace(e.line, d=float(e.line.d + e.line.n @ off))
    return replace(e, x_mid_px=e.x_mid_px + dx, rows=(e.rows[0] + dy, e.rows[1] + dy), line=ln)


# the coarse search's Canny thresholds for a second look, where the default (30, 90) found
# no pole or sample: a defocused step of 30 DN, or one in shade, does not reach 90
FAINT_CANNY = (10, 30)


def _roi_edges(image: np.ndarray, roi: tuple[int, int, int, int], what: str,
               min_contrast: float, canny: tuple[int, int] = (30, 90)) -> list[SideEdge]:
    """The near-vertical edges inside a region of interest (x0, y0, x1, y1, exclusive)."""
    h, w = np.asarray(image).shape[:2]
    x0, y0, x1, y1 = (int(v) for v in roi)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 16 or y1 - y0 < 40:
        raise VisionError(f"side image: the {what} region {tuple(roi)} is empty or too small "
                          f"inside the {w} x {h} image (needs at least 16 x 40 px)")
    crop = np.asarray(image)[y0:y1, x0:x1]
    min_rows = max(20, min(60, int(0.3 * (y1 - y0))))
    try:
        edges = find_vertical_edges(crop, min_contrast=min_contrast, min_rows=min_rows,
                                    canny=canny)
    except VisionError as exc:
        raise VisionError(f"side image: {what} region {tuple(roi)}: {exc}") from None
    return [_shifted(e, x0, y0) for e in edges]


# JPEG coding cuts a Gaussian edge's finest detail, and the disc (whose edge ends a radius
# out) then fits it as well or better: on 60 coded views of Gaussian edges, 0.98-1.0 times
# the Gaussians' residual on 7 and 0.80 on one (the pre-check 0.0015 -> 0.0038 deg off on
# one, 2.3 u); on 12 coded views through a disc, 0.46-0.93. On a coded frame the disc is
# kept where it fits by this share better than the best Gaussian model
_CODED_DISC_MARGIN = 0.9
# the profile fit's blur models (:func:`alignd.vision.edge_profile.step_basis`): a lens's
# Gaussian, a filter's on the pixel grid, a lens out of focus (a disc, whose edge the
# Gaussians misfit by an error that follows its sub-pixel phase: the pre-check 0.0043 deg
# off on a corpus view); the one that fits a frame's edges best is kept (:func:`_one_spread`)
SPREADS: tuple[Spread, ...] = ("optics", "pixel grid", "disc")
_GAUSSIANS: tuple[Spread, ...] = ("optics", "pixel grid")
# the profile fit's window, +- this many px where the other edges leave room (6 px clear
# of them; :func:`_half_width`). Each row's levels and slopes are its own, and near the
# edge a slope is nearly collinear with the edge's position: a wider window measures the
# slopes farther out. +-12 against +-7 on the bench's 300 views (regions, pre-check by
# uncertainty), seed 2224: max 0.00289 -> 0.00209 deg, RMS 0.00051 -> 0.00045, 16.6 ->
# 12.9 frames a view; +-16: 0.00238 (docs/vision.md, "A wider window")
PROFILE_HALF_WIDTH = 12
# ... where its angle agrees with the +-7 px window's within this many standard errors of
# their difference (the narrower fit's variance less the wider's, at least a tenth of
# the narrower's); else the narrow window's. A pole shaded 240-280 DN across, clipped at
# one edge, read 0.015 deg off in the wide window
NARROW_HALF_WIDTH = 7
WIDE_AGREEMENT = 3.0


def _profiled(gray: np.ndarray, e: SideEdge, others: list[SideEdge],
              roi: tuple[int, int, int, int] | None, end_trim_rows: int = 10,
              spreads: tuple[Spread, ...] = SPREADS, strict: bool = False,
              half_width: int | None = None, line: Highlight | bool | None = None
              ) -> SideEdge | None:
    """The edge re-measured as a blurred step over its rows (:mod:`edge_profile`); the
    window stays clear of the other edges and inside the region. Unchanged if that fails
    (None when ``strict``: a tracked edge must be measured in this frame). ``line``: a line
    beside the edge, as :func:`alignd.vision.edge_profile.fit_vertical_edge` takes it."""
    h, w = gray.shape
    hw = half_width or _half_width(gray, e, others, roi, line)
    x0, y0, x1, y1 = roi if roi is not None else (0, 0, w, h)
    x0, y0, x1, y1 = max(int(x0), 0), max(int(y0), 0), min(int(x1), w), min(int(y1), h)
    r0 = max(e.rows[0] + end_trim_rows, y0 + 4)
    r1 = min(e.rows[1] - end_trim_rows, y1 - 5)
    y_mid = (e.rows[0] + e.rows[1]) / 2
    b = -float(e.line.n[1] / e.line.n[0])
    fits = [fit_vertical_edge(gray, float(e.line.minor_at(y_mid)), b, y_mid,
                              np.arange(r0, r1 + 1), half_width=hw, x_limits=(x0, x1),
                              spread=spread, blur0=e.blur_px or 1.0, line=line)
            for spread in spreads]
    # the spread model that describes the edge better: residuals in DN over the same pixels
    fit = min((f for f in fits if f is not None), key=lambda f: f.rms_dn, default=None)
    # it refines the edge found, never moves to another one: within 3 px of it over the
    # rows, half the 6 px that separate two edges found (an angle bound of 0.1 deg, or
    # 1.5 px, rejected good fits where the area method was off: 0.1-0.15 deg off on JPEG
    # frames, 1.8 px at an end, where the profile fit was within 0.003 deg)
    ends = np.array([r0, y_mid, r1], float)
    # (or where it found a line beside the edge, the line within 3 px of it: the edge found
    # was the flank of a polished rod's highlight, the rod's edge a few px beyond)
    beside = 0.0 if fit is None or fit.highlight is None else fit.highlight.offset_px
    if fit is None or min(np.max(np.abs(fit.a + d + fit.b * (ends - fit.y_mid)
                                        - e.line.minor_at(ends))) for d in {0.0, beside}) > 3.0:
        return None if strict else e
    ln = fit.line()
    ln = replace(ln, rms_px=e.line.rms_px)
    return replace(e, angle_deg=fit.angle_deg, sigma_deg=fit.sigma_deg, x_mid_px=fit.a, line=ln,
                   spread=fit.spread, half_width=hw, blur_px=fit.blur_px, bands=fit.bands,
                   band_angle_deg=fit.band_angle_deg, rms_dn=fit.rms_dn,
                   highlight=fit.highlight)


def _half_width(gray: np.ndarray, e: SideEdge, others: list[SideEdge],
                roi: tuple[int, int, int, int] | None, line: Highlight | bool | None,
                spreads: tuple[Spread, ...] = SPREADS) -> int:
    """The profile fit's window for edge ``e``: as wide as the other edges leave room for,
    up to :data:`PROFILE_HALF_WIDTH`, where its angle agrees with the narrow window's
    (:data:`WIDE_AGREEMENT`): the per-row slopes are straight lines, and a surface shaded
    on a curve (a rod) is one only near the edge. Else :data:`NARROW_HALF_WIDTH` (or less,
    where the room is less), and so where either fit found a line along the edge (a
    polished rod's highlight). Decided once for every blur model, whose residuals are then
    compared over the same windows (the fits here each take the best of ``spreads``)."""
    gaps = [g for o in others if (g := _gap_px(e, o)) > 3]
    room = int(np.clip(math.floor(min(gaps, default=99.0) - 6.0), 4, PROFILE_HALF_WIDTH))
    if room <= NARROW_HALF_WIDTH:
        return room
    narrow = _profiled(gray, e, others, roi, strict=True, half_width=NARROW_HALF_WIDTH,
                       line=line, spreads=spreads)
    wide = _profiled(gray, e, others, roi, strict=True, half_width=room, line=line,
                     spreads=spreads)
    if narrow is None or wide is None:
        return NARROW_HALF_WIDTH if wide is None else room
    if narrow.highlight is not None or wide.highlight is not None:
        return NARROW_HALF_WIDTH  # a polished rod: its surface is shaded on a curve
    bound = WIDE_AGREEMENT * math.sqrt(max(narrow.sigma_deg ** 2 - wide.sigma_deg ** 2,
                                           0.1 * narrow.sigma_deg ** 2))
    return room if abs(wide.angle_deg - narrow.angle_deg) <= bound else NARROW_HALF_WIDTH


def _gap_px(e: SideEdge, o: SideEdge) -> float:
    """How far edge ``o`` lies from ``e``: their middles' distance in x, or 0 where ``o``
    lies within 3 px of ``e`` all along the rows both span (at their ends and middle):
    the same edge, found again over part of its rows. The middles' x differ by the edge's
    slope times the rows between them: on a camera rolled 1 deg, a second find of the
    sample edge over its upper half sat 6 px from it and held the window to +-4 px.
    (The least distance over the shared rows for every edge narrowed polished poles'
    windows where a highlight's flank runs beside the edge over part of it: 33 of 120
    fits changed, the automatic mode's max 0.00217 -> 0.00384 deg.)"""
    r0, r1 = max(e.rows[0], o.rows[0]), min(e.rows[1], o.rows[1])
    if r1 > r0 and e.line.vertical and o.line.vertical:
        ys = np.array([r0, (r0 + r1) / 2, r1], float)
        if float(np.max(np.abs(o.line.minor_at(ys) - e.line.minor_at(ys)))) <= 3.0:
            return 0.0
    return abs(o.x_mid_px - e.x_mid_px)


def _pole_pair(edges: list[SideEdge], max_width_px: float) -> list[SideEdge]:
    """The rod in its region: the narrowest pair of x-adjacent edges of opposite polarity,
    at least _LEVEL_FAR apart (narrower is a line, as in :func:`_pole_runs`: a polished
    pole shaded to the background's level at one side shows one edge, and a line through
    its shading 6 px inside was paired with it, 0.004 deg of tilt; the one edge alone is
    what :func:`measure_tilt` then falls back on)."""
    srt = sorted(edges, key=lambda e: e.x_mid_px)
    bars = {k: b.x_mid_px - a.x_mid_px for k, (a, b) in enumerate(itertools.pairwise(srt))
            if a.contrast * b.contrast < 0
            and _LEVEL_FAR <= b.x_mid_px - a.x_mid_px <= max_width_px
            and abs(a.angle_deg - b.angle_deg) < 0.5}
    if not bars:
        return []
    k = min(bars, key=lambda j: bars[j])
    return [srt[k], srt[k + 1]]


# a second full-height bar beside the narrowest, with no edge between them, must be this many
# times wider for the narrowest to be taken for the pole
_CLEARLY_WIDER = 2.0
# the share of the image's (region's) rows a pole edge must be measured in
_MIN_ROWS_SHARE = 0.5
# the levels beside an edge are read this far from it (px), and short of halfway to the next
_LEVEL_NEAR, _LEVEL_FAR = 3, 12


def _side_levels(gray: np.ndarray, edges: list[SideEdge]) -> np.ndarray:
    """The image's level just left and just right of each edge (sorted by x), (n, 2): the
    median over the edge's rows of the pixels _LEVEL_NEAR to _LEVEL_FAR px beside it, short
    of halfway to the next edge. Read from the image, not only summed from the edges' steps:
    a pole lit from one side (a cylinder) steps 50 DN more at one edge than at the other,
    so the sum did not return to the background beyond it."""
    h, w = gray.shape
    xs = [e.x_mid_px for e in edges]
    out = np.empty((len(edges), 2))
    for k, e in enumerate(edges):
        ys = np.arange(max(e.rows[0], 0), min(e.rows[1], h - 1) + 1, 2)
        x = e.line.minor_at(ys.astype(float))
        for side, sgn in enumerate((-1, 1)):
            nxt = xs[k + sgn] if 0 <= k + sgn < len(xs) else math.inf * sgn
            room = abs(nxt - e.x_mid_px) / 2
            d = np.arange(min(_LEVEL_NEAR, max(room - 1, 1)), min(_LEVEL_FAR, max(room, 2)))
            cols = np.clip(np.rint(x[:, None] + sgn * d[None, :]), 0, w - 1).astype(int)
            out[k, side] = float(np.median(gray[ys[:, None], cols]))
    return out


def _pole_runs(gray: np.ndarray, edges: list[SideEdge], max_width_px: float, rows: int,
               advice: str = "set side_camera.pole_roi_px and sample_roi_px"
               ) -> list[SideEdge]:
    """The rod among ``edges`` (the full-height ones unaided, a region's with regions):
    edges i and j of opposite polarity at most ``max_width_px`` apart with one level on both
    their outer sides (a pole stands on the background), and any edges between them its
    surface (a highlight along a shiny rod, the shading of a rod lit from one side). Not a
    pole: edges whose inside comes back to their outer level (two things, or the gap between
    them), or, where the image's two outer levels agree (the background at both ends), to
    that level (the gap between a pole and a sample of one level: a bar too, and where it
    was the narrower it was taken for the pole). A bar inside another is the rod's surface.
    Of what remains, the narrowest; a VisionError where another shares an edge with it, or
    lies beside it with no edge between them and is not _CLEARLY_WIDER (either could be the
    pole: a full-height sample narrower than the pole was taken for it, and the tilt's sign
    flipped). Only edges measured in at least _MIN_ROWS_SHARE of ``rows`` count: a line
    fitted through pieces of a penumbra (in 20 % of the rows, 1.2 px rms, 5 deg off) between
    a pole and its shadow on the wall behind stood between them, so they did not count as
    side by side and the shadow, the narrower, was taken for the pole."""
    srt = sorted((e for e in edges if _length(e) >= _MIN_ROWS_SHARE * rows),
                 key=lambda e: e.x_mid_px)
    if len(srt) < 2:
        return []
    # each level two ways: read beside the edges (a shaded pole's steps do not sum to zero)
    # and, across a pair of edges, summed from their steps (a shadow's edge near the pole
    # makes the levels read beside it differ; the steps are local; but a highlight's edges
    # step less than its plateau, so not summed across a run). Region k: left of edge k
    lv = _side_levels(gray, srt)
    step = np.abs(lv[:, 1] - lv[:, 0])
    c = np.array([e.contrast for e in srt])
    summed = np.concatenate([[0.0], np.cumsum(c)])
    x = np.array([e.x_mid_px for e in srt])
    ends_agree = bool(abs(lv[0, 0] - lv[-1, 1]) <= _BACKGROUND_LEVEL * np.median(step)
                      or abs(summed[-1]) <= _BACKGROUND_LEVEL * np.median(np.abs(c)))
    # a region narrower than _LEVEL_FAR between two edges is a line, not a level: a
    # highlight along a polished rod (its flanks found as edges, its peak as bright as the
    # background), never a pole (the edge finder needs ~12 px between two edges). A bar
    # bounded by one on its outside is no pole; inside one, its level is the rod's surface
    gaps = np.diff(x)
    line_right = np.concatenate([gaps < _LEVEL_FAR, [False]])  # edge k's right region
    line_left = np.concatenate([[False], gaps < _LEVEL_FAR])
    runs = []
    for i, j in itertools.combinations(range(len(srt)), 2):
        if (c[i] * c[j] >= 0 or x[j] - x[i] > max_width_px
                or abs(srt[i].angle_deg - srt[j].angle_deg) >= 0.5
                or line_left[i] or line_right[j]):
            continue
        tol = _BACKGROUND_LEVEL * min(step[i], step[j])
        tol_c = _BACKGROUND_LEVEL * min(abs(c[i]), abs(c[j]))
        pair = j == i + 1
        if not (abs(lv[i, 0] - lv[j, 1]) <= tol
                or (pair and abs(summed[i] - summed[j + 1]) <= tol_c)):
            continue  # not one level on both its sides
        level = ~line_right[i:j]  # the regions inside that are levels, not lines
        inside = np.concatenate([lv[i:j, 1][level], lv[i + 1:j + 1, 0][level]])
        at = np.concatenate([x[i:j][level], x[i + 1:j + 1][level]])
        if np.any(np.abs(inside - (lv[i, 0] + lv[j, 1]) / 2) <= tol):
            continue  # back at its outer level inside
        # the background under a linear gradient, from the image's two ends
        bg = np.interp(at, [x[0], x[-1]], [lv[0, 0], lv[-1, 1]])
        if ends_agree and np.any(np.abs(inside - bg) <= tol):
            continue  # the background inside: a gap
        runs.append((i, j))
    runs = [r for r in runs if not any(o != r and o[0] <= r[0] and r[1] <= o[1] for o in runs)]
    if not runs:
        return []
    width = {r: x[r[1]] - x[r[0]] for r in runs}
    best = min(runs, key=width.__getitem__)
    for r in runs:  # beside it: sharing an edge, or with none between them and not clearly
        # wider (the corpus' samples are 3-5 times its poles' width)
        shared = r[0] == best[1] or best[0] == r[1]
        next_to = r[0] - best[1] == 1 or best[0] - r[1] == 1
        if shared or (next_to and width[r] < _CLEARLY_WIDER * width[best]):
            lo, hi = sorted((best, r))
            raise VisionError(
                f"side image: the reference pole is ambiguous: bars at x {x[lo[0]]:.0f}-"
                f"{x[lo[1]]:.0f} and {x[hi[0]]:.0f}-{x[hi[1]]:.0f} px with no edge between "
                "them, either could be the pole and the other the sample or the gap beside "
                f"it; {advice}")
    return [srt[best[0]], srt[best[1]]]


def _region_pole(gray: np.ndarray, pool: list[SideEdge], width: float,
                 roi: tuple[int, int, int, int]) -> list[SideEdge]:
    """The rod in its region: as unaided (:func:`_pole_runs`: a highlight or shading along
    it is its surface, and a second bar beside it makes it ambiguous: a region drawn wide
    enough to hold the pole's shadow had the shadow, the narrower, taken for the pole),
    else the narrowest pair of opposite edges, else []."""
    return (_pole_runs(gray, pool, width, int(roi[3] - roi[1]),
                       advice=f"narrow side_camera.pole_roi_px {tuple(roi)} to the pole alone")
            or _pole_pair(pool, width))


def _auto_pole(gray: np.ndarray, edges: list[SideEdge], h: int, min_fraction: float,
               max_width_px: float) -> list[SideEdge]:
    """The pole unaided: a narrow bar whose edges run through the whole height; failing
    that, 90 % of it (uneven light, ends)."""
    for frac in (min_fraction, 0.9):
        pole = _pole_runs(gray, [e for e in edges if _spans(e, h, frac)], max_width_px, h)
        if pole:
            return pole
    return []


def _no_narrower_bar(gray: np.ndarray, edges: list[SideEdge], pole: list[SideEdge],
                     h: int, min_fraction: float) -> None:
    """A VisionError where the long edges (over half the rows) hold a bar narrower than the
    full-height one taken for the pole, one of its edges running through the image: the
    pole with its other edge read in part of the rows (a polished rod's highlight beside
    it) or found only by the fainter search, and the bar taken a full-height sample. Its
    tilt was measured against the pole's own edge, the sign flipped (0.26 deg off)."""
    lo, hi = sorted(e.x_mid_px for e in pole)
    outside = [e for e in edges if not lo + 3 < e.x_mid_px < hi - 3]  # not its surface
    try:  # a tenth narrower at least: the bar taken, whose edges are among these, is not
        bar = _pole_runs(gray, outside, 0.9 * (hi - lo), h)
    except VisionError:  # two narrow bars side by side: not the pole taken either
        bar = []
    # one of its edges runs through the whole image, as a pole's does: a sample on its
    # holder narrower than the pole is a bar of long edges too (our own renderer's, over
    # 92 % of the height)
    if len(bar) == 2 and any(_spans(e, h, min_fraction) for e in bar):
        a, b = sorted(e.x_mid_px for e in bar)
        raise VisionError(
            f"side image: the reference pole is ambiguous: the bar at x {lo:.0f}-{hi:.0f} px "
            f"runs through the image, but a narrower one at x {a:.0f}-{b:.0f} px has edges "
            "found in part of the rows or only at a lower contrast; either could be the "
            "pole; set side_camera.pole_roi_px and sample_roi_px")


def _merge(a: list[SideEdge], b: list[SideEdge]) -> list[SideEdge]:
    """Edges of two searches, one per position: the first search's where both found it,
    unless the second's is straighter and measured in more rows. On a faint edge the
    first search can fit a line through pieces of it and of a shading beside it (1.1 px
    rms, 2 deg off, 5 px from the edge); it hid the second's straight edge, and a polished
    pole's region then took the shading for the pole's edge (0.02 deg of tilt)."""
    out = []
    for e in a:
        near = [o for o in b if abs(o.x_mid_px - e.x_mid_px) < 6.0]
        better = [o for o in near
                  if o.line.rms_px < e.line.rms_px and _length(o) > _length(e)]
        out.append(min(better, key=lambda o: o.line.rms_px) if better else e)
    out += [e for e in b if all(abs(e.x_mid_px - o.x_mid_px) >= 6.0 for o in a)]
    return sorted(out, key=lambda e: e.x_mid_px)


def _partner(main: SideEdge, pool: list[SideEdge]) -> list[SideEdge]:
    """The sample's other face: parallel, opposite polarity, over the same rows."""
    out = [main]
    for e in pool:
        if e is main or e.contrast * main.contrast >= 0 or abs(e.angle_deg - main.angle_deg) >= 0.2:
            continue
        lo, hi = max(e.rows[0], main.rows[0]), min(e.rows[1], main.rows[1])
        if hi - lo >= 0.8 * _length(main) and hi - lo >= 0.8 * _length(e):
            out.append(e)
            break
    return out


def measure_tilt(image: np.ndarray, *, pole_roi_px: tuple[int, int, int, int] | None = None,
                 sample_roi_px: tuple[int, int, int, int] | None = None,
                 pole_x_px: float | None = None, sample_x_px: float | None = None,
                 min_contrast: float = 15.0, pole_min_fraction: float = 0.97,
                 max_pole_width_px: float | None = None, max_edge_rms_px: float = 0.35
                 ) -> SideMeasurement:
    """Sample angle, pole angle and tilt from one side-camera frame.

    With regions of interest (``pole_roi_px``, ``sample_roi_px``: x0, y0, x1, y1 in px, from
    the config's ``side_camera`` keys) each target is measured inside its own region: the
    pole as below (:func:`_region_pole`; or its narrowest pair of opposite edges, or its one
    edge), the sample as its longest edge there. Without them (automatic mode) the pole is
    the narrowest bar on the background (two edges of opposite polarity, at most
    ``max_pole_width_px`` apart, default a tenth of the width, any edges between them its
    surface: :func:`_pole_runs`) whose edges both run through the image height (or, failing
    that, 90 % of it: uneven light may hide their ends), and the sample edge is the edge
    outside it nearest the pole among the long ones (at least 80 % of the longest other
    edge); its parallel opposite face is averaged in when it covers the same rows.
    ``pole_x_px`` / ``sample_x_px`` (approximate x) pick among the edges instead. Raises
    VisionError when either target is missing or ambiguous.
    """
    raw = image  # (whether it was JPEG-coded is read on the frame as it came)
    # hot and dead pixels replaced (edges.despeckle); the searches below read this frame
    image = gray = despeckle(as_gray(image, "side image"))
    h, w = gray.shape
    mode = "roi" if pole_roi_px is not None or sample_roi_px is not None else "auto"
    # the regions' edges: the windows of the edges measured keep clear of them (a
    # highlight's flank beside a pole's edge, found in its region, is no sample's or pole's)
    seen: list[SideEdge] = []
    if pole_roi_px is not None:
        width = float(pole_roi_px[2] - pole_roi_px[0])
        pool = _roi_edges(image, pole_roi_px, "pole", min_contrast)
        pole = _region_pole(gray, pool, width, pole_roi_px)
        if not pole:  # a faint pole edge: look again with lower thresholds
            pool = _merge(pool, _roi_edges(image, pole_roi_px, "pole", min_contrast,
                                           FAINT_CANNY))
            pole = (_region_pole(gray, pool, width, pole_roi_px)
                    or ([max(pool, key=_length)] if pool else []))
        if not pole:
            raise VisionError(f"side image: reference pole not found in its region "
                              f"{tuple(pole_roi_px)}")
        seen += pool
    edges: list[SideEdge] = []
    faint: list[list[SideEdge]] = []  # the lower thresholds' edges, once searched
    faint_searched = False  # edges holds them too

    def faint_edges() -> list[SideEdge]:
        """The search with the lower thresholds, run once at most."""
        if not faint:
            faint.append(find_vertical_edges(image, min_contrast=min_contrast,
                                             canny=FAINT_CANNY))
        return faint[0]
    if pole_roi_px is None or sample_roi_px is None:
        edges = find_vertical_edges(image, min_contrast=min_contrast)
        if not edges:
            raise VisionError("side image: no near-vertical edge found (neither sample nor "
                              "pole)")
    if pole_roi_px is None:
        if pole_x_px is not None:
            pool = sorted(edges, key=lambda e: abs(e.x_mid_px - pole_x_px))[:2]
            pool = [e for e in pool if abs(e.x_mid_px - pole_x_px) < 60]
        else:
            pole = _auto_pole(gray, edges, h, pole_min_fraction, max_pole_width_px or 0.1 * w)
            if not pole:
                # a faint, defocused or shaded pole edge may not reach the coarse search's
                # threshold: look again with a lower one
                faint_searched = True
                edges = _merge(edges, faint_edges())
                pole = _auto_pole(gray, edges, h, pole_min_fraction,
                                  max_pole_width_px or 0.1 * w)
            if pole:  # a pole edge the first search missed may show it is elsewhere
                _no_narrower_bar(gray, edges if faint_searched
                                 else _merge(edges, faint_edges()), pole, h,
                                 pole_min_fraction)
        if pole_x_px is not None:
            pole = _pole_pair(pool, max_pole_width_px or 0.1 * w)
        if not pole and pole_x_px is not None and pool:
            pole = [max(pool, key=_length)]
        if not pole:
            raise VisionError("side image: reference pole not found (no narrow bar whose two "
                              "edges run through the image from top to bottom; set "
                              "side_camera.pole_roi_px)")
    if sample_roi_px is not None:
        def besides_pole(pool: list[SideEdge]) -> list[SideEdge]:
            return [e for e in pool if all(abs(e.x_mid_px - p.x_mid_px) > 3 for p in pole)]

        rest = besides_pole(_roi_edges(image, sample_roi_px, "sample", min_contrast))
        if not rest:  # a faint sample edge: look again with lower thresholds
            rest = besides_pole(_roi_edges(image, sample_roi_px, "sample", min_contrast,
                                           FAINT_CANNY))
        if not rest:
            raise VisionError(f"side image: sample edge not found in its region "
                              f"{tuple(sample_roi_px)}")
        main = max(rest, key=_length)
        seen += rest
    else:
        try:
            main, rest = _auto_sample(edges, pole, h, sample_x_px, max_edge_rms_px)
        except VisionError:
            if faint_searched:
                raise
            # a faint sample edge: look again with lower thresholds
            edges = _merge(edges, faint_edges())
            main, rest = _auto_sample(edges, pole, h, sample_x_px, max_edge_rms_px)
    sample = _partner(main, rest)
    others = [*edges, *seen, *pole, *sample]
    quality = _coded_near(raw, sample[0])
    joint = _one_spread(gray, pole, sample, others, pole_roi_px, sample_roi_px,
                        coded=quality is not None)
    if joint is not None:
        pole, sample = joint
    else:
        pole = _each_profiled(gray, pole, others, pole_roi_px, None, "pole")
        sample = _each_profiled(gray, sample, others, sample_roi_px, False, "sample")
    return replace(_measurement(sample, pole, mode, (pole_roi_px, sample_roi_px)),
                   coded_quality=quality)


# an edge whose rows are clipped (a pixel at black or full scale beside it) in more than
# this share is not measured: the area method's line on it is biased
_CLIPPED_SHARE = 0.5


def _each_profiled(gray: np.ndarray, edges: list[SideEdge], others: list[SideEdge],
                   roi: tuple[int, int, int, int] | None, line: Highlight | bool | None,
                   what: str) -> list[SideEdge]:
    """Each edge of one target (the pole's, the sample's) re-measured by the profile fit;
    one it cannot measure is left out where another was measured, else they are kept as
    found, unless clipped: a VisionError then. The area method's line on a clipped edge (a
    pole at full scale, its step flattened on one side by an amount that follows the light
    along it) was 0.014-0.024 deg off at a stated 0.0003-0.0008, and outweighed the other
    edge's profile fit; with both edges clipped, the tilt was 0.013 deg off at 25 u."""
    fitted = [p for e in edges
              if (p := _profiled(gray, e, others, roi, strict=True, line=line)) is not None]
    if fitted:
        return fitted
    share, e, bright = max(((_clipped_share(gray, e, b), e, b) for e in edges
                            for b in (True, False)), key=lambda t: t[0])
    if share > _CLIPPED_SHARE:
        raise VisionError(
            f"side image: the {what}'s edge at x {e.x_mid_px:.0f} px is clipped "
            f"({'full scale' if bright else 'black'} beside it) in {100 * share:.0f} % of its "
            f"rows, and cannot be measured; {'lower' if bright else 'raise'} the side "
            f"camera's exposure or gain, or the light on the {what}")
    return edges


def _clipped_share(gray: np.ndarray, e: SideEdge, bright: bool, half_width: int = 7
                   ) -> float:
    """The share of the edge's rows with a pixel at full scale (``bright``; 255) or black
    (0) within ``half_width`` px of it."""
    h, w = gray.shape
    ys = np.arange(max(e.rows[0], 0), min(e.rows[1], h - 1) + 1)
    x = np.rint(e.line.minor_at(ys.astype(float))).astype(int)
    cols = np.clip(x[:, None] + np.arange(-half_width, half_width + 1)[None, :], 0, w - 1)
    px = gray[ys[:, None], cols]
    hit = px >= 254.5 if bright else px <= 0.5
    return float(np.mean(hit.any(axis=1))) if len(ys) else 0.0


def _auto_sample(edges: list[SideEdge], pole: list[SideEdge], h: int,
                 sample_x_px: float | None, max_edge_rms_px: float
                 ) -> tuple[SideEdge, list[SideEdge]]:
    """The sample edge without a region: among the long straight edges besides the pole
    and outside it (at least 80 % of the longest), the one nearest ``sample_x_px`` or else
    the pole; and the edges its opposite face is looked for among."""
    lo = min(p.x_mid_px for p in pole) - 3
    hi = max(p.x_mid_px for p in pole) + 3
    rest = [e for e in edges if not lo <= e.x_mid_px <= hi]  # nor the pole's surface
    if sample_x_px is not None:
        rest = [e for e in rest if abs(e.x_mid_px - sample_x_px) < 150]
    # a straight edge fits to hundredths of a pixel; a fit through the sample's edge
    # and a nearly collinear holder edge below it does not, and would bias the tilt
    rest = [e for e in rest if e.line.rms_px <= max_edge_rms_px]
    if not rest:
        raise VisionError("side image: sample edge not found (no straight edge besides "
                          "the pole)")
    longest = max(_length(e) for e in rest)
    if longest < 0.25 * h:
        raise VisionError(f"side image: sample edge not found (the longest edge besides "
                          f"the pole covers {longest} of {h} rows)")
    long_ones = [e for e in rest if _length(e) >= 0.8 * longest]
    near = sample_x_px if sample_x_px is not None else float(
        np.mean([e.x_mid_px for e in pole]))
    return min(long_ones, key=lambda e: abs(e.x_mid_px - near)), rest


def _one_spread(gray: np.ndarray, pole: list[SideEdge], sample: list[SideEdge],
                others: list[SideEdge], pole_roi: tuple[int, int, int, int] | None,
                sample_roi: tuple[int, int, int, int] | None, coded: bool = False
                ) -> tuple[list[SideEdge], list[SideEdge]] | None:
    """Every edge profiled with the one blur model that fits them all best (their squared
    residuals summed over the same rows): the blur comes from the camera (its lens, or its
    processing), the same for every edge of a frame. Chosen edge by edge, a faint sample
    edge on a JPEG frame took the pixel-grid model (the coding softens it on the pixel
    grid) where the pole's clearly took the optics', and that model's error followed the
    edge's phase: 0.0018-0.0034 deg of tilt on the bench's views. On a JPEG-coded frame
    (``coded``) the disc must fit better by :data:`_CODED_DISC_MARGIN`, and the windows
    are chosen by the Gaussian models' fits (the disc's, taken there as well, widened a
    coded Gaussian edge's window: 0.0015 -> 0.0036 deg off). None when no model fits
    every edge."""
    fitted: list[tuple[list[SideEdge], list[SideEdge]]] = []
    names: list[Spread] = []
    # (on a coded frame the windows are the Gaussians' to decide, as the disc's place is)
    near = _GAUSSIANS if coded else SPREADS
    pole_hw = [_half_width(gray, e, others, pole_roi, None, near) for e in pole]
    sample_hw = [_half_width(gray, e, others, sample_roi, False, near) for e in sample]
    for spread in SPREADS:
        ps = [_profiled(gray, e, others, pole_roi, spreads=(spread,), strict=True,
                        half_width=k)
              for e, k in zip(pole, pole_hw, strict=True)]
        # a line beside an edge is a polished pole's highlight: the samples are diffuse (a
        # shadow's or a lamp's boundary beside an uneven-light sample's edge, fitted as
        # one, doubled its error and the pre-check took 64 frames where it took 8)
        ss = [_profiled(gray, e, others, sample_roi, spreads=(spread,), strict=True,
                        half_width=k, line=False)
              for e, k in zip(sample, sample_hw, strict=True)]
        p_ok, s_ok = [p for p in ps if p is not None], [q for q in ss if q is not None]
        if len(p_ok) == len(ps) and len(s_ok) == len(ss):
            fitted.append((p_ok, s_ok))
            names.append(spread)
    if not fitted:
        return None
    # each edge's squared residual weighed by the most rows a model kept on it: a model
    # that leaves most of an edge's rows out as misfits must not win by their absence (the
    # pixel-grid model kept 107 of 448 rows of a JPEG sample edge and its cost over them
    # was the lower, though its residual was higher on every edge; the pre-check's tilt
    # was 0.0059 deg off with it, 0.0006 with the optics')
    rows = np.max([[f.line.n_used for f in (*ps, *ss)] for ps, ss in fitted], axis=0)
    costs = [float(np.dot(rows, [(f.rms_dn or 0.0) ** 2 for f in (*ps, *ss)]))
             for ps, ss in fitted]
    if coded and "disc" in names and len(names) > 1:
        k = names.index("disc")
        rest = min(c for j, c in enumerate(costs) if j != k)
        if costs[k] > _CODED_DISC_MARGIN * rest:
            costs[k] = math.inf
    return fitted[int(np.argmin(costs))]


def _measurement(sample: list[SideEdge], pole: list[SideEdge], mode: str,
                 rois: tuple[tuple[int, int, int, int] | None, tuple[int, int, int, int] | None]
                 ) -> SideMeasurement:
    sa, ss = _combine(sample)
    pa, ps = _combine(pole)
    return SideMeasurement(sa, pa, sa - pa, math.hypot(ss, ps), tuple(sample), tuple(pole), mode,
                           rois)


def _tracked(image: np.ndarray, prev: SideMeasurement) -> SideMeasurement | None:
    """The same pole and sample edges measured again in a later frame of the same view,
    each started from where ``prev`` found it and fitted with the blur model chosen there
    (the search is skipped: the rig does not move between pre-check frames). None when an
    edge is not where it was."""
    gray = despeckle(as_gray(image, "side image"))
    others = [*prev.pole_edges, *prev.sample_edges]
    pole_roi, sample_roi = prev.rois
    out: list[list[SideEdge]] = [[], []]
    for k, (edges, roi) in enumerate(((prev.pole_edges, pole_roi),
                                      (prev.sample_edges, sample_roi))):
        for e in edges:
            spreads = (e.spread,) if e.spread is not None else SPREADS
            # the first frame's model: a line beside the edge there, or none
            p = _profiled(gray, e, others, roi, spreads=spreads, strict=True,
                          half_width=e.half_width,
                          line=e.highlight if e.highlight is not None else False)
            if p is None:
                return None
            out[k].append(p)
    return _measurement(out[1], out[0], prev.mode, prev.rois)


@dataclass(frozen=True)
class TiltAverage:
    """The tilt of N frames of one view: their mean and its standard uncertainty.

    ``u_deg`` is the largest of the fits' own (sqrt of the mean per-frame variance over N),
    the frames' scatter (their standard deviation over sqrt N, from 3 frames on: a fit
    that understates its error shows up in the scatter of independent frames) and the
    fits' error clustered by row band across the frames (:func:`_u_blocks`: the part of a
    JPEG frame's coding error that the next frame repeats, which neither of the others
    sees). On libjpeg-coded frames the coding's bias, measured by simulation
    (:func:`_jpeg_bias`), is taken off ``tilt_deg`` and its simulation error added to
    ``u_deg`` in quadrature."""

    tilt_deg: float
    u_deg: float
    frames: tuple[SideMeasurement, ...]
    # JPEG frames: the libjpeg quality found and the coding's bias taken off the tilt (deg;
    # see :func:`_jpeg_bias`); None for frames not JPEG-coded
    jpeg_quality: int | None = None
    jpeg_bias_deg: float | None = None
    stop: str = ""  # why frame taking stopped, when it was driven by a target uncertainty

    @property
    def n(self) -> int:
        return len(self.frames)

    @property
    def scatter_deg(self) -> float:
        """Standard deviation of the per-frame tilts (NaN for fewer than two frames)."""
        t = [m.tilt_deg for m in self.frames]
        return float(np.std(t, ddof=1)) if len(t) > 1 else math.nan

    def to_json(self) -> dict[str, object]:
        first = self.frames[0].to_json()
        return {**first, "tilt_deg": self.tilt_deg, "sigma_deg": self.u_deg,
                "sample_angle_deg": float(np.mean([m.sample_angle_deg for m in self.frames])),
                "pole_angle_deg": float(np.mean([m.pole_angle_deg for m in self.frames])),
                "frames": self.n, "frame_tilts_deg": [m.tilt_deg for m in self.frames]}


def measure_tilt_frames(images: list[np.ndarray], *,
                        pole_roi_px: tuple[int, int, int, int] | None = None,
                        sample_roi_px: tuple[int, int, int, int] | None = None,
                        more: Callable[[int], list[np.ndarray]] | None = None,
                        u_target_deg: float | None = None, max_frames: int | None = None,
                        gamma: ToneCurve = 1.0) -> TiltAverage:
    """The tilt from several frames of the same view (the pre-check's measurement): the
    first frame is measured as :func:`measure_tilt` does, the others track its edges (a
    full search again where an edge is not where it was). From 3 frames on, 8-bit grey
    JPEG frames also have the coding's bias taken off (:class:`TiltAverage`).

    With ``more`` (k -> k further frames of the view) and ``u_target_deg``, frames are
    added while the uncertainty is above the target: as many again each time, up to
    ``max_frames`` in all. On JPEG-coded frames u falls slowly (the coding error a still
    view's frames share does not average away), yet the simulated coding bias taken off
    at the end is the truer the more frames it is simulated from, so they are not stopped
    early (docs/vision.md, "A wider window, and the stall rule's end").
    ``TiltAverage.stop`` says why it stopped. ``gamma``: the camera's tone curve
    (``cameras[].gamma``), undone before each raw frame is measured
    (:func:`alignd.vision.edges.linearise`); ``images`` and ``more``'s are the frames as
    the camera delivered them. JPEG-coded ones are measured
    as coded, the coding's bias taken off there: undoing the curve after the coding did
    worse than leaving it (docs/vision.md, "A camera's tone curve")."""
    if not images:
        raise VisionError("side image: no frame to measure the tilt in")
    images = list(images)
    first = measure_tilt(linearise(images[0], gamma), pole_roi_px=pole_roi_px,
                         sample_roi_px=sample_roi_px)
    # the frames' JPEG quality (None: not coded) for the bias step: measure_tilt read it on
    # the frame as it came, unless that frame was linearised first (a float frame)
    quality = ((first.coded_quality if is_linear(gamma) else _coded_quality(images[0], first))
               if len(images) >= 3 or more is not None else None)
    if quality is not None and not is_linear(gamma):
        gamma = 1.0
        first = measure_tilt(images[0], pole_roi_px=pole_roi_px, sample_roi_px=sample_roi_px)
    frames = [first]

    def track(new: list[np.ndarray]) -> None:
        for raw in new:
            img = linearise(raw, gamma)
            m = _tracked(img, first)
            frames.append(m if m is not None else measure_tilt(
                img, pole_roi_px=pole_roi_px, sample_roi_px=sample_roi_px))

    track(images[1:])
    stop = ""
    if more is not None and u_target_deg is not None:
        limit = max(max_frames or len(frames), len(frames))
        while True:
            u = _average_tilt(images, frames, None).u_deg
            if u <= u_target_deg:
                stop = f"u {u:.4f} <= {u_target_deg:g} deg"
                break
            if len(frames) >= limit:
                stop = f"{limit} frames, the most allowed"
                break
            new = more(min(len(frames), limit - len(frames)))
            if not new:
                stop = "no further frame"
                break
            images.extend(new)
            track(new)
    return replace(_average_tilt(images, frames, quality), stop=stop)


def _average_tilt(images: list[np.ndarray], frames: list[SideMeasurement],
                  quality: int | None) -> TiltAverage:
    """The mean tilt of ``frames`` (measured in ``images``) and its standard uncertainty
    (:class:`TiltAverage`), less the coding's bias for frames JPEG-coded at ``quality``
    (None: none taken off; a simulation of a second or so, so the frame taking leaves it
    for a final call)."""
    t = np.array([m.tilt_deg for m in frames])
    n = len(frames)
    u_fit = math.sqrt(float(np.mean([m.sigma_deg ** 2 for m in frames])) / n)
    u_scatter = float(np.std(t, ddof=1)) / math.sqrt(n) if n >= 3 else 0.0
    tilt, u = float(t.mean()), max(u_fit, u_scatter, _u_blocks(frames))
    found = _jpeg_bias(images, frames, quality) if n >= 3 and quality is not None else None
    if found is None:
        return TiltAverage(tilt, u, tuple(frames))
    quality, bias = found
    # the bias is taken off as far as it stands clear of its own simulation noise (a
    # shrinkage like edges._shrink's): at quality >= 90 it is mostly that noise
    g, se = bias.bias_deg, bias.u_deg
    taken = g * g * g / (g * g + (JPEG_BIAS_SE * se) ** 2 + 1e-30)
    return TiltAverage(tilt - taken, math.hypot(u, se), tuple(frames), quality, taken)


# the coding bias's shrinkage, in its standard errors: on the bench's 60 JPEG side views
# (regions, 8 frames) the pre-check's max / RMS error was 0.00442 / 0.00103 deg with the
# whole bias taken off, 0.00397 / 0.00095 at 1, 0.00346 / 0.00090 at 2, 0.00320 / 0.00093
# at 3 (0.00614 / 0.00166 without the correction)
JPEG_BIAS_SE = 2.0
JPEG_BIAS_DRAWS = 16  # simulated frames per edge


def _jpeg_bias(images: list[np.ndarray], frames: list[SideMeasurement], quality: int
               ) -> tuple[int, EdgeBias] | None:
    """The JPEG coding's bias on the mean tilt of ``frames`` (measured in ``images``,
    coded at libjpeg ``quality``: :func:`_coded_quality`) and that quality, or None when
    the frames are not 8-bit grey or an edge cannot be simulated.
    Each edge's bias is measured by coding its fit again
    (:func:`alignd.vision.jpeg_bias.edge_angle_bias`; seeded, so the same frames give the
    same tilt) and combined as :func:`_combine` weighs the edges."""
    if any(np.asarray(im).dtype != np.uint8 or np.asarray(im).ndim != 2 for im in images):
        return None
    first = frames[0]
    if not first.sample_edges or not first.pole_edges or any(
            len(m.sample_edges) != len(first.sample_edges)
            or len(m.pole_edges) != len(first.pole_edges) for m in frames):
        return None
    grays = [np.asarray(im) for im in images]
    h, w = grays[0].shape
    rng = np.random.default_rng(0)
    pole_roi, sample_roi = first.rois
    total, var = 0.0, 0.0
    for kind, sign, roi in (("sample", 1.0, sample_roi), ("pole", -1.0, pole_roi)):
        edges = first.sample_edges if kind == "sample" else first.pole_edges
        wts = np.array([1.0 / max(e.sigma_deg, 1e-6) ** 2 for e in edges])
        for k, (wk, e) in enumerate(zip(wts / wts.sum(), edges, strict=True)):
            if e.spread is None or e.half_width is None or e.blur_px is None:
                return None
            seen = [(m.sample_edges if kind == "sample" else m.pole_edges)[k] for m in frames]
            y_mid = (e.rows[0] + e.rows[1]) / 2
            a = float(np.mean([x.line.minor_at(y_mid) for x in seen]))
            b = -float(np.mean([x.line.n[1] / x.line.n[0] for x in seen]))
            rx0, ry0, rx1, ry1 = roi if roi is not None else (0, 0, w, h)
            rows = np.arange(max(e.rows[0] + 10, int(ry0) + 4),
                             min(e.rows[1] - 10, int(ry1) - 5) + 1)
            if rows.size < 40:
                return None
            # the frames' mean blur: the simulation draws the edge to match it
            blur = float(np.mean([x.blur_px or e.blur_px for x in seen]))
            got = edge_angle_bias(grays, quality, a, b, y_mid, rows, blur, e.spread,
                                  e.half_width, (max(int(rx0), 0), min(int(rx1), w)), rng,
                                  draws=JPEG_BIAS_DRAWS)
            if got is None:
                return None
            total += sign * float(wk) * got.bias_deg
            var += (float(wk) * got.u_deg) ** 2
    return quality, EdgeBias(total, math.sqrt(var))


def _coded_quality(image: np.ndarray, m: SideMeasurement) -> int | None:
    """The libjpeg quality ``image`` was coded at, read in a block-aligned crop around the
    sample edge ``m`` found (:func:`alignd.vision.jpeg_bias.jpeg_quality`); None for an
    image that is not 8-bit grey or not JPEG-coded."""
    return _coded_near(image, m.sample_edges[0]) if m.sample_edges else None


def _coded_near(image: np.ndarray, e0: SideEdge) -> int | None:
    """:func:`_coded_quality`, read around the edge ``e0``."""
    gray = np.asarray(image)
    if gray.dtype != np.uint8 or gray.ndim != 2:
        return None
    x0 = max(int(e0.x_mid_px) - 32, 0) // 8 * 8
    y0 = max(e0.rows[0], 0) // 8 * 8  # the crop on the block grid
    return jpeg_quality(gray[y0:min(e0.rows[1] + 1, gray.shape[0]), x0:x0 + 64])


def _band_terms(edges: tuple[SideEdge, ...], sign: float) -> dict[int, float] | None:
    """The weighted mean angle's error terms per row band (as :func:`_combine` weighs
    the edges), times ``sign``; None when an edge has none (not profile-fitted)."""
    w = np.array([1.0 / max(e.sigma_deg, 1e-6) ** 2 for e in edges])
    out: dict[int, float] = {}
    for wi, e in zip(w / w.sum(), edges, strict=True):
        if e.bands is None or e.band_angle_deg is None:
            return None
        for g, v in zip(e.bands.tolist(), e.band_angle_deg.tolist(), strict=True):
            out[g] = out.get(g, 0.0) + sign * float(wi) * v
    return out


# bands of 1 and 4 block rows: a near-vertical edge crosses the block columns slowly, so its
# coding error is correlated over several block rows, not only within one. On the bench's
# 60 JPEG side scenes (8 frames each, regions) the pre-check's RMS |error| / u was 1.72
# with the frames' bands independent, 1.32 with 8-row bands shared across frames, 1.17
# with 32-row ones, 1.19 with 64-row ones
BAND_MERGE = (1, 4)


def _u_blocks(frames: list[SideMeasurement]) -> float:
    """The mean tilt's uncertainty with each band of rows of all frames as one unit.

    JPEG/MJPEG codes the same scene on the same 8 x 8 block grid in every frame, so part
    of a block's coding error repeats from frame to frame and does not average away: the
    per-band error terms of the frames are summed before squaring (a sandwich clustered
    over frames as well as rows), for bands of each size in :data:`BAND_MERGE` block rows;
    the largest. Where the frames' errors are independent this is about the fits' own
    error over sqrt N; where they repeat it does not shrink with N. 0 when an edge lacks
    the terms."""
    out = 0.0
    for k in BAND_MERGE:
        total: dict[int, float] = {}
        for m in frames:
            for d in (_band_terms(m.sample_edges, 1.0), _band_terms(m.pole_edges, -1.0)):
                if d is None:
                    return 0.0
                for g, v in d.items():
                    total[g // k] = total.get(g // k, 0.0) + v / len(frames)
        out = max(out, math.sqrt(sum(v * v for v in total.values())))
    return out


def baseline_tilt(image: np.ndarray, pole_x_px: float, sample_x_px: float, *,
                  theta_step_deg: float = 0.01, window_px: float = 40.0
                  ) -> tuple[float, float, float]:
    """The thesis' method: Canny + Hough; the strongest line near each x gives its angle.

    Returns (sample_angle_deg, pole_angle_deg, tilt_deg); NaN where no line was found.
    """
    gray = as_gray(image, "side image")
    h = gray.shape[0]
    lines = _hough_vertical(gray, theta_step_deg, 3.0, h // 4)

    def pick(x: float) -> float:
        near = [ln for ln in lines if abs(ln[1] - x) < window_px]
        return min(near, key=lambda ln: ln[2])[0] if near else math.nan

    s, p = pick(sample_x_px), pick(pole_x_px)
    return s, p, s - p
