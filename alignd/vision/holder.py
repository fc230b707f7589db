"""Sample-holder tracking in the top camera: corners and pose per frame, sub-pixel.

Coarse: the holder is the most rectangular blob (either polarity) over a ladder of
thresholds (Otsu's and fixed steps, so shadows and extra grey levels cannot hide it) of a
4x-downsampled frame, kept only where the threshold cuts its edge near half height; the
strongest step within +-10 px of each side of that box then gives each side to a few tenths
of a pixel. Fine: each side is measured in every pixel column (or row) it crosses with the
area method of :mod:`alignd.vision.edges` and fitted as a line; the candidate that passes
every check then has each side's crossings refined by fitting the pixel-exact model of a
blurred step (:mod:`alignd.vision.profile_fit`, about half the area method's noise); the
corners are the intersections of adjacent sides, so every corner uses some hundred
columns instead of the few pixels around it (the thesis' detector had 0.3 px noise). The
quadrilateral is not forced to be a rectangle, so a tilted camera's perspective is followed;
where the four sides' directions agree with a rectangle's within their noise, they share
one (:mod:`alignd.vision.holder_square`: a corner's error is mostly its sides' directions).

Corners come ordered by their angle around the centre, starting from the image's -x
direction and turning toward -y (on screen: top-left, top-right, bottom-right, bottom-left
for an upright holder). That order is stable while the holder's image turns by less than
the angle between its diagonal and its long side (34 deg for 60 x 40 mm), so it holds over a
+-10 deg sweep; with ``hint`` (the previous frame's corners) it is kept by nearest match.

A detection that fails a check (too few edge columns, poor line fit, low contrast, wrong
size, not convex) is returned with ``ok`` False and NaN for the affected corners: never a
wrong point. A side found between the two steps of a narrow band beside it (a hard
shadow's) is moved in to the inner one, the holder's edge
(:mod:`alignd.vision.holder_bands`). A blank, saturated or target-free image raises VisionError.
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Literal, NamedTuple

import cv2
import numpy as np
from scipy.special import ndtri

from alignd.errors import VisionError
from alignd.vision.edges import (
    ColumnJudging,
    EdgePoints,
    Line,
    as_gray,
    check_usable,
    coarse_edges_many,
    column_judging,
    despeckle,
    edge_points,
    edge_points_many,
    fit_line,
    intersect,
    residual_correlation,
)
from alignd.vision.holder_bands import REACH as BAND_REACH
from alignd.vision.holder_bands import SideProfiles, read_sides, side_bands
from alignd.vision.holder_neighbours import REACH as NEIGHBOUR_REACH
from alignd.vision.holder_neighbours import neighbour_steps, without_neighbours
from alignd.vision.holder_search import (
    FrameVotes,
    search_candidates,
    voted_by_voters,
    voted_either_way,
)
from alignd.vision.holder_square import parallel_to, square_sides
from alignd.vision.holder_steps import FAR_PX, InnerStep, inner_step, side_frame
from alignd.vision.lens import Lens
from alignd.vision.profile_fit import fit_profiles

__all__ = ["HolderDetection", "YawMeasurement", "measure_yaw", "order_corners", "track_holder"]

log = logging.getLogger(__name__)

# a whole side's common-mode error (px, normal to it), on top of its fit's covariance:
# calibrated on the randomised corpus so that corner errors over corner_sigma_px have an
# RMS near 1 (see tests/test_vision_holder_sigma.py)
_SIDE_COMMON_PX = 0.02
_AGREE_PX, _AGREE_SIGMA = 0.05, 3.0  # profile vs area corners: allowed difference
# ... and where they differ more, this share of the difference counts in the corners'
# uncertainty; the refined corners are returned only where the two lie within
# _REFINED_APART_PX (the area method's own errors on the corpora reach 0.7 px; farther
# apart, one of them is on another edge: beside an 8 px sample strip along a side on the
# pixel columns the two lay 1.0-2.2 px apart, the refined corners as far off; see _finish)
_DISAGREE_SHARE = 0.5
_REFINED_APART_PX = 0.9
# a strip wider than inner_step looks along a side (_wide_strip): that side's length within
# this share of one expected size, the step looked for this far beyond the depth the other
# puts the holder's side at, and found within this share of that depth
_WIDE_STRIP_FIT, _WIDE_STRIP_BEYOND_PX, _WIDE_STRIP_SLACK = 0.05, 8.0, 0.15
# a side blurred more than this (Gaussian width, px) reaches the tails of the area method's
# +-5 px window: refined corners it rejects are checked once more against its +-9 px ones
# (1.0 and 1.2 alike on the corpus)
_SOFT_BLUR_PX = 1.0
# where a side's edge pixels are clipped (at the sensor's full scale or at zero) in more
# than this share of its columns, the area method reads the clip as the level and errs
# toward the unclipped side (see _clip_offset), while the profile fit leaves the clipped
# pixels out: the agreement test allows for that offset there
_CLIP_SHARE = 0.2
# ... and by at least this much (px): a level within a few noise sigma of full scale has
# its noise clipped, which lowers the tails' mean (corpus #751 of the bench's seed: a
# holder at about full scale, area corners 0.3 px off where the step's clip explains 0.1)
_CLIP_AGREE_PX = 0.3
# a side clipped in more than this share of its crossings counts toward clip_warning
_SATURATED_SHARE = 0.5
# a detection the edge profiles disagreed with, kept on the area method's corners, is
# refused when those are uncertain beyond this (px; see _finish)
_AREA_ALONE_SIGMA_PX = 0.3
# ... or when one side's line fits this many times worse than the four sides' median (its
# windows hold a second step: see _rough_side)
_ROUGH_SIDE_RATIO = 3.0
# a side's edge must run through at least this share of the columns (rows) its length calls
# for, and 10 of them: a floor hole as dark as the holder can hide over half of a short
# side (corpus breadboards at 640 x 480: 0.5 refused three right holders, 0.3 no wrong one)
_MIN_SIDE_SHARE = 0.3
# a side with stray columns (runs of fewer than _RUN_COLUMNS between gaps over _RUN_GAP_PX)
# whose other columns span less than this share of that length shows beside one of its
# ends only: where its direction disagrees with the opposite side's, it takes that one
# (holder_square.parallel_to; corpus sweeps: a floor hole hid 33 of a 68 px side's 48
# columns, the 15 left lay within 13 px but for one stray column by the hole, which set
# the side's direction, and its far corner was 1.5 px off, 7 of its sigma)
_MIN_SIDE_SPAN = 0.5
_RUN_COLUMNS, _RUN_GAP_PX = 5, 3.0
# candidates refused only for a side's crossings scattering over max_rms_px, by up to this
# factor, are refined once more with that much allowed, after every candidate has failed:
# a soft, low-contrast side on a textured floor scatters 0.6-0.8 px and is the holder's
# (allowed at once, it also took rougher sides of holders found right before)
_SECOND_RMS_FACTOR = 4.0 / 3.0
# opposite sides whose fitted edge widths differ by more than this (px) and this factor
# cannot be one flat face's (see _unlike_opposite_blurs)
_BLUR_UNLIKE_PX, _BLUR_UNLIKE_RATIO = 1.2, 3.0
# opposite sides fitted more than this far apart in width (px) are fitted again with the
# sharper one's width, where that is a blur of at least _BLUR_ALIKE_MIN_PX (a sharp
# edge's width, near the pixel's own footprint, is ill-determined: a faint holder's
# sides, 13 DN steps, read 0.15-1.1 px at a blur of about 0.6; see _alike_opposite_blurs)
_BLUR_ALIKE_PX = 0.4
_BLUR_ALIKE_MIN_PX = 1.0
# tracking with a lens: the fine windows lie on the chord between a side's corners, which
# a distorted side bows away from; up to this far in its middle (px) they still catch it
# as the coarse search's best-fit line would (corpus lens frames: 90 % bow under 0.7 px;
# #111 of seed 2124, 1.6 px, misfitted on the chord and fell back to the area method)
_SEED_SAGITTA_PX = 1.0
_RESEED_PX = 3.0  # a tracked holder that moved more than this is located again (see _refine)
# tracking despeckles the frame this far around the previous corners: the side search's 10
# px, the edge windows and the profiles read beside a side (21.5 px in, 14 out) within it
_SPECK_MARGIN_PX = 40
# area corners this far (px) from the corners their windows were placed from: the windows
# were misplaced, and a refined fit they disagree with is checked against them placed again
_MISPLACED_PX = 1.0
_HALF_WIDTH = 5  # the fine edge window: +-5 px (+-9 px for soft edges)
_WIDE = 9
# the area method's windows stop this far (px along a side) short of the corners, where the
# neighbouring side's transition would enter them (in the wide windows, further)
_MARGIN, _WIDE_MARGIN = 10.0, 12.0
_NEIGHBOURS_PASSES, _NEIGHBOURS_SETTLED_PX = 3, 0.05  # see _off_the_neighbours
_NEIGHBOURS_NEAR_PX = 0.3  # ... and its first pass
_NO_EDGE_SIDES = 2  # a refused candidate with this many sides bare of edges: not looked again
# a side whose crossings stop more than _WIDE_MARGIN plus this (px, or this share of the
# side, the larger) short of both its corners is not the holder's (see _bare_ends)
_BARE_END_PX, _BARE_END_SHARE = 8.0, 0.1
_BARE_PROBE_PX = 6.0  # ... unless the image steps there as the side does, this far across it
_ONE_BARE_SHARE = 0.3  # ... or short of one corner by this share of the side (and _WIDE_MARGIN)
# a side whose crossings bend away from its line smoothly (a cubic along it) by more than this
# (px rms), _BENT_RATIO times as much as the other sides' median, is not an edge of the
# holder: a cable's edge cutting a larger rectangle to the holder's size (unseen corpora,
# seeds 41100 #498 and 111100 #993: 0.43 and 0.24 px, returned 570 and 298 px wrong; 31100
# #676, a grain's dark patch along a side, 0.37 px, 1.15 px wrong). Over 13 corpora three
# right holders bent so, each in a JPEG frame (a near-axis side drifting across the
# coding's blocks); a lens not modelled bends every side alike (see _bent_side)
_BENT_PX, _BENT_RATIO = 0.18, 6.0
_BENT_MIN_POINTS, _BENT_MIN_SPAN = 24, 1.0 / 3.0  # ... judged on enough of the side
_BENT_F = 20.0  # ... and where the bend stands out of the noise (see _bent_side)
# opposite sides further than this from parallel (deg, in the ideal image): more than a
# camera that passes the rim pre-check (tilt under 3 deg) makes of a holder (under 1 deg
# for one a fifth of the field wide); a side on another edge at a slant is looked for
# within (see _not_askew)
_MAX_SKEW_DEG = 2.0
_LADDER_TRIES = 3  # the threshold ladder's boxes tried beyond max_candidates (track_holder)
# a full search that found no holder of the expected size looks once more with this as its
# min_contrast (DN): a holder whose sides step less than 15 DN along part of them (12-18 DN
# off its disc under uneven light). Not the first search's: there it let noisier columns
# into a side that was found at 15 (a side over a floor hole, rms 0.76 px)
FAINT_CONTRAST = 10.0
# ... and keeps what it finds only where the sides' median step is under this many times
# the first search's min_contrast (20 DN): a faint holder (13-18 DN beside a sample's
# 60 DN side: 13-19 DN), not a box the first search refused for something else (a label's
# edges with one of the holder's sides, looked for at 0.75 of its size: 53 DN)
FAINT_STEP_RATIO = 4.0 / 3.0


@dataclass(frozen=True)
class HolderDetection:
    """Holder corners (4, 2) px in a consistent order, pose and quality of one frame."""

    ok: bool
    corners_px: np.ndarray
    center_px: np.ndarray
    angle_deg: float
    quality: float  # 0..1, 1 = every column used, corners well determined
    # estimated standard error of a corner: the line fits' (inflated for residuals that
    # correlate along a side) plus each side's common-mode error
    corner_sigma_px: float
    polarity: str  # "dark": holder darker than its surroundings, or "light"
    size_px: tuple[float, float]  # mean length of sides 0-1/3-2 and 1-2/0-3
    corner_ok: np.ndarray = field(default_factory=lambda: np.zeros(4, bool))
    edge_rms_px: tuple[float, ...] = ()
    reason: str = ""
    # the line fits' own standard error of a corner (independent columns, no common-mode
    # term): the scale the area and profile methods' corners are compared on
    fit_sigma_px: float = math.nan
    lines: tuple[Line | None, ...] = ()
    # each side's Gaussian edge width (px) found by the profile fit, side k running from
    # corner k to corner k + 1; () when the profile fit was not used
    side_blur_px: tuple[float, ...] = ()
    # sides whose edge pixels clip (full scale or zero) in over _SATURATED_SHARE of their
    # columns: at 4 the face's true level is nowhere visible (see clip_warning)
    clipped_sides: int = 0
    # sides found between two steps (a hard shadow's band beside them) and moved in to the
    # inner one, the holder's edge (:func:`_off_the_bands`)
    banded_sides: int = 0
    # of those, sides at a cast shadow's soft edge (no band: :func:`_finish` may still
    # look for a step beside them)
    tail_sides: int = 0
    # sides with a second step a few px beside them, measured again on an image without it
    # (:mod:`alignd.vision.holder_neighbours`)
    neighbour_sides: int = 0
    # found only by the second, fainter search (:data:`FAINT_CONTRAST`), or tracked from
    # such a detection: its sides step less than the min_contrast asked for
    faint: bool = False
    # whether the profile fit modelled a cast shadow's penumbra beside a side
    # (:func:`alignd.vision.profile_fit.fit_profiles`); tracking looks for one again only
    # then, or where a side moved
    penumbra: bool = False

    @property
    def warning(self) -> str:
        """What the operator should know about a holder found (clipped edges, a faint
        holder); "" if nothing."""
        return "; ".join(w for w in (self.clip_warning, self.faint_warning) if w)

    @property
    def faint_warning(self) -> str:
        """Why a holder found only at :data:`FAINT_CONTRAST` is worth raising the
        contrast of: its corners are noisier, and a few DN less and it is not found."""
        if not (self.ok and self.faint):
            return ""
        median = _median_step(self)
        step = f" (their median step is about {median:.0f} DN)" if math.isfinite(median) else ""
        return ("the holder was found only by a second search at a lower contrast: its "
                f"sides step less than 15 DN against what surrounds them, along part of them "
                f"at least{step}; its corners are noisier, and a few DN less would lose it: "
                "make it darker or lighter than the disc (20 DN or more), or light it more "
                "(docs/configure.md, the holder frame)")

    @property
    def clip_warning(self) -> str:
        """What to tell the operator about a holder whose edges clip along every side; ""
        if not. How far beyond the clip the level lies cannot be seen, and a step twice
        the visible one or more moves the corners by 0.5-1.8 px while corner_sigma_px
        stays 0.05-0.1 (docs/vision.md, clipped edges)."""
        if self.clipped_sides < 4:
            return ""
        return ("the holder's edges clip along all four sides (its face or what surrounds "
                "it reads full scale or zero), so its corners may be off by up to about 2 px, "
                "more than corner_sigma_px says; lower the exposure or the light until "
                "neither reaches full scale")

    def to_json(self) -> dict[str, object]:
        """The analyze contract's fields (NaN corners become null)."""
        def pt(p: np.ndarray) -> list[float] | None:
            return [float(p[0]), float(p[1])] if np.all(np.isfinite(p)) else None
        return {"ok": self.ok, "corners_px": [pt(c) for c in self.corners_px],
                "pose": {"center_px": pt(self.center_px),
                         "angle_deg": self.angle_deg if math.isfinite(self.angle_deg) else None},
                "quality": round(self.quality, 4),
                "corner_sigma_px": (round(self.corner_sigma_px, 5)
                                    if math.isfinite(self.corner_sigma_px) else None),
                "polarity": self.polarity, "size_px": list(self.size_px),
                **({"reason": self.reason} if self.reason else {}),
                **({"warning": self.warning} if self.warning else {})}


def order_corners(corners: np.ndarray, hint: np.ndarray | None = None) -> np.ndarray:
    """Sort 4 corners by angle around their centre from -x (screen: TL, TR, BR, BL);
    with ``hint`` choose the cyclic order closest to it."""
    c = np.asarray(corners, float)
    ctr = c.sum(axis=0) / len(c)  # (the mean, without np.mean's overhead)
    ang = np.arctan2(c[:, 1] - ctr[1], c[:, 0] - ctr[0])
    c = c[np.argsort(ang)]
    if hint is not None:
        h = np.asarray(hint, float)
        if h.shape == (4, 2) and np.all(np.isfinite(h)):
            rolled = c[_ROLLS]  # (4 shifts, 4, 2): every cyclic order at once
            costs = np.sqrt(((rolled - h[None]) ** 2).sum(axis=2)).sum(axis=1)
            c = rolled[int(np.argmin(costs))]
    return c


_ROLLS = (np.arange(4)[None, :] + np.arange(4)[:, None]) % 4  # row k: np.roll(c, -k)
_NEXT = _ROLLS[1]  # c[_NEXT]: each corner's successor (np.roll(c, -1, axis=0))


def _side_lengths(c: np.ndarray) -> np.ndarray:
    """The length of each side k (corner k to k + 1) of a quadrilateral."""
    d = c[_NEXT] - c
    return np.sqrt((d * d).sum(axis=1))


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _quad_center(c: np.ndarray) -> np.ndarray:
    p, r = c[0], c[2] - c[0]
    q, s = c[1], c[3] - c[1]
    den = _cross(r, s)
    if abs(den) < 1e-12:
        return c.mean(axis=0)
    return p + _cross(q - p, s) / den * r


def _quad_angle(c: np.ndarray) -> float:
    a, b = c[1] - c[0], c[2] - c[3]
    v = a / math.hypot(a[0], a[1]) + b / math.hypot(b[0], b[1])
    return math.degrees(math.atan2(v[1], v[0]))


def _fit_sides(gray: np.ndarray, corners: np.ndarray, half_width: int, margin: float,
               min_contrast: float, lens: Lens | None = None
               ) -> list[tuple[Line | None, EdgePoints]]:
    """Each side's area-method crossings (frame pixels) and the line through them (in the
    ideal image when there is a lens)."""
    found = edge_points_many(gray, [(corners[i], corners[(i + 1) % 4]) for i in range(4)],
                             half_width=half_width, margin_px=margin, min_contrast=min_contrast)
    return [(fit_line(_ideal(pts, lens)), pts) for pts in found]


# the last few crossings undistorted, by identity: each check of a frame's sides reads
# them in the ideal image (with a lens, about 30 undistortions of 8 sets of crossings a
# tracked frame, 18 % of a lens frame's time). EdgePoints are frozen, and an entry holds
# its own, so no other takes its id while it is remembered
_IDEAL: OrderedDict[int, tuple[EdgePoints, Lens, EdgePoints]] = OrderedDict()
_IDEAL_KEPT = 16


def _ideal(pts: EdgePoints, lens: Lens | None) -> EdgePoints:
    """``pts`` in the ideal (undistorted) image."""
    if lens is None or lens.k1 == 0.0 or pts.xy.shape[0] == 0:
        return pts
    seen = _IDEAL.get(id(pts))
    if seen is not None and seen[0] is pts and seen[1] == lens:
        return seen[2]
    out = EdgePoints(lens.undistort(pts.xy), pts.contrast, pts.vertical)
    _IDEAL[id(pts)] = (pts, lens, out)
    while len(_IDEAL) > _IDEAL_KEPT:
        _IDEAL.popitem(last=False)
    return out


def _profile_sides(gray: np.ndarray, sides: list[tuple[Line | None, EdgePoints]],
                   half_width: int, margin: float, lens: Lens | None = None,
                   blur: np.ndarray | None = None, penumbra: bool = True
                   ) -> tuple[list[tuple[Line | None, EdgePoints]], np.ndarray, float, bool]:
    """The area method's crossings (``margin`` px short of the corners) refined by the
    profile fit, which reaches nearer the corners, their lines, each side's blur
    (``blur``: known widths, see :func:`fit_profiles`), how far the area method's
    corners may lie from them for a penumbra beside a side (the profile fit models it,
    the area method does not: a corner moves with both of its sides, sqrt(2) times the
    largest side's move) and whether a penumbra was modelled (``penumbra``: looked for)."""
    fit = fit_profiles(gray, [pts for _ln, pts in sides], half_width=half_width, blur=blur,
                       corner_gap_px=margin, penumbra=penumbra)
    bent = math.sqrt(2.0) * float(np.max(np.abs(fit.bend_px), initial=0.0))
    ideal = [_ideal(f, lens) for f in fit.edges]
    # (sides whose directions agree with a rectangle's share it: holder_square)
    lines = square_sides([fit_line(p) for p in ideal], ideal)
    return list(zip(lines, fit.edges, strict=True)), fit.widths, bent, fit.penumbra


class _Prior(NamedTuple):
    """What tracking reuses of the previous detection where its sides held."""

    corners: np.ndarray
    blur: np.ndarray  # each side's blur width (px)
    banded: bool  # a side lay between two steps
    penumbra: bool  # a penumbra lay beside a side


def _side_match(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """For each side of quadrilateral ``dst`` (corner k to k + 1), the index of the side
    of ``src`` nearest to it (by their midpoints): the same side in another order."""
    ms = (src + src[_NEXT]) / 2
    md = (dst + dst[_NEXT]) / 2
    return np.argmin(((md[:, None, :] - ms[None, :, :]) ** 2).sum(axis=2), axis=1)


def track_holder(image: np.ndarray, expected_size_px: tuple[float, float] | None = None,
                 hint: np.ndarray | HolderDetection | None = None, *, polarity: str | None = None,
                 min_contrast: float = 15.0, max_rms_px: float = 0.6,
                 passes: int = 1, lens: Lens | None = None,
                 size_tolerance: float = 0.12, max_candidates: int = 6,
                 refine: Literal["profile", "area"] = "profile") -> HolderDetection:
    """Find the holder's top face in a top-camera frame.

    ``expected_size_px`` (long, short side in px; from the config's holder size and pixel
    size) makes the search look for that size (centre voting, see
    :func:`alignd.vision.holder_search.search_candidates`)
    and rejects any result more than ``size_tolerance`` off; ``hint`` (previous corners)
    seeds tracking, keeps the corner order and falls back to a full search when the holder
    is not there; given as the previous frame's detection, its sides' blur widths are
    reused where every side moved by less than a pixel (the blur estimate is a third of
    the profile fit's cost; a side that moved, or a full search, measures it anew);
    ``polarity`` ("dark"/"light") restricts the search; ``lens`` (focal
    length, principal point, k1) straightens distorted sides (corners stay in frame
    pixels; the angle and the size are those of the undistorted image). ``refine``:
    "profile" refines the accepted sides by the profile fit of
    :mod:`alignd.vision.profile_fit` (about half the corner noise, about 5 ms more a
    frame), "area" keeps the area method's crossings (the faster, noisier). Where a full
    search with an expected size finds nothing, it searches once more at
    :data:`FAINT_CONTRAST`, for a holder whose sides step less than ``min_contrast`` along
    part of them, and keeps only such a faint one (``faint``). Raises VisionError when
    the image is unusable or holds no candidate; returns ``ok`` False, with the reason,
    when no candidate passes the checks.
    """
    raw = np.asarray(image)
    # tracking reads a few thousand pixels: an 8-bit frame is used as it is (no copy)
    gray = raw if raw.ndim == 2 and raw.dtype == np.uint8 and min(raw.shape) >= 16 else \
        as_gray(image, "top image")
    # what the previous detection found, reused where its sides held
    prior: _Prior | None = None
    # whether to look for a second step beside the sides: a plate or a floor step is rigid
    # with the holder or the rig, so a tracked frame looks only where the previous one
    # found one (3-4 ms a frame otherwise)
    neighbours = True
    # a holder found faint is tracked at the contrast it was found at
    track_contrast = min_contrast
    if isinstance(hint, HolderDetection):
        hint_arr: np.ndarray | None = np.asarray(hint.corners_px, float)
        if hint.faint:
            track_contrast = min(min_contrast, FAINT_CONTRAST)
        neighbours = bool(hint.neighbour_sides)
        if len(hint.side_blur_px) == 4 and np.all(np.isfinite(hint.side_blur_px)):
            prior = _Prior(np.asarray(hint.corners_px, float), np.asarray(hint.side_blur_px),
                           bool(hint.banded_sides), hint.penumbra)
    else:
        hint_arr = None if hint is None else np.asarray(hint, float)
    reasons: list[str] = []
    full = gray  # the frame before its specks go (the full search despeckles all of it)
    if hint_arr is not None and hint_arr.shape == (4, 2) and np.all(np.isfinite(hint_arr)):
        # hot and dead pixels (edges.despeckle; a copy only where there are any), around
        # the previous corners: what tracking reads
        lo, hi = np.floor(hint_arr.min(axis=0)), np.ceil(hint_arr.max(axis=0))
        gray = despeckle(gray, (int(lo[0]) - _SPECK_MARGIN_PX, int(lo[1]) - _SPECK_MARGIN_PX,
                                int(hi[0]) + _SPECK_MARGIN_PX, int(hi[1]) + _SPECK_MARGIN_PX))
        # tracking: the previous corners seed the fine windows (or, when the sides moved,
        # the +-10 px side search); if the holder is not there any more, fall back to a
        # full search
        try:
            seed = order_corners(hint_arr)
            det = _refine(gray, seed, polarity, expected_size_px, hint_arr, track_contrast,
                          max_rms_px, passes, lens, size_tolerance, refine == "profile",
                          seeded=True, prior=prior, neighbours=neighbours)
            if det.ok and (prior is None or _shift(order_corners(det.corners_px, prior.corners),
                                                    prior.corners) > 1.0):
                # (a holder within a pixel of the previous detection's corners has its
                # sides on the same edges, which that detection's check cleared)
                det = _looked_again(gray, det, polarity, expected_size_px, hint_arr,
                                    track_contrast, max_rms_px, passes, lens, size_tolerance,
                                    refine == "profile")
            if det.ok:
                return replace(det, faint=True) if track_contrast < min_contrast else det
            reasons.append(f"at the previous corners: {det.reason}")
        except VisionError as exc:
            reasons.append(f"at the previous corners: {exc}")
    # (a frame the previous corners fit is usable; only a full search needs the check)
    gray = despeckle(full)
    if gray.dtype == np.uint8:  # the 8-bit frame (or its despeckled copy): the search
        gray = as_gray(gray, "top image")  # wants floats (any other was converted above)
    check_usable(gray, min_contrast, "top image")
    search = partial(_full_search, gray, expected_size_px, hint_arr, polarity, max_rms_px,
                     passes, lens, size_tolerance, max_candidates, refine == "profile")
    # a holder of its size too faint for the first search (a grey holder on a grey disc,
    # under 15 DN along part of its sides): once more at a lower contrast, only where the
    # first found nothing, so that what it finds is never changed
    second = expected_size_px is not None and min_contrast > FAINT_CONTRAST
    first: VisionError | None = None
    try:
        det = search(min_contrast, reasons)
        if det.ok or not second:
            return det
    except VisionError as exc:
        if not second:
            raise
        first = exc
    try:
        faint: HolderDetection | None = search(FAINT_CONTRAST, [])
    except VisionError:
        faint = None
    if faint is not None and faint.ok:
        step = _median_step(faint)
        if step < FAINT_STEP_RATIO * min_contrast:
            log.info("top image: the holder found only at a contrast of %g DN (its sides "
                     "step %.0f DN)", FAINT_CONTRAST, step)
            return replace(faint, faint=True)
        # a box whose sides step as much as the first search asks was refused there for
        # something else (a label's edges with a side of the holder, where the holder is
        # not of the size looked for); that refusal stands
        log.info("top image: the second search's box at (%.0f, %.0f) steps %.0f DN, not "
                 "faint: refused as the first search refused it", *faint.center_px, step)
    if first is not None:
        raise first
    return det


def _full_search(gray: np.ndarray, expected_size_px: tuple[float, float] | None,
                 hint_arr: np.ndarray | None, polarity: str | None, max_rms_px: float,
                 passes: int, lens: Lens | None, size_tolerance: float, max_candidates: int,
                 profile: bool, min_contrast: float, reasons: list[str]) -> HolderDetection:
    """The search of a whole frame (:func:`track_holder` without a hint, or where the
    hint failed): the candidates refined in turn, the first that passes returned; else
    not ok with every candidate's reason (appended to ``reasons``), or VisionError where
    there was no candidate at all."""
    tried: list[np.ndarray] = []  # the boxes refined, their corners ordered
    rough: list[np.ndarray] = []  # boxes refused for a side's scatter alone (second pass)
    last: HolderDetection | None = None
    # the frame's centre voting, its edge map and peaks shared by the votes again below
    votes = None if expected_size_px is None else FrameVotes(gray, expected_size_px,
                                                             min_contrast, size_tolerance)

    # whether a side of a box measured lost most of its columns to their neighbours' mean
    # contrast: only then can the last try below (by their median) measure anything else
    watch = ColumnJudging()

    def measure(box: np.ndarray, rms_px: float, judging: ColumnJudging = watch
                ) -> HolderDetection:
        """``box`` refined and checked (VisionError where its sides cannot be located)."""
        with column_judging(judging):
            det = _refine(gray, order_corners(box), polarity, expected_size_px, hint_arr,
                          min_contrast, rms_px, passes, lens, size_tolerance, profile)
            return _looked_again(gray, det, polarity, expected_size_px, hint_arr,
                                 min_contrast, rms_px, passes, lens, size_tolerance, profile)

    def later() -> Iterator[tuple[np.ndarray, float]]:
        """Once every box has failed: the rough ones allowing more scatter, then the boxes
        voted again with their peaks' own directions, then with sides paired whichever way
        they contrast, those not refined yet."""
        yield from ((box, max_rms_px * _SECOND_RMS_FACTOR) for box in rough)
        if votes is None:
            return
        seen = list(tried)
        if tried:
            for box in voted_by_voters(votes, max_candidates):
                if not any(_shift(order_corners(box, b), b) < 8.0 for b in tried):
                    seen.append(order_corners(box))
                    yield box, max_rms_px
        for box in voted_either_way(votes, max_candidates):
            if not any(_shift(order_corners(box, b), b) < 8.0 for b in seen):
                seen.append(order_corners(box))
                yield box, max_rms_px

    # the voted boxes take at most max_candidates tries, and the threshold ladder's, which
    # follow, a few more: where the holder's two sizes pair at different scales (a plate
    # beside one side, 5 % of the holder), its sides vote along one midline only, every
    # voted box lies somewhere along it, and the ladder's outline is the one there is
    for box in search_candidates(gray, votes, expected_size_px, polarity,
                                 max_voted=max_candidates):
        ctr = box.mean(axis=0)
        if any(np.linalg.norm(ctr - t.mean(axis=0)) < 8.0 for t in tried):
            continue
        if len(tried) >= max_candidates + _LADDER_TRIES:
            break
        tried.append(order_corners(box))
        try:
            det = measure(box, max_rms_px)
        except VisionError as exc:
            reasons.append(f"candidate at ({ctr[0]:.0f}, {ctr[1]:.0f}): {exc}")
            continue
        if det.ok:
            return det
        reasons.append(f"candidate at ({ctr[0]:.0f}, {ctr[1]:.0f}): {det.reason}")
        last = det
        if _only_rough(det, max_rms_px):
            rough.append(box)
    for box, rms_px in later():
        try:
            det = measure(box, rms_px)
        except VisionError:
            continue
        if det.ok:
            return det
    # last, the boxes refined once more with each side's columns judged against their
    # neighbours' median (a side passing a floor hole lost its stronger columns with the
    # hole's: edges.ColumnJudging; only here, where every box failed, and only where a
    # side of one lost so many: elsewhere the median judges as the mean did)
    if watch.lost_seen:
        by_median = ColumnJudging(watch.lost_share, by_median=True)
        for box in tried:
            try:
                det = measure(box, max_rms_px, by_median)
            except VisionError:
                continue
            if det.ok:
                return det
    if last is None and not tried:
        raise VisionError("top image: no holder found (no rectangular target of either "
                          "polarity" + (f" near {expected_size_px[0]:.0f} x "
                                        f"{expected_size_px[1]:.0f} px" if expected_size_px
                                        else "") + ")")
    why = "no holder found: " + "; ".join(reasons)
    if last is None:
        raise VisionError(f"top image: {why}")
    return HolderDetection(ok=False, corners_px=np.full((4, 2), np.nan),
                           center_px=np.full(2, np.nan), angle_deg=math.nan, quality=0.0,
                           corner_sigma_px=math.nan, polarity=last.polarity,
                           size_px=(math.nan, math.nan), reason=why)


def _median_step(det: HolderDetection) -> float:
    """The median of the found sides' steps (DN, unsigned)."""
    steps = [abs(ln.contrast) for ln in det.lines if ln is not None]
    return float(np.median(steps)) if steps else math.inf


def _only_rough(det: HolderDetection, max_rms_px: float) -> bool:
    """Whether ``det`` was refused with all four sides found, one or more of them only for
    crossings scattering over ``max_rms_px`` by up to _SECOND_RMS_FACTOR."""
    rms = np.asarray(det.edge_rms_px, float)
    return (not det.ok and rms.size == 4 and bool(np.all(np.isfinite(rms)))
            and max_rms_px < float(rms.max()) <= max_rms_px * _SECOND_RMS_FACTOR)


def _looked_again(gray: np.ndarray, det: HolderDetection, polarity: str | None,
                  expected_size_px: tuple[float, float] | None, hint: np.ndarray | None,
                  min_contrast: float, max_rms_px: float, passes: int, lens: Lens | None,
                  size_tolerance: float, profile: bool) -> HolderDetection:
    """``det`` after the checks that may measure the holder again elsewhere (a side on
    a shadow's edge, :func:`_not_a_shadow`; on another edge at a slant,
    :func:`_not_askew`): a found holder passes both, a refused one neither; then, what
    they leave, a side bare at one end (:func:`_one_bare_end`)."""
    for check in (_not_a_shadow, _not_askew):
        if det.ok:
            det = check(gray, det, polarity, expected_size_px, hint, min_contrast,
                        max_rms_px, passes, lens, size_tolerance, profile)
    why = _one_bare_end(gray, det, lens) if det.ok else ""
    return _not_ok(det, why) if why else det


def _not_a_shadow(gray: np.ndarray, det: HolderDetection, polarity: str | None,
                  expected_size_px: tuple[float, float] | None, hint: np.ndarray | None,
                  min_contrast: float, max_rms_px: float, passes: int, lens: Lens | None,
                  size_tolerance: float, profile: bool) -> HolderDetection:
    """``det``, unless one of its sides is a shadow's outer edge (a second step just
    inside it, :func:`alignd.vision.holder_steps.inner_step`, that the expected
    size puts the holder's side at): then the holder measured again with that side moved
    in to the inner step, or not ok with the reason. Never a holder a shadow's width too
    large. The levels alone cannot tell a shadow band beyond a side from a shadow's edge
    across the holder parallel to it (both step twice the same way): the size does, so
    without an expected size there is no such check."""
    if expected_size_px is None:
        return det
    step = inner_step(gray, det.corners_px) or _wide_strip(gray, det, lens, expected_size_px)
    if step is None:
        return det
    k = step.side
    c = np.asarray(det.corners_px, float)
    # the sides' lengths in the ideal image, as the size check measures them (a lens's
    # distortion stretches the frame's by a few %: a side 1.9 % long read a 4 px inner
    # step as the better fit, seed 177 #713 at 640 x 480)
    lengths = _side_lengths(c if lens is None else lens.undistort(c))
    along, across = float(lengths[k]), float(lengths[(k + 1) % 4] + lengths[k - 1]) / 2
    if (_size_misfit((along, across - step.depth_px), expected_size_px)
            >= _size_misfit((along, across), expected_size_px)):
        return det  # the inner step lies across the holder: the side is where it should be
    moved = c.copy()
    moved[[k, (k + 1) % 4]] += step.depth_px * np.asarray(step.inward)
    why = (f"side {k} has a second step {step.depth_px:.0f} px inside it "
           f"({100 * step.ratio:.0f} % of its own), where the holder's size puts the side "
           "(a shadow's or a strip's edge taken for the side?)")
    try:
        again = _refine(gray, order_corners(moved), polarity, expected_size_px, hint,
                        min_contrast, max_rms_px, passes, lens, size_tolerance, profile)
    except VisionError as exc:
        again = replace(det, ok=False, reason=f"{why}; measured at the inner step: {exc}")
    if again.ok and inner_step(gray, again.corners_px) is None:
        log.debug("top image: %s; measured at the inner step instead", why)
        return again
    # a strip beside the side contrasting the other way (a white sample beside a grey
    # holder on a dark disc) steps back to the disc at its far edge, the stronger step,
    # which the +-10 px search finds again: the fine windows straight on the inner step,
    # kept only where that side is the strip's (sides of both contrasts, _strip_side)
    try:
        inner = _refine(gray, order_corners(moved), polarity, expected_size_px, hint,
                        min_contrast, max_rms_px, passes, lens, size_tolerance, profile,
                        seeded=True)
    except VisionError:
        return _not_ok(replace(det, reason=""), why)
    if inner.ok and inner_step(gray, inner.corners_px) is None \
            and _beside_a_strip(inner, lens):
        log.debug("top image: %s; measured at the inner step, beside a strip", why)
        return inner
    return _not_ok(replace(det, reason=""), why)


def _wide_strip(gray: np.ndarray, det: HolderDetection, lens: Lens | None,
                expected_size_px: tuple[float, float]) -> InnerStep | None:
    """A step inside a side deeper than :func:`inner_step` looks (``FAR_PX``), where the
    expected size puts the holder's side: a strip wider than that along a side of a
    nearly square holder (a sample beside it, 26-40 px on a 200 x 182 px holder) makes a
    rectangle within the size tolerance with its sides' roles swapped, and it was
    returned whole. Looked for only on a side whose length is one expected size (within
    ``_WIDE_STRIP_FIT``) while the extent across it exceeds the other by more than
    ``FAR_PX``; the step must lie within ``_WIDE_STRIP_SLACK`` of that depth."""
    c = np.asarray(det.corners_px, float)
    lengths = _side_lengths(c if lens is None else lens.undistort(c))
    for k in range(4):
        along = float(lengths[k])
        across = float(lengths[(k + 1) % 4] + lengths[k - 1]) / 2
        for e_along, e_across in (expected_size_px, expected_size_px[::-1]):
            depth = across - e_across
            if abs(along / e_along - 1.0) > _WIDE_STRIP_FIT or depth <= FAR_PX:
                continue
            step = inner_step(gray, c, side=k, far_px=depth + _WIDE_STRIP_BEYOND_PX)
            if step is not None and abs(step.depth_px - depth) <= _WIDE_STRIP_SLACK * depth:
                return step
    return None


def _beside_a_strip(det: HolderDetection, lens: Lens | None) -> bool:
    """Whether ``det``'s sides contrast both ways (one of them beside a strip: it passed
    :func:`_strip_side`'s check)."""
    lines = list(det.lines)
    c = det.corners_px if lens is None else lens.undistort(det.corners_px)
    return len(lines) == 4 and len(set(_outside_signs(lines, c))) > 1


def _not_askew(gray: np.ndarray, det: HolderDetection, polarity: str | None,
               expected_size_px: tuple[float, float] | None, hint: np.ndarray | None,
               min_contrast: float, max_rms_px: float, passes: int, lens: Lens | None,
               size_tolerance: float, profile: bool) -> HolderDetection:
    """``det``, or the holder measured again inside a slanted side of it.

    A side on another straight edge beyond the holder's own, at a slant, keeps a
    rectangle within the size tolerance (corpus seed 7100 #477: a dark holder's side on a
    bright rim ring 13-27 px beyond it, 4.8 deg from parallel to its opposite, returned 27
    px off). Opposite sides more than ``_MAX_SKEW_DEG`` from parallel are more than a
    camera that passes the rim pre-check makes: the side whose corners are furthest from
    square is placed again parallel to its opposite at the expected size, and the holder
    measured from there is taken where its own sides are parallel. Where it is not (a
    keystone: the edges are where they were), ``det`` stands. Without an expected size
    there is no such look."""
    if expected_size_px is None:
        return det
    c = order_corners(det.corners_px)
    ci = c if lens is None else lens.undistort(c)
    skew, k = _skew(ci)
    if skew <= _MAX_SKEW_DEG:
        return det
    # the odd side k, moved parallel to its opposite (k + 2, from corner k + 2 to k + 3)
    # at the expected extent across
    a, b = ci[(k + 2) % 4], ci[(k + 3) % 4]
    u = (b - a) / max(float(np.linalg.norm(b - a)), 1e-9)
    m = np.array([-u[1], u[0]])
    if float(np.dot((ci[k] + ci[(k + 1) % 4]) / 2 - a, m)) < 0:
        m = -m
    lengths = _side_lengths(ci)
    across = float(lengths[(k + 1) % 4] + lengths[(k + 3) % 4]) / 2
    s = min(expected_size_px, key=lambda e: abs(e - across))
    moved = ci.copy()
    moved[(k + 1) % 4], moved[k] = a + s * m, b + s * m
    if lens is not None:
        moved = lens.distort(moved)
    why = (f"opposite sides {skew:.1f} deg from parallel (side {k} on another edge at a "
           "slant?)")
    try:
        again = _refine(gray, order_corners(moved), polarity, expected_size_px, hint,
                        min_contrast, max_rms_px, passes, lens, size_tolerance, profile)
    except VisionError:
        return det
    if not again.ok:
        return det
    ca = order_corners(again.corners_px)
    if _skew(ca if lens is None else lens.undistort(ca))[0] > _MAX_SKEW_DEG:
        return det  # the same slanted edges (a keystoned holder): they are the holder's
    log.debug("top image: %s; measured again with that side parallel to its opposite", why)
    return again


def _skew(c: np.ndarray) -> tuple[float, int]:
    """The larger angle between opposite sides of the quadrilateral ``c`` (deg), and of
    that pair the side (k: corner k to k + 1) whose corners are further from square."""
    edge = c[_NEXT] - c
    ang = np.degrees(np.arctan2(edge[:, 1], edge[:, 0]))

    def between(p: float, q: float) -> float:  # the angle between two lines, 0-90 deg
        d = (p - q) % 180.0
        return float(min(d, 180.0 - d))

    pairs = [between(ang[0], ang[2]), between(ang[1], ang[3])]
    k = int(np.argmax(pairs))
    off = [90.0 - between(ang[i - 1], ang[i]) for i in range(4)]  # at corner i
    if off[(k + 2) % 4] + off[(k + 3) % 4] > off[k] + off[(k + 1) % 4]:
        k = (k + 2) % 4
    return pairs[k % 2], k


def _size_misfit(size: tuple[float, float], expected: tuple[float, float]) -> float:
    """How far a rectangle's sides are off the expected ones: the larger relative error,
    long side to long side (a nearly square holder with a plate along one side makes a
    rectangle whose longer side is the plate's way)."""
    (a, b), (ea, eb) = sorted(size, reverse=True), sorted(expected, reverse=True)
    return max(abs(a / ea - 1.0), abs(b / eb - 1.0))


def _refine(gray: np.ndarray, corners: np.ndarray, polarity: str | None,
            expected_size_px: tuple[float, float] | None, hint: np.ndarray | None,
            min_contrast: float, max_rms_px: float, passes: int, lens: Lens | None = None,
            size_tolerance: float = 0.15, profile: bool = True, seeded: bool = False,
            prior: _Prior | None = None,
            neighbours: bool = True) -> HolderDetection:
    """Fine fit from approximate corners (a coarse box or, ``seeded``, the previous frame's
    corners; ``prior``: what the previous detection found, reused when the sides held:
    the sides' blurs, whether a side lay between two steps (if none did, the sides are not
    looked at for a band again, :func:`_off_the_bands`) and whether a penumbra lay beside
    one (if none did, the profile fit does not look for one); ``neighbours``: whether to
    look for a second step beside the sides, :func:`_off_the_neighbours`)."""
    # (the fine windows straight on the previous sides: with a lens, only where they bow
    # little between their corners; the coarse search runs otherwise)
    sides = _fit_sides(gray, corners, _HALF_WIDTH, _MARGIN, min_contrast, lens) \
        if seeded and passes <= 1 and _sagitta(corners, lens) <= _SEED_SAGITTA_PX else None
    blur, bands = None, True
    if sides is not None and _seed_holds(sides, corners, max_rms_px, lens):
        # every side within a pixel of where it was: its blur is the previous frame's,
        # and so is its edge's make (one step or two: 2-5 ms a frame to tell; a penumbra
        # beside it or none: 1.5-2 ms)
        penumbra = True
        if prior is not None:
            blur = prior.blur[_side_match(prior.corners, corners)]
            bands, penumbra = prior.banded, prior.penumbra
        det = _finish(gray, corners, sides, polarity, expected_size_px, hint, min_contrast,
                      max_rms_px, lens, size_tolerance, profile, blur, bands, neighbours,
                      penumbra)
        if not (profile and det.ok and not det.side_blur_px):
            return det
        # the profile fit did not confirm the area method's corners on the previous
        # sides' windows: as the coarse search places them (its corners, then the area
        # method's own; soft sides through a lens, seed 177 #353: 0.15 px off, 0.02 so)
    at, sides = _locate(gray, corners, min_contrast, passes, lens)
    if seeded and _shift(at, corners) > _RESEED_PX:
        # the holder moved far within the +-10 px side search (a sweep's 2 deg steps): the
        # fine windows sat off-centre and could straddle a nearby edge (a sample strip
        # along a side), skewing a side by up to 2 px at a corner; located again around
        # what was found, before the profile fit (once, not on both: a sweep's tracked
        # frame took 75 ms with the whole measurement made twice)
        with contextlib.suppress(VisionError):
            at, sides = _locate(gray, at, min_contrast, passes, lens)
    if blur is not None:
        blur = blur[_side_match(corners, at)]
    return _finish(gray, at, sides, polarity, expected_size_px, hint, min_contrast,
                   max_rms_px, lens, size_tolerance, profile, blur, bands, neighbours)


def _sagitta(corners: np.ndarray, lens: Lens | None) -> float:
    """How far the lens bends the holder's sides in the frame: the largest distance
    between a side's chord (corner to corner) and its middle (px)."""
    if lens is None or lens.k1 == 0.0:
        return 0.0
    ideal = lens.undistort(corners)
    mid = lens.distort((ideal + ideal[_NEXT]) / 2)
    return _shift(mid, (corners + corners[_NEXT]) / 2)


def _seed_holds(sides: list[tuple[Line | None, EdgePoints]], corners: np.ndarray,
                max_rms_px: float, lens: Lens | None) -> bool:
    """Tracking: whether the fine windows centred on the previous frame's sides caught
    every side whole (nearly every column used, a good fit) and the sides moved by less
    than a pixel: then the +-10 px coarse search that re-centres the windows would give
    the same windows and is not needed."""
    lines = [ln for ln, _pts in sides if ln is not None]
    if len(lines) != 4:
        return False
    for span, ln in zip(_side_lengths(corners).tolist(), lines, strict=True):
        crossed = max(span - 20.0, 1.0) * max(abs(ln.n[0]), abs(ln.n[1]))  # columns (rows)
        if ln.rms_px > max_rms_px or ln.n_used < 0.8 * crossed:
            return False
    new = np.array([intersect(lines[i - 1], lines[i]) for i in range(4)])
    if not np.all(np.isfinite(new)):
        return False
    if lens is not None:
        new = lens.distort(new)
    return _shift(new, corners) <= 1.0


def _locate(gray: np.ndarray, corners: np.ndarray, min_contrast: float, passes: int,
            lens: Lens | None) -> tuple[np.ndarray, list[tuple[Line | None, EdgePoints]]]:
    """The sides' area-method crossings and lines, from approximate corners: the corners
    the fine windows were centred on, and the sides."""
    # pass 0: strongest step near each side of the approximate box (+-10 px), good to a few
    # tenths of a pixel; then the area method (exact wherever the edge sits in its window,
    # so one pass suffices; more passes re-centre the windows on the previous lines)
    coarse = coarse_edges_many(gray, [(corners[i], corners[(i + 1) % 4]) for i in range(4)],
                               search_px=10, min_step=min_contrast / 2)
    if any(c is None for c in coarse):
        raise VisionError("top image: the holder's sides could not be located "
                          f"(side(s) {[i for i, c in enumerate(coarse) if c is None]})")
    lines: list[Line | None] = list(coarse)
    empty = EdgePoints(np.empty((0, 2)), np.empty(0), False)
    sides: list[tuple[Line | None, EdgePoints]] = [(None, empty)] * 4
    lines_ideal = False  # after a fine pass with a lens, lines live in the ideal image
    for _ in range(max(passes, 1)):
        new = corners.copy()
        for i in range(4):
            a, b = lines[i - 1], lines[i]
            if a is not None and b is not None:
                p = intersect(a, b)
                if np.all(np.isfinite(p)):
                    new[i] = p
        if lines_ideal and lens is not None:
            new = lens.distort(new)
        if np.max(np.linalg.norm(new - corners, axis=1)) > 0.25 * np.linalg.norm(
                corners[2] - corners[0]):
            break  # a line went astray: keep the previous corners and flag below
        corners = new
        sides = _fit_sides(gray, corners, _HALF_WIDTH, _MARGIN, min_contrast, lens)
        lines = [s[0] for s in sides]
        lines_ideal = True
    return corners, sides


def _finish(gray: np.ndarray, corners: np.ndarray, sides: list[tuple[Line | None, EdgePoints]],
            polarity: str | None, expected_size_px: tuple[float, float] | None,
            hint: np.ndarray | None, min_contrast: float, max_rms_px: float,
            lens: Lens | None, size_tolerance: float, profile: bool,
            blur: np.ndarray | None = None, bands: bool = True,
            neighbours: bool = True, penumbra: bool = True) -> HolderDetection:
    """The detection from the sides' area-method fits: checked, widened for soft edges,
    refined by the profile fit where that agrees (``penumbra``: whether it looks for a
    penumbra beside a side), and its sides moved off a band beside them (``bands``) or
    measured again without a second step near them (``neighbours``)."""
    pol = _polarity(gray, corners)
    # a side beside a strip (a white sample beside a grey holder on a dark disc) may
    # contrast the other way
    assemble = partial(_assemble, strip_side=_strip_side(gray, sides, corners, lens))
    # with the profile fit to follow, the area method's corner sigma is rarely reported:
    # its residual correlations are left out here and measured only when it is
    det = assemble(sides, corners, pol, expected_size_px, hint, max_rms_px, lens,
                   size_tolerance, inflate=not profile)
    hw, used, margin = _HALF_WIDTH, sides, _MARGIN
    if not det.ok and "rms" in det.reason:
        # a soft (defocused) edge overflows the +-5 px window: measure it in +-9 px
        wide = _fit_sides(gray, corners, _WIDE, _WIDE_MARGIN, min_contrast, lens)
        det2 = assemble(wide, corners, pol, expected_size_px, hint, max_rms_px, lens,
                        size_tolerance, inflate=not profile)
        if det2.ok:
            det = det2
            hw, used, margin = _WIDE, wide, _WIDE_MARGIN
    if profile and not det.ok:
        det = assemble(used, corners, pol, expected_size_px, hint, max_rms_px, lens,
                       size_tolerance)
    elif profile:
        # the sides it passed, refined by the profile fit: kept when they pass as well
        fine, widths, bent, pen = _profile_sides(gray, used, hw, margin, lens, blur,
                                                 penumbra)
        # opposite sides somewhat unalike are fitted again alike (so unlike that they
        # cannot be one face's, they are left as they are, for the refusal below)
        alike = (_alike_opposite_blurs(widths) if blur is None and not
                 _unlike_opposite_blurs(tuple(float(v) for v in widths)) else None)
        if alike is not None:
            fine, widths, bent, pen = _profile_sides(gray, used, hw, margin, lens, alike)
        det3 = assemble(fine, corners, pol, expected_size_px, hint, max_rms_px, lens,
                        size_tolerance)
        # two estimates of the same corners must agree within the area method's
        # uncertainty (and the penumbra the profile fit modelled, which the area method
        # reads as edge); where they do not, one of them erred (the model did not fit:
        # a hole in the window, a penumbra not modelled; or the area method did, below),
        # and the checks that follow decide which corners, if any, are returned
        moved = _shift(det3.corners_px, det.corners_px) if det3.ok else math.inf
        agree = moved <= _AGREE_PX + _AGREE_SIGMA * det.fit_sigma_px + bent
        # (read once: the disagreement below asks again)
        clipped = det3.ok and not agree and _clipped_share(gray, used) > _CLIP_SHARE
        if clipped:
            agree = moved <= (_AGREE_PX + _AGREE_SIGMA * det.fit_sigma_px
                              + max(_CLIP_AGREE_PX, _clip_offset(used, fine, widths)))
        if (det3.ok and not agree and hw == _HALF_WIDTH
                and np.nanmax(widths / _window_reach(corners), initial=0.0)
                > _SOFT_BLUR_PX):
            # a soft side's transition overflows the area method's +-5 px, which then
            # errs by 0.1-0.3 px itself (its tails inside the blur): a second opinion in
            # +-9 px may confirm the refined corners (the +-5 px ones stay the fallback)
            wide = _fit_sides(gray, corners, _WIDE, _WIDE_MARGIN, min_contrast, lens)
            det9 = assemble(wide, corners, pol, expected_size_px, hint, max_rms_px, lens,
                            size_tolerance, inflate=False)
            if det9.ok:
                moved = _shift(det3.corners_px, det9.corners_px)
                agree = moved <= _AGREE_PX + _AGREE_SIGMA * det9.fit_sigma_px + bent
        if det3.ok and not agree and _shift(det.corners_px, corners) > _MISPLACED_PX:
            # the windows lie between the corners searched from; where those were a few
            # px off along a side (a rectangle's corners on a keystoned holder), the end
            # windows reach past a true corner and the area method errs there itself
            # (0.1-0.2 px): its own corners place them once more, and where they then fit
            # at least as well (misplaced windows, not a misfit), they may confirm the
            # refined corners (an uncertain area fit placed again from its own wrong
            # corners loosened the test and let a holder 3.4 px wrong through; from
            # corners within a px, a penumbra fooled both alike)
            again = _fit_sides(gray, det.corners_px, hw, margin, min_contrast, lens)
            det2 = assemble(again, det.corners_px, pol, expected_size_px, hint, max_rms_px,
                            lens, size_tolerance, inflate=False)
            if det2.ok and det2.fit_sigma_px <= det.fit_sigma_px:
                moved = _shift(det3.corners_px, det2.corners_px)
                agree = moved <= _AGREE_PX + _AGREE_SIGMA * det2.fit_sigma_px + bent
        if agree:
            det = replace(det3, side_blur_px=tuple(
                float(v) for v in widths[_side_match(corners, det3.corners_px)]),
                penumbra=pen)
            why = _unlike_opposite_blurs(det.side_blur_px)
        else:
            det = assemble(used, corners, pol, expected_size_px, hint, max_rms_px, lens,
                           size_tolerance)
            why = ""
            if det.ok and det.corner_sigma_px > _AREA_ALONE_SIGMA_PX:
                # the edge model did not fit and the model-free corners are loose: what
                # was fitted is likely not the holder's outline (a side along a label's
                # or a cable's edge; corpus frames 1.7-73 px off, sigma 0.37-0.54 px,
                # where every right holder kept this way had sigma under 0.24 px)
                why = (f"the edge profiles do not fit and the area method's corners are "
                       f"uncertain to {det.corner_sigma_px:.2f} px (a side on another "
                       "edge?)")
            elif det.ok:
                why = _rough_side(det.edge_rms_px)
            if det.ok and not why and det3.ok:
                # two estimates of the corners disagree, neither refused. The area
                # method errs too (under a steep light, a soft side's overflowing window,
                # a noisy floor, JPEG blocks; docs/vision.md, "Two fits that disagree"):
                # the refined corners are returned where they lie within 0.9 px of the
                # area method's and their sides fit at least as well, or clip (the area
                # method reads the clip as the level; the profile fit leaves those pixels
                # out, so it fits fewer), unconfirmed (no side blurs: tracking measures
                # them again). Half the difference counts in the corners' uncertainty
                # either way, as a band's move does (_off_the_bands)
                apart = _shift(det3.corners_px, det.corners_px)
                if apart <= _REFINED_APART_PX and (
                        det3.fit_sigma_px <= det.fit_sigma_px or clipped):
                    det = det3
                det = replace(det, corner_sigma_px=math.hypot(
                    det.corner_sigma_px, _DISAGREE_SHARE * apart))
        if why:
            det = _not_ok(det, why)
    if det.ok:
        bare = _bare_ends(gray, det, lens) or _bent_side(used, corners, lens)
        if bare:
            det = _not_ok(det, bare)
    if polarity is not None and det.ok and pol != polarity:
        raise VisionError(f"top image: the holder found is {pol}, not {polarity}")
    if det.ok:
        det = replace(det, clipped_sides=int(np.count_nonzero(
            _clipped_shares(gray, used) > _SATURATED_SHARE)))
    # the sides' profiles, read once for the band check and the neighbour look (whose
    # reach is the larger) at the corners found
    prof = None
    if det.ok and (bands or neighbours):
        prof = read_sides(gray, det.corners_px, lens, NEIGHBOUR_REACH if neighbours else
                          BAND_REACH)
        if bands:
            det = _off_the_bands(gray, det, lens, expected_size_px, size_tolerance, prof)
    # a refused candidate is measured again without the steps beside its sides (which
    # can spoil a side's fit), but not where two sides found no edge at all: no step
    # beside them would give them one, and the look costs 5-10 ms a candidate
    bare_sides = sum(ln is None for ln, _pts in used)
    # (beside sides at a shadow's soft edge, a step further out is still looked for where
    # the profile fit did not confirm the sides, and the sides measured again without it
    # are looked at for such an edge again: a shadow shifted 8 px along a holder lies at
    # its long sides and 8 px beyond a short one, whose fit only the look cleared, 0.2 px
    # off without it. Where the sides were confirmed, the look is not made: a corpus
    # scene's, 81100 #853, went 0.12 -> 0.23 px rms)
    tails = det.tail_sides > 0
    looked = not det.banded_sides or (det.banded_sides == det.tail_sides
                                      and not det.side_blur_px)
    if neighbours and looked and (det.ok or bare_sides < _NO_EDGE_SIDES):
        det = _off_the_neighbours(gray, det, corners, polarity, expected_size_px, hint,
                                  min_contrast, max_rms_px, lens, size_tolerance, profile,
                                  None if tails else prof, tails)
    return det


def _off_the_neighbours(gray: np.ndarray, det: HolderDetection, corners: np.ndarray,
                        polarity: str | None, expected_size_px: tuple[float, float] | None,
                        hint: np.ndarray | None, min_contrast: float, max_rms_px: float,
                        lens: Lens | None, size_tolerance: float, profile: bool,
                        prof: SideProfiles | None = None, tails: bool = False
                        ) -> HolderDetection:
    """``det`` measured again without the second steps near its sides
    (:mod:`alignd.vision.holder_neighbours`), from its corners or, where the checks refused
    it (a side that scatters, profiles that do not fit), the corners its windows sat on;
    ``det`` itself where no side has such a step or the sides measured again fail.

    The steps are found and removed along the sides given, so each pass starts from the
    previous one's corners, until they move by under ``_NEIGHBOURS_SETTLED_PX`` (a side a
    pixel off its edge, or at an angle to it, reads a blurred step at the wrong place:
    from a coarse box 2.9 px off at one end, one pass left two sides 0.44 px off). A first
    pass that moves them by under ``_NEIGHBOURS_NEAR_PX`` stands: its steps were fitted
    that near the sides, and over 107 such drawn plates a second pass moved them by
    0.037 px at most (its measurement again costs 10-15 ms).
    ``prof``: the profiles of ``det``'s sides, read already when it is ok. ``tails``:
    ``det`` has sides at a shadow's soft edge, which the sides measured again are looked
    at for too (:func:`_off_the_bands`)."""
    at = np.asarray(det.corners_px if det.ok else corners, float)
    for n_pass in range(_NEIGHBOURS_PASSES):
        steps = neighbour_steps(gray, at, lens, prof if det.ok else None)
        prof = None  # the next pass reads its own, at the corners it starts from
        if not steps:
            return det
        clean = without_neighbours(gray, at, steps, lens)
        again = _finish(clean, at, _fit_sides(clean, at, _HALF_WIDTH, _MARGIN, min_contrast,
                                              lens),
                        polarity, expected_size_px, hint, min_contrast, max_rms_px, lens,
                        size_tolerance, profile, None, bands=tails, neighbours=False)
        what = ", ".join(f"side {n.side} {n.at_px:+.1f} px" for n in steps)
        if not again.ok:
            log.debug("top image: a step beside a side (%s), but the sides measured again "
                      "without it failed: %s", what, again.reason)
            return det
        moved = _shift(again.corners_px, at)
        at = np.asarray(again.corners_px, float)
        if moved <= (_NEIGHBOURS_NEAR_PX if n_pass == 0 else _NEIGHBOURS_SETTLED_PX):
            log.debug("top image: sides measured again without a step beside them: %s", what)
            return replace(again, neighbour_sides=len(steps))
    log.debug("top image: the sides measured again without a step beside them did not "
              "settle (%.2f px in the last pass)", moved)
    return det


def _shift(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance between corresponding corners of ``a`` and ``b`` (px)."""
    return float(np.max(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=1)))


def _window_reach(corners: np.ndarray) -> np.ndarray:
    """Per side, how far the area method's windows reach across it per px along their
    pixel column or row: the cosine of its angle to the nearest image axis (a side at 45
    deg is crossed by its +-5 px windows over +-3.5 px only)."""
    n = side_frame(np.asarray(corners, float))[2]
    return np.max(np.abs(n), axis=1)


def _off_the_bands(gray: np.ndarray, det: HolderDetection, lens: Lens | None,
                   expected_size_px: tuple[float, float] | None, size_tolerance: float,
                   prof: SideProfiles | None = None) -> HolderDetection:
    """``det`` with each side found between two steps or on the outer one (a hard
    shadow's band beside it, :func:`alignd.vision.holder_bands.side_bands`) moved in to
    the inner step, the holder's edge; its corners' sigma grows by that step's standard
    error. Not ok when the moved holder's size fails the size check. ``prof``: the
    profiles of ``det``'s sides, if read already."""
    bands = side_bands(gray, det.corners_px, lens, prof)
    if not bands:
        return det
    c = np.asarray(det.corners_px, float)
    ci = c if lens is None else lens.undistort(c)
    n = side_frame(ci)[2]
    shift = np.zeros(4)
    extra = 0.0
    for b in bands:
        shift[b.side] = b.inner_px
        extra = max(extra, b.sigma_px)
    # each corner k is where sides k - 1 and k meet: moved along both normals so that it
    # lies on both moved lines (a + n_a . x = shift_a for the corner's offset x)
    out = ci.copy()
    for k in range(4):
        A = np.array([n[k - 1], n[k]])
        out[k] = ci[k] + np.linalg.solve(A, np.array([shift[k - 1], shift[k]]))
    side = _side_lengths(out)
    size = (float(side[0] + side[2]) / 2, float(side[1] + side[3]) / 2)
    what = ", ".join(f"side {b.side} by {-b.inner_px:.2f} px" for b in bands)
    if expected_size_px is not None and _size_misfit(size, expected_size_px) > size_tolerance:
        return _not_ok(det, f"a side steps twice, the holder's edge and a band beside it "
                            f"(a hard shadow?); moved in to the inner step ({what}), the "
                            f"holder is "
                            f"{max(size):.1f} x {min(size):.1f} px, expected "
                            f"{max(expected_size_px):.1f} x {min(expected_size_px):.1f}")
    log.debug("top image: sides beside a band moved in to its inner step: %s", what)
    center, angle = _quad_center(out), _quad_angle(out)
    frame = out if lens is None or lens.k1 == 0.0 else lens.distort(out)
    if lens is not None and lens.k1 != 0.0:
        center = lens.distort(center[None])[0]
    return replace(det, corners_px=frame, center_px=center, angle_deg=angle, size_px=size,
                   corner_sigma_px=math.hypot(det.corner_sigma_px, extra), lines=(),
                   banded_sides=len(bands), tail_sides=sum(b.tail for b in bands))


def _rough_side(rms: tuple[float, ...]) -> str:
    """Why the area method's corners, kept where the edge profiles did not fit, cannot be
    trusted for one side's roughness, or "".

    A narrow band beside a side (a sharp holder's cast shadow 3-5 px off it) puts a
    second step in that side's +-5 px windows: its crossings scatter, its line fits
    several times worse than the other sides', the profile fit merges the band into the
    step and disagrees, and the area method's corners err by the band's pull (corpus
    #639 of seed 6100: 1.45 px off, that side 0.44 px rms against 0.05-0.10, corner
    standard error 0.11 px). Over the area-kept detections of eight corpora the right
    ones' roughest side was at most 2.2 times the sides' median, the rest 4.0-9.0 (0.45
    and 0.82 px off; those are refused too)."""
    v = np.asarray(rms, float)
    if v.size != 4 or not np.all(np.isfinite(v)):
        return ""
    k = int(np.argmax(v))
    ratio = float(v[k] / max(float(np.median(v)), 1e-9))
    if ratio < _ROUGH_SIDE_RATIO:
        return ""
    return (f"the edge profiles do not fit and side {k}'s edge scatters {ratio:.1f} times "
            f"as much as the sides' median ({v[k]:.2f} px rms): a second step beside it "
            "(a shadow's band?)")


def _alike_opposite_blurs(widths: np.ndarray) -> np.ndarray | None:
    """The sides' edge widths (``widths``, corner k to k + 1) with each opposite pair that
    differs by more than ``_BLUR_ALIKE_PX`` held at the sharper one's (where that is
    ``_BLUR_ALIKE_MIN_PX`` or more), or None where none does. One lens blurs a flat face's
    opposite sides alike; a side fitted much softer has taken something beside its edge
    into the blur (a penumbra, a shadow's band, a floor's slope), which moves the edge
    too. Over 13 corpora the 20 detections with a side fitted 0.4 px or more wider than
    the other three's median had a median error of 0.16-0.35 px, up to 0.91, against 0.016
    for the rest; fitted again with the width held (the profile fit's ``blur``), 0.83 ->
    0.33 px (71100 #979), 0.91 -> 0.84 (81100 #776)."""
    w = np.asarray(widths, float)
    out = w.copy()
    for a, b in ((0, 2), (1, 3)):
        if not (math.isfinite(w[a]) and math.isfinite(w[b])):
            continue
        lo, hi = min(w[a], w[b]), max(w[a], w[b])
        if lo >= _BLUR_ALIKE_MIN_PX and hi - lo > _BLUR_ALIKE_PX:
            out[a] = out[b] = lo
    return None if np.array_equal(out, w) else out


def _unlike_opposite_blurs(blur: tuple[float, ...]) -> str:
    """Why the sides' fitted edge widths cannot be one holder's outline, or "".

    Opposite sides are parallel edges of one flat face, a few hundred px apart: the lens
    blurs them alike. A side fitted far softer than its opposite one has a second step
    merged into its profile (a cast shadow's band beside it: corpus frames 1-1.4 px off
    with widths 2.5 / 2.1 px against 0.2 / 0.15), where the right holders' opposite sides
    differ by at most 0.8 px."""
    if len(blur) != 4:
        return ""
    for k in (0, 1):
        a, b = blur[k], blur[k + 2]
        if not (math.isfinite(a) and math.isfinite(b)):
            continue
        lo, hi = min(a, b), max(a, b)
        if hi - lo > _BLUR_UNLIKE_PX and hi > _BLUR_UNLIKE_RATIO * lo:
            return (f"opposite sides {k} and {k + 2} have edges {a:.2f} and {b:.2f} px wide "
                    "(one lens blurs both alike): a shadow or a second edge beside the "
                    "softer one?")
    return ""


def _not_ok(det: HolderDetection, why: str) -> HolderDetection:
    """``det`` refused with the reason (no corners, no pose)."""
    return replace(det, ok=False, corners_px=np.full((4, 2), np.nan),
                   center_px=np.full(2, np.nan), angle_deg=math.nan, quality=0.0,
                   corner_ok=np.zeros(4, bool), size_px=(math.nan, math.nan),
                   reason="; ".join(r for r in (det.reason, why) if r))


def _clip_offset(area: list[tuple[Line | None, EdgePoints]],
                 fine: list[tuple[Line | None, EdgePoints]], widths: np.ndarray) -> float:
    """How far the area method's corners may lie from the refined ones on clipped sides.

    A step of height D blurred by s and clipped at a level a fraction 1 / k of D up (its
    tails then read D / k) has its area crossing moved toward the unclipped side by
    s k phi(Phi^-1(1 / k)) (the integral of min(k Phi, 1) - Phi; 0.8 s at k = 2). k is
    each side's fitted step height over the area method's; a corner moves with both of
    its sides: sqrt(2) times the largest side's offset (its windows' ends, which cut the
    integral short, make the area method's own offset a little smaller)."""
    worst = 0.0
    for (_la, pa), (_lf, pf), s in zip(area, fine, widths, strict=True):
        if pa.xy.shape[0] == 0 or pf.xy.shape[0] == 0 or not math.isfinite(float(s)):
            continue
        ca = float(np.median(np.abs(pa.contrast)))
        k = float(np.median(np.abs(pf.contrast))) / max(ca, 1e-9)
        if k > 1.0:
            z = float(ndtri(1.0 / k))
            worst = max(worst, float(s) * k * math.exp(-0.5 * z * z) / math.sqrt(2 * math.pi))
    return math.sqrt(2.0) * worst


def _clipped_share(gray: np.ndarray, sides: list[tuple[Line | None, EdgePoints]]) -> float:
    """The largest of :func:`_clipped_shares`."""
    return float(np.max(_clipped_shares(gray, sides), initial=0.0))


def _clipped_shares(gray: np.ndarray, sides: list[tuple[Line | None, EdgePoints]]
                    ) -> np.ndarray:
    """Each side's share of crossings with a pixel within 4 px of the edge (the area
    method's window) at the sensor's full scale or at zero (frames are in 8-bit DN of full
    scale, see :func:`alignd.vision.edges.as_gray`; a float frame above 255 counts as
    unclipped, every share 0)."""
    h, w = gray.shape
    j = np.arange(-4, 5)
    n = np.array([pts.xy.shape[0] for _ln, pts in sides])
    if not n.any():
        return np.zeros(len(sides))
    # every side's windows in one gather: the rows and columns of their pixels
    ys, xs = [], []
    for _ln, pts in sides:
        k = 1 if pts.vertical else 0  # the major axis: x along columns, y along rows
        c = np.rint(pts.xy[:, 1 - k]).astype(np.intp)[:, None] + j
        t = np.rint(pts.xy[:, k]).astype(np.intp)[:, None].repeat(j.size, axis=1)
        ys.append(t if pts.vertical else c)
        xs.append(c if pts.vertical else t)
    v = gray[np.minimum(np.maximum(np.concatenate(ys), 0), h - 1),
             np.minimum(np.maximum(np.concatenate(xs), 0), w - 1)]
    if float(v.max()) > 255.0 + 1e-3:
        return np.zeros(len(sides))
    hit = np.any((v >= 254.5) | (v <= 0.5), axis=1)
    side = np.repeat(np.arange(len(sides)), n)
    return np.bincount(side, weights=hit, minlength=len(sides)) / np.maximum(n, 1)


def _polarity(gray: np.ndarray, c: np.ndarray) -> str:
    """"dark" when the quadrilateral's middle is darker than just outside its sides."""
    h, w = gray.shape
    ctr = c.sum(axis=0) / len(c)  # (the mean, without np.mean's overhead)
    mids = (c + c[_NEXT]) / 2
    v = mids - ctr
    v /= np.maximum(np.linalg.norm(v, axis=1), 1e-9)[:, None]
    at = np.vstack([ctr[None], mids + 12.0 * v])  # the middle, then just outside each side
    x = np.clip(np.rint(at[:, 0]), 2, w - 3).astype(np.intp)
    y = np.clip(np.rint(at[:, 1]), 2, h - 3).astype(np.intp)
    d = np.arange(-2, 3)
    patches = gray[(y[:, None, None] + d[None, :, None]), (x[:, None, None] + d[None, None, :])]
    level = np.partition(patches.reshape(5, 25).astype(np.float32), 12, axis=1)[:, 12]
    out = np.sort(level[1:])
    return "dark" if level[0] < 0.5 * float(out[1] + out[2]) else "light"


def _columns_span(ln: Line, pts: EdgePoints) -> tuple[float, bool]:
    """How far along ``ln`` its columns (those within its rejection reach) run, counting
    only runs of at least _RUN_COLUMNS between gaps over _RUN_GAP_PX (px); and whether
    there are shorter, stray runs."""
    resid = np.abs(pts.xy @ ln.n - ln.d)
    t = np.sort(pts.xy[resid <= 3.5 * max(ln.rms_px, 0.01)] @ np.array([-ln.n[1], ln.n[0]]))
    if t.size == 0:
        return 0.0, False
    # the runs' first and last columns (t ascending: the kept runs' span is the first
    # kept one's start to the last kept one's end)
    gap = np.flatnonzero((t[1:] - t[:-1]) > _RUN_GAP_PX)
    if gap.size == 0:  # (one run, nearly every side: kept, or else a stray one)
        kept_one = t.size >= _RUN_COLUMNS
        return (float(t[-1] - t[0]) if kept_one else 0.0), not kept_one
    first = np.concatenate(([0], gap + 1))
    last = np.concatenate((gap, [t.size - 1]))
    kept = np.flatnonzero(last - first + 1 >= _RUN_COLUMNS)
    span = float(t[last[kept[-1]]] - t[first[kept[0]]]) if kept.size else 0.0
    return span, kept.size < first.size


def _assemble(sides: list[tuple[Line | None, EdgePoints]], corners: np.ndarray, pol: str,
              expected_size_px: tuple[float, float] | None, hint: np.ndarray | None,
              max_rms_px: float, lens: Lens | None = None, size_tolerance: float = 0.15,
              inflate: bool = True, strip_side: int | None = None) -> HolderDetection:
    """The detection the sides' lines make: corners, checks, pose and uncertainty
    (``inflate`` False: corner_sigma_px without the sides' residual correlation, for a
    detection whose uncertainty is not reported; ``strip_side``: the side beside which
    :func:`_strip_beside` found a strip, which may contrast the other way)."""
    lines = [s[0] for s in sides]
    reasons = []
    edge_ok = []
    short = np.zeros(4, bool)  # a side's columns beside one of its ends only
    frac = []
    spans = _side_lengths(corners).tolist()
    for i, (ln, _pts) in enumerate(sides):
        expected = max(spans[i] - 20.0, 1.0) * 0.7  # columns/rows crossed, at most
        if ln is None:
            edge_ok.append(False)
            frac.append(0.0)
            reasons.append(f"side {i}: no edge found")
            continue
        f = min(1.0, ln.n_used / expected)
        frac.append(f)
        good = ln.n_used >= 10 and f >= _MIN_SIDE_SHARE and ln.rms_px <= max_rms_px
        if not good:
            reasons.append(f"side {i}: {ln.n_used} columns, rms {ln.rms_px:.2f} px")
        else:
            run, stray = _columns_span(ln, _ideal(_pts, lens))
            short[i] = stray and run < _MIN_SIDE_SPAN * max(spans[i] - 20.0, 1.0)
        edge_ok.append(good)
    for k in np.flatnonzero(short):
        i, j = int(k), int(k + 2) % 4
        ln, other = lines[i], lines[j]
        if ln is not None and other is not None and edge_ok[j] and not short[j]:
            # (its crossings' scatter stays its own line's: the checks judge the scatter,
            # not the direction borrowed)
            lines[i] = replace(parallel_to(ln, _ideal(sides[i][1], lens), other),
                               rms_px=ln.rms_px)
        else:
            edge_ok[i] = False
            reasons.append(f"side {i}: its edge shows beside one end only, and the "
                           "opposite side gives it no direction")
    out = np.full((4, 2), np.nan)
    sig = np.full(4, np.nan)
    fit_sig = np.full(4, np.nan)
    # the fit's covariance counts the columns as independent: scaled up by how much its
    # residuals correlate along the side (JPEG blocks, texture, penumbrae)
    infl = [residual_correlation(ln, _ideal(pts, lens)) if ln is not None and good
            and inflate else 1.0
            for ln, (_ln, pts), good in zip(lines, sides, edge_ok, strict=True)]
    for i in range(4):
        a, b = lines[i - 1], lines[i]
        if edge_ok[i - 1] and edge_ok[i] and a is not None and b is not None:
            p = intersect(a, b)
            out[i] = p
            # plus the error common to a whole side (its illumination slope's and blur's
            # noise, the same in every column), in each side's normal direction
            sa, sb = _point_sigma(a, p), _point_sigma(b, p)
            fit_sig[i] = math.hypot(sa, sb)
            sig[i] = math.sqrt(infl[i - 1] * sa ** 2 + infl[i] * sb ** 2
                               + 2 * _SIDE_COMMON_PX ** 2)
    corner_ok = np.all(np.isfinite(out), axis=1)
    ok = bool(corner_ok.all())
    center = np.full(2, np.nan)
    angle = math.nan
    size = (math.nan, math.nan)
    if ok:
        # the holder must sit on the correct side of every line (convex, not self-crossing)
        signs = _outside_signs(lines, out)
        if not _convex(out):
            ok = False
            reasons.append("fitted sides do not form a convex quadrilateral")
        elif len(set(signs)) > 1 and not _one_strip_reversed(signs, strip_side):
            ok = False
            reasons.append("sides of both polarities (not one object): "
                           + ", ".join("+" if v > 0 else "-" for v in signs))
        else:
            center = _quad_center(out)
            angle = _quad_angle(out)
            side = [math.hypot(*(out[(k + 1) % 4] - out[k])) for k in range(4)]
            size = ((side[0] + side[2]) / 2, (side[1] + side[3]) / 2)
            if (expected_size_px is not None
                    and _size_misfit(size, expected_size_px) > size_tolerance):
                ok = False
                reasons.append(f"size {max(size):.1f} x {min(size):.1f} px, expected "
                               f"{max(expected_size_px):.1f} x {min(expected_size_px):.1f}")
        if not ok:
            out[:] = np.nan
            corner_ok[:] = False
    if lens is not None and lens.k1 != 0.0 and ok:
        out = lens.distort(out)
        center = lens.distort(center[None])[0]
    corner_sigma, fit_sigma = _finite_max(sig), _finite_max(fit_sig)
    quality = min(frac) if frac else 0.0
    if math.isfinite(fit_sigma):
        quality *= max(0.0, 1.0 - fit_sigma / 0.5)
    if hint is not None and ok:
        out = order_corners(out, hint)
    return HolderDetection(ok=ok, corners_px=out, center_px=center, angle_deg=angle,
                           quality=float(quality) if ok else 0.0, corner_sigma_px=corner_sigma,
                           polarity=pol, size_px=size, corner_ok=corner_ok,
                           edge_rms_px=tuple(ln.rms_px if ln else math.nan for ln in lines),
                           reason="; ".join(reasons), lines=tuple(lines),
                           fit_sigma_px=fit_sigma)


def _bare_ends(gray: np.ndarray, det: HolderDetection, lens: Lens | None) -> str:
    """Why a side of ``det`` cannot be the holder's outline, or "".

    A side's crossings run from near one corner to near the other (the windows stop
    ``_WIDE_MARGIN`` short of each). Where they stop well short of *both* corners, either
    clutter beside the side took out its end columns (floor holes or screws by both
    corners: corpus #638 of seed 5000, a right holder) or there is no edge there at all:
    an edge inside the holder that the other three sides happen to frame (a label's:
    corpus #937 of seed 5000 at 640 x 480, a rectangle of the holder's size 23 px off,
    its label side bare for 34 and 36 px at its ends, where the right holders' sides of
    four corpora were bare for at most 11 px). The image tells them apart: across the
    line at a bare end, a side still steps as it does where it was measured."""
    corners = det.corners_px if lens is None else lens.undistort(det.corners_px)
    for i, ln, (lo, hi), length, per_major in _side_spans(det.lines, corners):
        bare = min(ln.major_span[0] - lo, hi - ln.major_span[1]) * per_major
        if bare <= _WIDE_MARGIN + max(_BARE_END_PX, _BARE_END_SHARE * length):
            continue
        if not _steps_at_both_ends(gray, ln, (lo, hi), per_major, corners.mean(axis=0),
                                   lens):
            return (f"side {i}: its edge stops {bare:.0f} px short of both corners (of "
                    f"{length:.0f} px) and the image does not step there: an edge inside "
                    "the holder, a label's?")
    return ""


def _side_spans(lines: tuple[Line | None, ...], corners: np.ndarray
                ) -> Iterator[tuple[int, Line, tuple[float, float], float, float]]:
    """Each side with a line: its index, the line, its corners' span along the line's
    major axis (the two corners nearest the line: a hint reorders the corners), its
    length and the px along it per px of that axis."""
    for i, ln in enumerate(lines):
        if ln is None:
            continue
        a, b = corners[np.argsort(np.abs(corners @ ln.n - ln.d))[:2]]
        k = 1 if ln.vertical else 0
        lo, hi = sorted((float(a[k]), float(b[k])))
        length = float(np.hypot(*(b - a)))
        if hi - lo >= 1e-6:
            yield i, ln, (lo, hi), length, length / (hi - lo)


def _one_bare_end(gray: np.ndarray, det: HolderDetection, lens: Lens | None) -> str:
    """Why a side of ``det`` whose crossings stop well short of one corner (more than
    ``_ONE_BARE_SHARE`` of it beyond the windows' margin) cannot be the holder's outline,
    or "": over that end the image does not step across the side and the level just
    inside it is not the one inside the measured stretch (:func:`_other_face_at_one_end`).
    A strip passing under the holder and a label's edge on it framed a quadrilateral of
    the holder's size (corpus #890 of seed 71100 at 800 x 600, 233 px off): two of its
    sides are the strip's edges, seen beside the holder only. Run last
    (:func:`_looked_again`): a candidate whose side first lies on a floor hole's rim
    beside a side the hole hides at one end reads so too, until the slant check measures
    it again on the holder's edge (:func:`_not_askew`; ``tests/test_vision_holder_hole``)."""
    corners = det.corners_px if lens is None else lens.undistort(det.corners_px)
    for i, ln, (lo, hi), length, per_major in _side_spans(det.lines, corners):
        ends = ((ln.major_span[0] - lo) * per_major, (hi - ln.major_span[1]) * per_major)
        if max(ends) <= _WIDE_MARGIN + _ONE_BARE_SHARE * length:
            continue
        trim = _WIDE_MARGIN / per_major
        bare_at = (np.arange(lo + trim, ln.major_span[0]) if ends[0] > ends[1]
                   else np.arange(ln.major_span[1], hi - trim))
        if _other_face_at_one_end(gray, ln, bare_at, corners.mean(axis=0), lens):
            return (f"side {i}: its edge stops {max(ends):.0f} px short of a corner (of "
                    f"{length:.0f} px), the image does not step there and what lies inside "
                    "it differs: the edge of something passing under the holder?")
    return ""


def _bent_side(sides: list[tuple[Line | None, EdgePoints]], corners: np.ndarray,
               lens: Lens | None) -> str:
    """Why one of the sides (their area-method crossings and lines, the windows placed
    between ``corners``) cannot be a straight edge of the holder, or "": its crossings
    (the line's inliers) bend away from its line by more than ``_BENT_PX`` (rms of a
    cubic along the side fitted to their distances from it) and ``_BENT_RATIO`` times the
    other sides' median bend. Noise scatters about a line; a curved edge (a cable's)
    bends, a lens not modelled bends every side, not one, and a side drifting slowly
    across a JPEG's 8 px blocks bends by up to about 0.25 px (three right holders in 13
    corpora were refused for it). A side seen over a short stretch only (under
    ``_BENT_MIN_POINTS`` crossings, or spanning under ``_BENT_MIN_SPAN`` of it) is not
    judged: beside a floor hole that hides most of a side, what shows follows the hole's
    rim."""
    c = np.asarray(corners, float)
    c = c if lens is None else lens.undistort(c)
    judged: list[tuple[int, np.ndarray, np.ndarray]] = []  # (side, along, distances)
    for i, (ln, pts) in enumerate(sides):
        if ln is None or pts.xy.shape[0] < _BENT_MIN_POINTS:
            continue
        xy = _ideal(pts, lens).xy
        r = xy @ ln.n - ln.d
        # outliers (a hole's or a screw's rim) left out at 3.5 times the line's rms, much
        # as fit_line leaves them out (it uses the median deviation)
        keep = np.abs(r) < 3.5 * max(ln.rms_px, 0.01)
        k = 1 if ln.vertical else 0
        along = xy[keep, k]
        span = abs(float(c[(i + 1) % 4, k] - c[i, k]))
        if along.size >= _BENT_MIN_POINTS and float(np.ptp(along)) >= _BENT_MIN_SPAN * span:
            judged.append((i, along, r[keep]))
    # a bend is at most the distances' own scatter: where none scatters that much (nearly
    # every frame), no cubic need be fitted (four cost about 0.5 ms)
    if not any(float(np.std(rk)) > _BENT_PX for _i, _a, rk in judged):
        return ""
    bends = [0.0] * len(sides)
    for i, along, rk in judged:
        t = (along - along.min()) / max(float(np.ptp(along)), 1e-9)
        fit = np.polyval(np.polyfit(t, rk, 3), t)
        shape, left = float(np.var(rk)) - float(np.var(rk - fit)), float(np.var(rk - fit))
        # the cubic's two terms beyond the line must explain far more than noise would
        # (F test; a noisy side's crossings, 0.7 px rms, bent by chance 0.26 px over 64)
        if shape * (along.size - 4) >= _BENT_F * 2.0 * max(left, 1e-12):
            bends[i] = float(np.sqrt(max(shape, 0.0)))
    b = np.asarray(bends)
    k = int(np.argmax(b))
    rest = float(np.median(np.delete(b, k)))
    if b[k] <= _BENT_PX or b[k] < _BENT_RATIO * rest:
        return ""
    return (f"side {k}'s edge bends away from a straight line by {b[k]:.2f} px (rms; the "
            f"others by {rest:.2f} px): a cable's or another curved edge taken for a side? "
            "(or a lens's distortion not modelled: cameras[].lens)")


def _steps_at_both_ends(gray: np.ndarray, ln: Line, ends: tuple[float, float],
                        per_major: float, center: np.ndarray, lens: Lens | None) -> bool:
    """Whether the image steps across ``ln`` beyond both ends of its crossings as it does
    along them: the level 6 px inside less the level 6 px outside, at every px of the
    major axis, keeps the measured stretch's sign and at least a third of its size in
    half of either bare end's positions."""
    lo, hi = ends
    trim = _WIDE_MARGIN / per_major
    stretches = [np.arange(lo + trim, ln.major_span[0]), np.arange(ln.major_span[1], hi - trim),
                 np.arange(ln.major_span[0], ln.major_span[1])]
    inside, outside = _levels_across(gray, ln, np.concatenate(stretches), center, lens)
    step = inside - outside
    n0, n1 = len(stretches[0]), len(stretches[1])
    ref = float(np.median(step[n0 + n1:])) if len(stretches[2]) else 0.0
    if ref == 0.0:
        return False
    like = step * math.copysign(1.0, ref) >= abs(ref) / 3.0
    return all(part.size == 0 or float(np.mean(part)) >= 0.5
               for part in (like[:n0], like[n0:n0 + n1]))


def _other_face_at_one_end(gray: np.ndarray, ln: Line, bare: np.ndarray,
                           center: np.ndarray, lens: Lens | None) -> bool:
    """Whether, over the positions ``bare`` (of the major axis) where a side's crossings
    are missing at one end, the image does not step across ``ln`` and the level just
    inside differs from the measured stretch's inside by half its step or more: what the
    side framed where it was measured is not what lies inside it there (a strip passing
    under the holder, seen beside it only), where a side hidden at one end by clutter as
    dark as the holder (a floor hole) has the holder's face inside all along."""
    measured = np.arange(ln.major_span[0], ln.major_span[1])
    if bare.size == 0 or measured.size == 0:
        return False
    inside, outside = _levels_across(gray, ln, np.concatenate([measured, bare]), center,
                                     lens)
    n = measured.size
    ref = float(np.median(inside[:n] - outside[:n]))
    if ref == 0.0:
        return False
    like = (inside[n:] - outside[n:]) * math.copysign(1.0, ref) >= abs(ref) / 3.0
    moved = abs(float(np.median(inside[n:])) - float(np.median(inside[:n])))
    return float(np.mean(like)) < 0.5 and moved >= 0.5 * abs(ref)


def _levels_across(gray: np.ndarray, ln: Line, major: np.ndarray, center: np.ndarray,
                   lens: Lens | None) -> tuple[np.ndarray, np.ndarray]:
    """The levels ``_BARE_PROBE_PX`` inside and outside the line ``ln`` (toward and away
    from ``center``) at the positions ``major`` of its major axis."""
    # points on the line x = a + b y (or y = a + b x), from n . p = d
    nx, ny = float(ln.n[0]), float(ln.n[1])
    if ln.vertical:
        pts = np.stack([(ln.d - ny * major) / nx, major], axis=1)
    else:
        pts = np.stack([major, (ln.d - nx * major) / ny], axis=1)
    inward = ln.n if float((center - pts.mean(axis=0)) @ ln.n) > 0 else -ln.n
    sides = [pts + s * _BARE_PROBE_PX * inward for s in (1.0, -1.0)]
    if lens is not None:
        sides = [lens.distort(p) for p in sides]
    inside, outside = (cv2.remap(gray, p[:, 0:1].astype(np.float32),
                                 p[:, 1:2].astype(np.float32), cv2.INTER_LINEAR,
                                 borderMode=cv2.BORDER_REPLICATE)[:, 0] for p in sides)
    return inside, outside


def _finite_max(v: np.ndarray) -> float:
    """The largest finite value of ``v`` (NaN when there is none): np.nanmax's value."""
    f = v[np.isfinite(v)]
    return float(f.max()) if f.size else math.nan


def _point_sigma(ln: Line, p: np.ndarray) -> float:
    """:meth:`Line.point_sigma` in scalar arithmetic (it runs eight times a frame)."""
    m = float(p[1] if ln.vertical else p[0])
    c = ln.cov_ab
    var = float(c[0, 0]) + m * (float(c[0, 1]) + float(c[1, 0])) + m * m * float(c[1, 1])
    return math.sqrt(max(var, 0.0)) * abs(float(ln.n[0] if ln.vertical else ln.n[1]))


def _outside_signs(lines: list[Line | None], corners: np.ndarray) -> list[int]:
    """Per side: +1 where the outside is brighter than the inside, -1 where darker."""
    ctr = corners.sum(axis=0) / len(corners)
    out = []
    for ln in lines:
        if ln is None:
            continue
        # Line.contrast is the level change toward increasing minor coordinate (x for
        # row-fitted sides, y for column-fitted ones); the inside is where the centre is
        minor_ctr = ctr[0] if ln.vertical else ctr[1]
        at = float(ln.minor_at(ctr[1] if ln.vertical else ctr[0]))
        toward_plus_is_out = minor_ctr < at
        out.append(int(np.sign(ln.contrast if toward_plus_is_out else -ln.contrast)))
    return out


def _one_strip_reversed(signs: list[int], strip_side: int | None) -> bool:
    """Whether the sides' contrasts differ only at ``strip_side``, the other three alike."""
    if strip_side is None or len(signs) != 4:
        return False
    others = {v for k, v in enumerate(signs) if k != strip_side}
    return len(others) == 1 and signs[strip_side] != next(iter(others))


def _strip_side(gray: np.ndarray, sides: list[tuple[Line | None, EdgePoints]],
                corners: np.ndarray, lens: Lens | None) -> int | None:
    """The side beside which a strip lies, contrasting the other way from the holder's
    surroundings: None unless exactly one side's edge contrasts against the other three
    and the image beyond it steps back to their surroundings' level (:func:`_strip_beside`).

    A holder between two levels (a grey aluminium holder on a dark disc with a white
    sample along one side; a dark holder on a light disc with a black one) has that side
    stepping up while the others step down: such a box was refused as straddling two
    objects. Beyond the strip the image steps back to the disc, and the holder and its
    strip make one outline, which a box across two objects does not."""
    if any(ln is None for ln, _pts in sides):
        return None
    c = corners if lens is None else lens.undistort(corners)
    signs = _outside_signs([ln for ln, _pts in sides], c)
    alone = [k for k, v in enumerate(signs) if signs.count(v) == 1]
    if len(alone) != 1:  # all alike, or two and two
        return None
    return alone[0] if _strip_beside(gray, corners, alone[0]) else None


# the strip beside a side: its levels read over the middle 80 % of the side, the face
# _STRIP_IN px inside, the surroundings _STRIP_OUT px outside the other sides; the strip
# may be up to _STRIP_MAX of the adjacent sides' length wide (a sample 3-10 mm against a
# holder 20-100 mm deep), and beyond it the image must be back on the surroundings' side
# of the face level by half their difference, over _STRIP_RUN px
_STRIP_IN, _STRIP_OUT, _STRIP_MAX, _STRIP_RUN = (-8.0, -3.0), (4.0, 9.0), 0.6, 4.0
# ... and the strip itself, from _STRIP_NEAR px beyond the side, must differ from the face
# by _STRIP_MIN_DN the other way (a strip 8 px wide, blurred, stays short of its level)
_STRIP_NEAR, _STRIP_MIN_DN = (1.5, 9.0), 5.0


def _strip_beside(gray: np.ndarray, corners: np.ndarray, k: int) -> bool:
    """Whether side ``k`` of the quadrilateral has a strip beside it whose far edge steps
    back to the level outside the other three sides (see :func:`_strip_side`)."""
    c = np.asarray(corners, float)
    ctr = c.mean(axis=0)
    lengths = _side_lengths(c)
    reach = _STRIP_MAX * float(lengths[(k + 1) % 4] + lengths[(k + 3) % 4]) / 2
    d = np.arange(_STRIP_IN[0], reach + _STRIP_RUN + 0.5, 0.5, dtype=np.float32)
    t = np.linspace(0.1, 0.9, 32, dtype=np.float32)
    levels = []
    for i in range(4):
        a, b = c[i], c[(i + 1) % 4]
        along = b - a
        n = np.array([-along[1], along[0]]) / (np.hypot(*along) or 1.0)
        if np.dot((a + b) / 2 - ctr, n) < 0:
            n = -n  # outward
        dist = d if i == k else d[d <= _STRIP_OUT[1]]
        p = a[None, None] + t[:, None, None] * along[None, None] + \
            dist[None, :, None] * n[None, None]
        prof = cv2.remap(gray.astype(np.float32, copy=False), p[..., 0].astype(np.float32),
                         p[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
        levels.append((dist, np.median(prof, axis=0)))  # across the side, robust to clutter
    face = float(np.median([np.median(lv[(x >= _STRIP_IN[0]) & (x <= _STRIP_IN[1])])
                            for x, lv in levels]))
    around = float(np.median([np.median(lv[(x >= _STRIP_OUT[0]) & (x <= _STRIP_OUT[1])])
                              for i, (x, lv) in enumerate(levels) if i != k]))
    x, lv = levels[k]
    # the strip's level: its extreme just beyond the side (a narrow strip, blurred, may
    # not reach its own level anywhere)
    toward = float(np.sign(around - face))
    near = lv[(x >= _STRIP_NEAR[0]) & (x <= _STRIP_NEAR[1])]
    if float(np.min((near - face) * toward)) > -_STRIP_MIN_DN:
        return False  # no strip of the other contrast just beyond the side
    back = (lv - face) * toward >= 0.5 * abs(around - face)
    run = max(1, round(_STRIP_RUN / 0.5))
    beyond = back & (x > _STRIP_NEAR[0])
    return bool(np.any(np.convolve(beyond, np.ones(run), "valid") >= run))


def _convex(c: np.ndarray) -> bool:
    d = c[_NEXT] - c  # side k: corner k to k + 1
    e = d[_NEXT]
    cr = d[:, 0] * e[:, 1] - d[:, 1] * e[:, 0]  # (each corner's turn, as _cross)
    return bool(np.all(cr > 0) or np.all(cr < 0))


# ---- sample yaw --------------------------------------------------------------------------
@dataclass(frozen=True)
class YawMeasurement:
    """The sample face line in the top view and its yaw from the turntable zero direction."""

    ok: bool
    face_angle_deg: float  # image direction of the face line (deg, x toward y)
    yaw_deg: float  # face angle - turntable angle - zero direction, in (-90, 90]
    face_px: np.ndarray  # (2, 2) end points of the measured face segment
    offset_px: float  # distance of the face from the holder side it is mounted on
    side: int  # holder side (0 = corners 0-1, 2 = corners 2-3) carrying the sample
    rms_px: float
    reason: str = ""


def measure_yaw(image: np.ndarray, det: HolderDetection, turntable_deg: float = 0.0,
                zero_direction_deg: float = 0.0, *, max_offset_px: float = 80.0,
                min_contrast: float = 15.0) -> YawMeasurement:
    """Find the sample face: the strongest edge parallel to a long holder side, outside it.

    The yaw is the face's image angle minus the turntable angle (image rotation by +a
    turns directions by +a in the design's convention) minus the turntable's zero
    direction in the image (a calibration constant, 0 when the image x axis is it).
    """
    nan2 = np.full((2, 2), np.nan)
    if not det.ok:
        return YawMeasurement(False, math.nan, math.nan, nan2, math.nan, -1, math.nan,
                              "holder not detected")
    gray = as_gray(image, "top image")
    c = det.corners_px
    best = None
    for side in (0, 2):
        p0, p1 = c[side], c[(side + 1) % 4]
        t = (p1 - p0) / np.linalg.norm(p1 - p0)
        n = np.array([-t[1], t[0]])
        if np.dot(det.center_px - p0, n) > 0:
            n = -n  # outward
        s = np.linspace(0.15, 0.85, 64)
        base = p0[None] + s[:, None] * (p1 - p0)[None]
        off = np.arange(0.0, max_offset_px, 1.0)
        mx = (base[None, :, 0] + off[:, None] * n[0]).astype(np.float32)
        my = (base[None, :, 1] + off[:, None] * n[1]).astype(np.float32)
        prof = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        mean = prof.mean(axis=1).astype(float)
        grad = np.gradient(mean)
        start = 5
        if mean.size <= start + 3:
            continue
        k = start + int(np.argmax(np.abs(grad[start:])))
        step = abs(float(mean[min(k + 3, mean.size - 1)] - mean[max(k - 3, 0)]))
        if step < min_contrast:
            continue
        if best is None or step > best[0]:
            best = (step, side, float(off[k]), p0 + off[k] * n, p1 + off[k] * n)
    if best is None:
        return YawMeasurement(False, math.nan, math.nan, nan2, math.nan, -1, math.nan,
                              "no sample face found beside the holder")
    _, side, offset, q0, q1 = best
    ln = fit_line(edge_points(gray, q0, q1, half_width=5, margin_px=12.0,
                              min_contrast=min_contrast))
    if ln is None or ln.rms_px > 0.5:
        return YawMeasurement(False, math.nan, math.nan, nan2, offset, side, math.nan,
                              "sample face edge could not be fitted")
    ang = ln.angle_deg
    ref = _quad_angle(c)
    ang = ang + 180.0 * round((ref - ang) / 180.0)  # same sense as the holder angle
    yaw = (ang - turntable_deg - zero_direction_deg + 90.0) % 180.0 - 90.0
    ends = np.array([q0, q1])
    if ln.vertical:
        face = np.column_stack([ln.minor_at(ends[:, 1]), ends[:, 1]])
    else:
        face = np.column_stack([ends[:, 0], ln.minor_at(ends[:, 0])])
    return YawMeasurement(True, float(ang), float(yaw), face, offset, side, ln.rms_px)
