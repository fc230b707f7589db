"""Sub-pixel straight-edge measurement shared by the holder, side-camera and rim analysis.

The edge locator is the *area method*: along a pixel column (or row) crossing an edge, the
sum of the normalised intensities ``(P_j - E) / (S - E)`` (S, E the levels at the start and
the end of the window) equals the distance from the window start to the edge crossing. For
the pixel-area (box) sampling of a camera, and any symmetric blur, this is exact for a
straight edge at any angle, so it has none of the "pixel locking" bias of gradient-peak or
centroid interpolation. The levels are estimated from the window tails, smoothed along the
edge (so a lighting gradient or a soft shadow crossing the edge is followed) and extrapolated
across the window with the edge's mean illumination slope.

Columns are used for edges within 45 deg of horizontal, rows otherwise; errors are then in
one image coordinate only, so the line fit is an ordinary least-squares fit of that
coordinate, with iterative rejection of outlying columns (specks, shadow boundaries).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from contextvars import ContextVar
from dataclasses import dataclass

import cv2
import numpy as np

from alignd.errors import VisionError
from drivers.config import ToneCurve
from drivers.tone_curves import decode, is_linear

__all__ = ["ColumnJudging", "EdgePoints", "Line", "adaptive_slope", "adaptive_slopes",
           "area_crossings", "area_crossings_many", "as_gray", "check_usable", "coarse_edge",
           "coarse_edges_many", "column_judging", "despeckle", "edge_points",
           "edge_points_many", "edge_rows", "fit_line", "intersect", "judged_by_median",
           "linearise", "residual_correlation", "segment_median", "sensor_full_scale",
           "speck_mask", "xy_columns"]


def as_gray(image: np.ndarray, what: str = "image") -> np.ndarray:
    """A 2-D float32 copy of ``image`` (BGR/BGRA converted to grey)."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] in (3, 4):
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.ndim != 2 or img.shape[0] < 16 or img.shape[1] < 16:
        raise VisionError(f"{what}: expected a 2-D (grey) or BGR image of at least 16 x 16 px, "
                          f"got shape {np.asarray(image).shape}")
    if img.dtype == np.uint16:
        # 10/12/14-bit cameras deliver 16-bit words, LSB- or MSB-aligned: express levels in
        # 8-bit DN of the sensor's own full scale so thresholds mean the same everywhere
        return img.astype(np.float32) * np.float32(255.0 / sensor_full_scale(img))
    return img.astype(np.float32)


SPECK_DN = 20.0  # a pixel this far (8-bit DN) above all 8 neighbours or below them is a speck
_RING = np.ones((3, 3), np.uint8)
_RING[1, 1] = 0
_SPECK_ROWS = 64


def speck_mask(gray: np.ndarray) -> np.ndarray:
    """1 where a pixel of ``gray`` (2-D, 8-bit or float in 8-bit DN) is a speck (see
    :func:`despeckle`), else 0, in ``gray``'s dtype."""
    # how far each pixel stands above its neighbours' largest or below their smallest
    # (OpenCV throughout: a frame without specks costs two 3 x 3 passes and a count), in
    # stripes of _SPECK_ROWS rows with a row of their neighbours either side: a stripe's
    # intermediates stay in the cache, where a whole frame's went out to memory and back
    # six times (a 1280 x 720 float frame: 7.9 ms whole, 1.5 ms in stripes)
    h = gray.shape[0]
    mask = np.empty(gray.shape, gray.dtype)
    for y0 in range(0, h, _SPECK_ROWS):
        y1 = min(y0 + _SPECK_ROWS, h)
        a = max(y0 - 1, 0)
        g = gray[a:min(y1 + 1, h)]
        out_of = cv2.max(cv2.subtract(g, cv2.dilate(g, _RING)),
                         cv2.subtract(cv2.erode(g, _RING), g))
        mask[y0:y1] = cv2.threshold(out_of, SPECK_DN, 1, cv2.THRESH_BINARY)[1][
            y0 - a:y1 - a]
    return mask


def despeckle(gray: np.ndarray, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """``gray`` (2-D, 8-bit or float in 8-bit DN) with its specks replaced by the median of
    their 8 neighbours (within ``box``, x0, y0, x1, y1 exclusive, if given); ``gray``
    itself where it has none.

    A speck is a pixel more than :data:`SPECK_DN` above the largest of its 8 neighbours
    or below the smallest: a hot or dead sensor pixel (cameras without defect correction,
    scientific and raw machine-vision ones) or a glint smaller than a pixel. No edge makes
    one (a pixel on an edge has a brighter neighbour on one side and a darker one on the
    other), nor does a line a pixel wide (its neighbours along it are like it), nor noise
    of a few DN. Inside an edge's window a speck moves that column's crossing: 0.1 % of
    the pixels hot and 0.1 % dead put the corpus's corners 0.052 px RMS off (0.56 at
    most), against 0.031 without them."""
    h, w = gray.shape
    x0, y0, x1, y1 = (0, 0, w, h) if box is None else (
        max(box[0], 0), max(box[1], 0), min(box[2], w), min(box[3], h))
    if x1 - x0 < 3 or y1 - y0 < 3:
        return gray
    mask = speck_mask(gray[y0:y1, x0:x1])
    if cv2.countNonZero(mask) == 0:
        return gray
    ys, xs = np.nonzero(mask)
    ys, xs = ys + y0, xs + x0
    dy, dx = np.nonzero(_RING)
    ny = np.clip(ys[:, None] + dy[None, :] - 1, 0, h - 1)
    nx = np.clip(xs[:, None] + dx[None, :] - 1, 0, w - 1)
    out = gray.copy()
    med = np.median(gray[ny, nx], axis=1)
    out[ys, xs] = (np.rint(med) if gray.dtype == np.uint8 else med).astype(gray.dtype)
    return out


def linearise(image: np.ndarray, gamma: ToneCurve) -> np.ndarray:
    """``image`` with a camera's tone curve undone: a value v of full scale F (8-bit, the
    sensor's bits in 16-bit words, or float in 8-bit DN) becomes 255 (v / F)^gamma, or the
    light a named curve ("srgb", "bt709": :mod:`drivers.tone_curves`) gives for v / F,
    float32 in 8-bit DN of light; ``gamma`` 1 returns ``image`` itself.

    Every edge model here takes a pixel's value to be proportional to the light on it (a
    blurred step's profile is point-symmetric about the edge). A camera that encodes its
    values as (light)^(1/gamma), as webcams and UVC cameras do (about 2.2), bends the
    profile: corners read 0.3 px off (RMS; up to 1.7 px) on the corpus's frames drawn so,
    0.034 px once undone. BT.709 frames: 0.34 px as they are, 0.049 undone as a pure
    power of 1.9, 0.037 by name (linear frames 0.037)."""
    if is_linear(gamma):
        return image
    if not isinstance(gamma, str) and not (math.isfinite(gamma) and 1.0 <= gamma <= 3.0):
        raise VisionError(f"the camera's gamma must be within 1-3, got {gamma!r}")
    img = np.asarray(image)
    if img.ndim == 3:
        img = as_gray(img)
    if img.dtype == np.uint8:
        return (255.0 * decode(np.arange(256, dtype=np.float32) / 255.0, gamma)).astype(
            np.float32)[img]
    full = sensor_full_scale(img) if img.dtype == np.uint16 else 255.0
    return (np.float32(255.0) * decode(img.astype(np.float32) / np.float32(full), gamma)
            ).astype(np.float32)


def sensor_full_scale(img: np.ndarray) -> float:
    """Full scale of a 16-bit image: 2^bits - 1 for the smallest of 8, 10, 12, 14 or 16
    bits holding its maximum, on the sensor's native grid (MSB-aligned words, whose low
    bits are all zero, count as 16 bit)."""
    a = np.asarray(img)
    top = int(a.max()) if a.size else 0
    for bits in (8, 10, 12, 14):
        if top <= (1 << bits) - 1:
            return float((1 << bits) - 1)
    return 65535.0


_BLANK_BLOCK = 8  # px: the blocks whose means judge a frame blank (check_usable)


def _block_means(gray: np.ndarray, k: int) -> np.ndarray:
    """The means of the whole k x k px blocks of ``gray`` (a frame smaller than a block:
    the frame itself)."""
    h, w = (gray.shape[0] // k) * k, (gray.shape[1] // k) * k
    if h == 0 or w == 0:
        return np.asarray(gray, np.float64)
    g = np.ascontiguousarray(gray[:h, :w], np.float32)
    return cv2.resize(g, (w // k, h // k), interpolation=cv2.INTER_AREA)  # exact block means


def check_usable(gray: np.ndarray, min_contrast: float, what: str = "image",
                 full_scale: float = 255.0) -> None:
    """Raise VisionError for a blank (featureless) or mostly saturated image.

    Blank is judged on the means of 8 x 8 px blocks (the noise averaged 8-fold), over their
    whole range: a target of any size worth finding fills a block, however small a part of
    the frame it is. (A 1-99 % range of the pixels called a frame blank whose holder
    covered under 1 % of it: a 195 x 98 px holder in a 1920 x 1080 frame.)"""
    blocks = _block_means(gray, _BLANK_BLOCK)
    lo, hi = float(blocks.min()), float(blocks.max())
    if hi - lo < min_contrast:
        raise VisionError(f"{what}: blank image (intensity range {hi - lo:.1f} DN over "
                          f"{_BLANK_BLOCK} x {_BLANK_BLOCK} px block means < "
                          f"{min_contrast:.0f} DN); no target can be found")
    sub = gray[::8, ::8].ravel()
    sat = float(np.mean(sub >= full_scale - 0.5))
    if sat > 0.5:
        raise VisionError(f"{what}: {100 * sat:.0f} % of the image is saturated; "
                          "reduce exposure or light")


@dataclass(frozen=True)
class Line:
    """A line n . p = d (n unit normal) with its fit statistics."""

    n: np.ndarray
    d: float
    rms_px: float
    n_points: int
    n_used: int
    cov_ab: np.ndarray  # covariance of (a, b) of minor = a + b * major
    vertical: bool  # True: fitted as x = a + b y (rows); False: y = a + b x (columns)
    major_span: tuple[float, float]
    contrast: float  # median end-minus-start level across the edge (signed)

    def minor_sigma_at(self, major: float) -> float:
        """Standard error of the line's minor coordinate at ``major``."""
        v = np.array([1.0, major])
        return float(math.sqrt(max(v @ self.cov_ab @ v, 0.0)))

    def point_sigma(self, p: np.ndarray) -> float:
        """Standard error of the line position (normal direction) near point p."""
        major = float(p[1] if self.vertical else p[0])
        return self.minor_sigma_at(major) * abs(self.n[0] if self.vertical else self.n[1])

    @property
    def angle_deg(self) -> float:
        """Direction of the line (deg, x toward y), in (-90, 90]."""
        a = math.degrees(math.atan2(self.n[0], -self.n[1]))
        return (a + 90.0) % 180.0 - 90.0

    def minor_at(self, major: np.ndarray | float) -> np.ndarray:
        if self.vertical:  # n0 x + n1 y = d -> x = (d - n1 y) / n0
            return (self.d - self.n[1] * np.asarray(major, float)) / self.n[0]
        return (self.d - self.n[0] * np.asarray(major, float)) / self.n[1]


@dataclass(frozen=True)
class EdgePoints:
    """Sub-pixel crossings of an edge, one per column (or row)."""

    xy: np.ndarray  # (N, 2)
    contrast: np.ndarray  # (N,) end level minus start level (DN), signed
    vertical: bool


def _mean_of(rows: np.ndarray) -> np.ndarray:
    """The mean of a few rows, added in order: for fewer than 8 the same sum as np.mean's
    over that axis, without a reduction's loop per column."""
    s = rows[0]
    for r in rows[1:]:
        s = s + r
    return s / len(rows)


def _nan_to_zero(v: np.ndarray) -> np.ndarray:
    """``v`` with NaN as 0 (np.nan_to_num for arrays without infinities, at less cost)."""
    return np.where(np.isnan(v), 0.0, v)


def edge_rows(good: np.ndarray, seg: np.ndarray, n_seg: int) -> list[np.ndarray]:
    """The indices of the ``good`` rows of each segment (``seg`` non-decreasing, 0 ..
    n_seg - 1): one pass over the rows, not a mask per segment."""
    idx = np.flatnonzero(good)
    counts = np.bincount(seg[idx], minlength=n_seg)
    return np.split(idx, np.cumsum(counts)[:-1])


def xy_columns(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The (N, 2) array of columns a and b (np.column_stack of two 1-D arrays)."""
    out = np.empty((a.size, 2))
    out[:, 0] = a
    out[:, 1] = b
    return out


def _moving_mean(v: np.ndarray, k: int) -> np.ndarray:
    """Mean over +-k along the last axis, truncated at the ends (k at most (n - 1) / 2)."""
    n = v.shape[-1]
    k = min(k, (n - 1) // 2)
    if n == 0 or k <= 0:
        return v
    csum = np.concatenate([np.zeros((*v.shape[:-1], 1)), np.cumsum(v, axis=-1)], axis=-1)
    i = np.arange(n)
    lo, hi = np.maximum(i - k, 0), np.minimum(i + k, n - 1)
    return (csum[..., hi + 1] - csum[..., lo]) / (hi - lo + 1)


def _median(v: np.ndarray) -> float:
    """Median of a 1-D array (the upper one for even sizes), without np.median's overhead."""
    v = np.asarray(v).ravel()
    if v.size == 0:
        return math.nan
    k = v.size // 2
    return float(np.partition(v, k)[k])


_SLOPE_SE = 3.0  # an edge's mean slope is shrunk toward 0 by its standard error times this


def _shrink(g: np.ndarray | float, se: np.ndarray | float) -> np.ndarray:
    """An edge's mean illumination slope g shrunk toward zero as g^2 / (g^2 + (c se)^2).

    One slope serves every column of the edge, so its noise is common to all of them: it
    shifts the whole edge (its level, extrapolated from the tails to the crossing, moves
    by the slope's error times a few pixels) and no scatter along the line reveals it.
    Where the slope is not clearly above its noise (no real gradient: only the sensor
    noise of the 3-pixel tails) it costs more than it corrects, and is taken near zero;
    a real gradient or penumbra, many standard errors strong, is kept almost whole.
    """
    g = np.asarray(g, float)
    c2 = (_SLOPE_SE * np.asarray(se, float)) ** 2
    return g * (g * g) / (g * g + c2 + 1e-30)


def adaptive_slope(v: np.ndarray, k: int) -> np.ndarray:
    """Per-column slope: the edge's robust mean (shrunk by :func:`_shrink`), replaced by
    the local (moving) mean over +-k columns only where that differs from the mean by
    more than 4 of its own standard errors (one value per edge, whose noise would
    otherwise tilt the line, except where a shadow's penumbra crosses the edge)."""
    g, n_kept, sd = _robust_mean_n(v)
    gs = float(_shrink(g, sd / math.sqrt(max(n_kept, 1))))
    if v.size < 3 or k <= 0:
        return np.full(v.shape, gs)
    loc = _moving_mean(v, k)
    sig = float(_median(np.abs(v - _median(v)))) * 1.4826 / math.sqrt(2 * k + 1)
    return np.where(np.abs(loc - g) > 4 * sig + 1e-9, loc, gs)


def segment_median(v: np.ndarray, seg: np.ndarray, n_seg: int, *, upper: bool = True
                   ) -> np.ndarray:
    """The median of each segment of ``v``: for an even count the upper of the middle two
    (as :func:`_median`) or, ``upper`` False, their mean (as np.median); ``seg``
    (non-decreasing, 0 .. n_seg - 1) names each value's segment. NaN for an empty
    segment."""
    counts = np.bincount(seg, minlength=n_seg)
    if v.size == 0:
        return np.full(n_seg, np.nan)
    # the segments as the rows of one array padded with +inf (sorting last): a partition
    # of every row at the middle positions (a sort of all the values cost several times
    # as much)
    rows = np.full((n_seg, int(counts.max())), np.inf)
    rows[seg, np.arange(v.size) - (np.cumsum(counts) - counts)[seg]] = v
    hi = counts // 2
    lo = np.maximum((counts - 1) // 2, 0)
    rows.partition(np.concatenate([hi, lo]) if not upper else hi, axis=1)
    out = rows[np.arange(n_seg), hi]
    if not upper:
        out = 0.5 * (out + rows[np.arange(n_seg), lo])
    out[counts == 0] = np.nan
    return out


def adaptive_slopes(v: np.ndarray, seg: np.ndarray, n_seg: int, k: int) -> np.ndarray:
    """:func:`adaptive_slope` of several edges in one batch (a few array operations in all,
    not per edge); ``seg`` (non-decreasing, 0 .. n_seg - 1) names each column's edge."""
    v = np.asarray(v, float)
    if v.size == 0:
        return v.copy()
    counts = np.bincount(seg, minlength=n_seg)
    starts = np.cumsum(counts) - counts
    med = segment_median(v, seg, n_seg)
    dev = np.abs(v - med[seg])
    mad = _nan_to_zero(segment_median(dev, seg, n_seg)) * 1.4826
    keep = dev <= 4.0 * (mad + 1e-9)[seg]
    nk = np.bincount(seg, weights=keep, minlength=n_seg)
    sk = np.bincount(seg, weights=np.where(keep, v, 0.0), minlength=n_seg)
    g_e = np.where(nk > 0, sk / np.maximum(nk, 1.0), med)
    g = g_e[seg]
    gs = _shrink(g_e, _nan_to_zero(mad) / np.sqrt(np.maximum(nk, 1.0)))[seg]
    if k <= 0:
        return gs
    loc = _segment_moving_mean(v, seg, counts, starts, k)
    sig = (mad / math.sqrt(2 * k + 1))[seg]
    return np.where((counts[seg] >= 3) & (np.abs(loc - g) > 4.0 * sig + 1e-9), loc, gs)


def _robust_mean_n(v: np.ndarray) -> tuple[float, int, float]:
    """Mean of v without its outliers (beyond 4 robust sigma of the median), the number
    of values it kept and their robust sigma."""
    if v.size == 0:
        return 0.0, 0, 0.0
    med = float(_median(v))
    mad = float(_median(np.abs(v - med))) * 1.4826
    keep = np.abs(v - med) <= 4 * (mad + 1e-9)
    n = int(np.count_nonzero(keep))
    return (float(v[keep].mean()) if n else med), n, mad


def _edge_columns(shape: tuple[int, int], p0: np.ndarray, p1: np.ndarray, margin_px: float,
                  vertical: bool | None) -> tuple[np.ndarray, np.ndarray, bool]:
    """The columns (rows) ``t`` a segment crosses, ends trimmed by ``margin_px``, and its
    predicted minor coordinate ``c`` in each."""
    p0 = np.asarray(p0, float)
    p1 = np.asarray(p1, float)
    dx, dy = p1 - p0
    if vertical is None:
        vertical = bool(abs(dy) > abs(dx))
    h, w = shape
    if vertical:  # rows: major = y, minor = x
        ma0, ma1, mi0, mi1, limit_major = p0[1], p1[1], p0[0], p1[0], h
    else:
        ma0, ma1, mi0, mi1, limit_major = p0[0], p1[0], p0[1], p1[1], w
    if ma1 < ma0:
        ma0, ma1, mi0, mi1 = ma1, ma0, mi1, mi0
    length = math.hypot(dx, dy)
    trim = margin_px * abs(ma1 - ma0) / max(length, 1e-9)
    t = np.arange(math.ceil(ma0 + trim), math.floor(ma1 - trim) + 1)
    t = t[(t >= 0) & (t < limit_major)]
    if t.size < 3 or ma1 - ma0 < 1e-9:
        return np.empty(0, int), np.empty(0), vertical
    return t, mi0 + (t - ma0) * (mi1 - mi0) / (ma1 - ma0), vertical


def edge_points(gray: np.ndarray, p0: np.ndarray, p1: np.ndarray, *, half_width: int = 5,
                margin_px: float = 8.0, tails: int = 3, smooth: int = 3,
                min_contrast: float = 10.0, vertical: bool | None = None) -> EdgePoints:
    """Measure the edge near the segment p0-p1 in every column (or row) it crosses.

    Windows of 2 * half_width + 1 px are centred on the predicted crossing; the segment's
    ends are trimmed by ``margin_px`` (corners, neighbouring edges). Crossings with a level
    difference under ``min_contrast`` or outside the window's middle are dropped.
    """
    return area_crossings_many(gray, [_edge_columns(gray.shape, p0, p1, margin_px, vertical)],
                               half_width=half_width, tails=tails, smooth=smooth,
                               min_contrast=min_contrast)[0]


def edge_points_many(gray: np.ndarray, segments: list[tuple[np.ndarray, np.ndarray]], *,
                     half_width: int = 5, margin_px: float = 8.0, tails: int = 3,
                     smooth: int = 3, min_contrast: float = 10.0) -> list[EdgePoints]:
    """:func:`edge_points` of several segments (p0, p1) in one batch: the same crossings,
    at the cost of one edge's array calls instead of one per edge."""
    return area_crossings_many(
        gray, [_edge_columns(gray.shape, p0, p1, margin_px, None) for p0, p1 in segments],
        half_width=half_width, tails=tails, smooth=smooth, min_contrast=min_contrast)


def area_crossings(gray: np.ndarray, t: np.ndarray, c: np.ndarray, vertical: bool, *,
                   half_width: int = 5, tails: int = 3, smooth: int = 3,
                   min_contrast: float = 10.0) -> EdgePoints:
    """Area-method crossings of an edge (straight or gently curved) predicted at minor
    coordinate ``c`` in each column (row) ``t``; t must run along the edge."""
    return area_crossings_many(gray, [(t, c, vertical)], half_width=half_width, tails=tails,
                               smooth=smooth, min_contrast=min_contrast)[0]


def _segment_moving_mean(v: np.ndarray, seg: np.ndarray, counts: np.ndarray,
                         starts: np.ndarray, k: int) -> np.ndarray:
    """Mean over +-k within each segment, truncated at its ends (k <= (n - 1) / 2)."""
    if v.size == 0 or k <= 0:
        return v
    n = counts[seg]
    ke = np.minimum(k, (n - 1) // 2)
    st = starts[seg]
    pos = np.arange(v.size) - st
    lo, hi = np.maximum(pos - ke, 0), np.minimum(pos + ke, n - 1)
    csum = np.concatenate(([0.0], np.cumsum(v)))
    return (csum[st + hi + 1] - csum[st + lo]) / (hi - lo + 1)


def _segment_moving_median(v: np.ndarray, seg: np.ndarray, counts: np.ndarray,
                           starts: np.ndarray, k: int) -> np.ndarray:
    """Median over +-k within each segment, the window cut at the segment's ends."""
    if v.size == 0 or k <= 0:
        return v
    j = np.arange(v.size)[:, None] + np.arange(-k, k + 1)[None, :]
    first = starts[seg][:, None]
    inside = (j >= first) & (j < first + counts[seg][:, None])
    return np.nanmedian(np.where(inside, v[np.clip(j, 0, v.size - 1)], np.nan), axis=1)


@dataclass
class ColumnJudging:
    """How :func:`area_crossings_many` judges an edge's columns within
    :func:`column_judging`: an edge that loses more than ``lost_share`` of its good columns
    for a step unlike their neighbours' mean is noted (``lost_seen``) and, ``by_median``,
    judged against their median instead. A side passing a dark hole in the floor beyond
    it steps less along the hole, and that run of weaker columns pulls the mean off the
    stronger ones, which go too. Not the default: a rectangle that is not the holder, a
    disc's rim and a cable across its sides, then kept enough of them to pass (corpus
    seed 111100 #993); the top camera's full search measures its boxes so only where
    every box failed and a side of one lost so many (0.25 left one of 288 drawn holders
    beside a floor hole refused, 0.4 none)."""

    lost_share: float = 0.4
    by_median: bool = False
    lost_seen: bool = False


_JUDGING: ContextVar[ColumnJudging | None] = ContextVar("column_judging", default=None)


@contextmanager
def column_judging(judging: ColumnJudging) -> Iterator[ColumnJudging]:
    """Within the block, edges' columns are judged as ``judging`` says (outside any, by
    their neighbours' mean, and nothing is noted)."""
    token = _JUDGING.set(judging)
    try:
        yield judging
    finally:
        _JUDGING.reset(token)


def judged_by_median(lost_share: float = 0.4) -> AbstractContextManager[ColumnJudging]:
    """:func:`column_judging` with an edge that loses more than ``lost_share`` of its
    columns to their neighbours' mean judged against their median instead."""
    return column_judging(ColumnJudging(lost_share, by_median=True))


def area_crossings_many(gray: np.ndarray, edges: list[tuple[np.ndarray, np.ndarray, bool]],
                        *, half_width: int = 5, tails: int = 3, smooth: int = 3,
                        min_contrast: float = 10.0) -> list[EdgePoints]:
    """:func:`area_crossings` of several edges (t, c, vertical) in one batch: every step is
    one array operation over all the columns of all the edges."""
    h, w = gray.shape
    m = 2 * half_width + 1
    out = [EdgePoints(np.empty((0, 2)), np.empty(0), v) for _t, _c, v in edges]
    parts = []
    for k, (t, c, vertical) in enumerate(edges):
        t = np.asarray(t).astype(np.intp)
        c = np.asarray(c, float)
        start = np.round(c).astype(np.intp) - half_width
        ok = (start >= 0) & (start + m <= (w if vertical else h))
        if np.count_nonzero(ok) < 3:
            continue
        t, start = t[ok], start[ok]
        parts.append((np.full(t.size, k), t, start, t * w if vertical else t,
                      np.full(t.size, 1 if vertical else w, np.intp)))
    if not parts:
        return out
    seg, t, start, base, stride = (np.concatenate(p) for p in zip(*parts, strict=True))
    ne = len(edges)
    counts = np.bincount(seg, minlength=ne)
    starts = np.cumsum(counts) - counts
    j = np.arange(m)
    flat = np.ascontiguousarray(gray).ravel()
    # the windows pixel-major (pixel, column): a column's levels then broadcast along the
    # long axis and the sum over a window's pixels adds whole rows (with a window's few
    # pixels along the last axis, numpy runs both as a short loop per column)
    P = flat.take(base + (start + j[:, None]) * stride).astype(np.float64)
    S = _mean_of(P[:tails])
    E = _mean_of(P[-tails:])
    S_s = _segment_moving_mean(S, seg, counts, starts, smooth)
    E_s = _segment_moving_mean(E, seg, counts, starts, smooth)
    js = (tails - 1) / 2
    je = m - 1 - (tails - 1) / 2
    n = seg.size
    if tails >= 2:
        # the illumination slope across each side: one value per edge (its noise would
        # otherwise tilt the line), except where a shadow's penumbra crosses the edge
        wts = np.arange(tails) - js
        wts = wts / float(wts @ wts)
        both = adaptive_slopes(np.concatenate([wts @ P[:tails], wts @ P[-tails:]]),
                               np.concatenate([seg, seg + ne]), 2 * ne, smooth)
        slope_s, slope_e = both[:n], both[n:]
    else:
        slope_s = slope_e = np.zeros(n)
    Sj = S_s + (j[:, None] - js) * slope_s
    Ej = E_s + (j[:, None] - je) * slope_e
    contrast = E_s - S_s
    good = np.abs(contrast) >= min_contrast
    # a column that clips a corner or a neighbouring edge shows a partial step, judged
    # against the contrast of the neighbouring columns (+-15), so that a shadow or
    # vignetting that changes the contrast along the edge is followed
    raw = E - S
    # (an edge without a good column has none to lose: 0 for its median, not NaN, which
    # the running sums would carry into the next edges)
    med = _nan_to_zero(segment_median(raw[good], seg[good], ne))
    filled = np.where(good, raw, med[seg])
    ref = _segment_moving_mean(filled, seg, counts, starts, 15)
    near = np.abs(raw - ref) <= 0.2 * np.abs(ref) + 3.0
    # a run of weaker columns (a side passing a dark hole in the floor beyond it) pulls
    # the mean of +-15 columns off the stronger ones as well, and a side lost most of its
    # columns (a short side 8 of 50: the holder refused, corpus seed 2124 #767): within
    # column_judging, where one loses over its share of its good columns so, that is
    # noted and (by_median) its columns are judged against their neighbours' median
    judging = _JUDGING.get()
    lost = np.zeros(ne, bool) if judging is None else (
        np.bincount(seg, good & ~near, ne) > judging.lost_share * np.bincount(seg, good, ne))
    if judging is not None and lost.any():
        judging.lost_seen = True
    if judging is not None and judging.by_median and lost.any():
        again = lost[seg]
        ref_m = _segment_moving_median(filled, seg, counts, starts, 15)
        near = np.where(again, np.abs(raw - ref_m) <= 0.2 * np.abs(ref_m) + 3.0, near)
    good &= near
    denom = Sj - Ej
    denom = np.where(good & (np.abs(denom) > 1e-6), denom, 1.0)
    frac = (P - Ej) / denom
    pos = start - 0.5 + np.ones(m) @ frac
    rel = pos - start
    good &= (rel > tails) & (rel < m - 1 - tails)
    # the profile must be a single step: no sample far outside the level range
    lo = np.minimum(Sj, Ej) - 0.35 * np.abs(contrast)
    hi = np.maximum(Sj, Ej) + 0.35 * np.abs(contrast)
    good &= np.all((lo < P) & (hi > P), axis=0)
    for k, sel in enumerate(edge_rows(good, seg, ne)):
        if sel.size == 0:
            continue
        tk, pk = t[sel].astype(float), pos[sel]
        vertical = edges[k][2]
        xy = xy_columns(pk, tk) if vertical else xy_columns(tk, pk)
        out[k] = EdgePoints(xy, contrast[sel], vertical)
    return out


def coarse_edge(gray: np.ndarray, p0: np.ndarray, p1: np.ndarray, *, search_px: int = 10,
                margin_px: float = 12.0, min_step: float = 10.0) -> Line | None:
    """Locate an edge within +-search_px of the segment p0-p1 to about a pixel: the
    strongest step of each column (row), then a robust line. Seeds :func:`edge_points`."""
    return coarse_edges_many(gray, [(p0, p1)], search_px=search_px, margin_px=margin_px,
                             min_step=min_step)[0]


def coarse_edges_many(gray: np.ndarray, segments: list[tuple[np.ndarray, np.ndarray]], *,
                      search_px: int = 10, margin_px: float = 12.0, min_step: float = 10.0
                      ) -> list[Line | None]:
    """:func:`coarse_edge` of several segments (p0, p1) in one batch (one gather and one
    step search for all their columns; a line fit per edge)."""
    h, w = gray.shape
    m = 2 * search_px + 1
    parts = []
    vert = []
    for k, (p0, p1) in enumerate(segments):
        t, c, vertical = _edge_columns(gray.shape, p0, p1, margin_px, None)
        vert.append(vertical)
        start = np.round(c).astype(np.intp) - search_px
        ok = (start >= 0) & (start + m <= (w if vertical else h))
        if np.count_nonzero(ok) < 8:
            continue
        t, start = t[ok].astype(np.intp), start[ok]
        parts.append((np.full(t.size, k), t, start, t * w if vertical else t,
                      np.full(t.size, 1 if vertical else w, np.intp)))
    out: list[Line | None] = [None] * len(segments)
    if not parts:
        return out
    seg, t, start, base, stride = (np.concatenate(p) for p in zip(*parts, strict=True))
    flat = np.ascontiguousarray(gray).ravel()
    # pixel-major (pixel, column), as in area_crossings_many
    P = flat.take(base + (start + np.arange(m)[:, None]) * stride).astype(np.float32)
    P = (P[:-2] + P[1:-1] + P[2:]) / 3  # a little smoothing against noise
    D = np.diff(P, axis=0)
    # one sign per edge: the dominant one
    ne = len(segments)
    up = segment_median(D.max(axis=0), seg, ne) >= segment_median(-D.min(axis=0), seg, ne)
    sign = np.where(up, 1.0, -1.0).astype(np.float32)[seg]
    SD = sign * D
    k = np.argmax(SD, axis=0)
    step = SD[k, np.arange(SD.shape[1])]
    pos = (start + k + 1.5).astype(float)
    tf = t.astype(float)
    # (an edge without columns gets no points, and no line)
    for e, sel in enumerate(edge_rows(step * 3 >= min_step, seg, ne)):
        xy = xy_columns(pos[sel], tf[sel]) if vert[e] else xy_columns(tf[sel], pos[sel])
        out[e] = fit_line(EdgePoints(xy, step[sel], vert[e]), reject_sigma=3.0, min_points=8,
                          min_sigma=0.7, start=_consensus(tf[sel], pos[sel]))
    return out


def _consensus(major: np.ndarray, minor: np.ndarray, band: float = 1.5, pairs: int = 24
               ) -> np.ndarray | None:
    """The points within ``band`` px of the line most of them lie on (None: too few).

    A run of columns whose strongest step is another edge (a floor hole or a shadow
    touching the side: a third of a short side, all at one end) tilts a least-squares
    line so far that its residuals' spread hides them, and the rejection keeps them. The
    lines through point pairs half the points apart (at most ``pairs`` of them, evenly
    spread: a run of outliers at one end, a fraction f of the points, still leaves 1 - 2f
    of them with both points on the edge) are each scored by the points within the band
    (one matrix); the best one's inliers start the fit, which may take any point back.
    """
    n = major.size
    half = n // 2
    if half < 4:
        return None
    i = np.unique(np.linspace(0, n - half - 1, min(n - half, pairs)).astype(np.intp))
    j = i + half
    slope = (minor[j] - minor[i]) / (major[j] - major[i])
    pred = minor[i, None] + (major[None] - major[i, None]) * slope[:, None]  # (pairs, n)
    near = np.abs(minor[None] - pred) <= band
    best = near[int(np.argmax(near.sum(axis=1)))]
    return best if int(np.count_nonzero(best)) >= 8 else None


def fit_line(pts: EdgePoints, *, reject_sigma: float = 3.5, min_points: int = 8,
             iterations: int = 4, min_sigma: float = 0.01, start: np.ndarray | None = None,
             slope: tuple[float, float] | None = None) -> Line | None:
    """Least-squares line minor = a + b * major with iterative robust rejection;
    ``start`` (bool per point): the points the first fit uses (default: all); ``slope``:
    b and its variance, known from elsewhere (only a is fitted; see
    :mod:`alignd.vision.holder_square`)."""
    n_pts = pts.xy.shape[0]
    if n_pts < min_points:
        return None
    k = 1 if pts.vertical else 0
    major, minor = pts.xy[:, k], pts.xy[:, 1 - k]
    m0 = float(major.sum()) / n_pts  # (np.mean's sum and division, without its overhead)
    u = major - m0
    use: np.ndarray | None = None  # None: every point
    if start is not None and not bool(start.all()):
        use = start
        iterations += 1  # the start is a guess, not an iteration's result
    uu, vv = (u, minor) if use is None else (u[use], minor[use])
    a0 = b = 0.0
    res = minor
    for _ in range(iterations):
        nu = uu.size
        if nu < min_points:
            return None
        um, vm = float(uu.sum()) / nu, float(vv.sum()) / nu
        if slope is None:
            du = uu - um
            b = float(du @ (vv - vm)) / max(float(du @ du), 1e-12)
        else:
            b = slope[0]
        a0 = vm - b * um
        res = minor - (a0 + b * u)
        ru = res if use is None else res[use]
        h = ru.size // 2  # the upper medians, as _median (inline: this runs most often)
        dev = np.abs(ru - np.partition(ru, h)[h])
        mad = float(np.partition(dev, h)[h]) * 1.4826
        new = np.abs(res) < reject_sigma * max(mad, min_sigma)
        same = bool(new.all()) if use is None else bool((new == use).all())
        if same:
            break
        use = new
        uu, vv = u[use], minor[use]
    n_used = n_pts if use is None else int(np.count_nonzero(use))
    if n_used < min_points:
        return None
    r = res if use is None else res[use]
    uf = u if use is None else u[use]
    s2 = float(r @ r) / max(n_used - (2 if slope is None else 1), 1)
    s_u, s_uu = float(uf.sum()), float(uf @ uf)
    if slope is not None:
        # a = (the points' mean) - b (their mean major): b's variance enters at that lever
        um, vb = s_u / n_used, slope[1]
        cov_c = np.array([[s2 / n_used + um * um * vb, -um * vb], [-um * vb, vb]])
    else:
        # covariance of (a, b) of the centred fit, by the 2 x 2 normal matrix's inverse
        det = n_used * s_uu - s_u * s_u
        if abs(det) < 1e-12:
            return None
        cov_c = (s2 / det) * np.array([[s_uu, -s_u], [-s_u, float(n_used)]])
    # back to a + b * major (un-centred)
    T = np.array([[1.0, -m0], [0.0, 1.0]])
    cov_ab = T @ cov_c @ T.T
    a = a0 - b * m0
    # minor - b * major - a = 0
    # vertical: x - b y = a; else: y - b x = a
    norm = math.hypot(1.0, b)
    nv = np.array([1.0, -b]) / norm if pts.vertical else np.array([-b, 1.0]) / norm
    return Line(n=nv, d=a / norm, rms_px=math.sqrt(s2), n_points=n_pts, n_used=n_used,
                cov_ab=cov_ab, vertical=pts.vertical,
                major_span=(float(major.min()), float(major.max())),
                contrast=float(_median(pts.contrast)))


def intersect(l1: Line, l2: Line) -> np.ndarray:
    """Intersection point of two lines (NaN when parallel)."""
    a, b = float(l1.n[0]), float(l1.n[1])
    c, d = float(l2.n[0]), float(l2.n[1])
    det = a * d - b * c
    if abs(det) < 1e-9:
        return np.array([np.nan, np.nan])
    return np.array([(d * l1.d - b * l2.d) / det, (a * l2.d - c * l1.d) / det])


def residual_correlation(ln: Line, pts: EdgePoints, block: int = 8) -> float:
    """Variance inflation of a line's fit for residuals correlated along the edge.

    The fit's covariance assumes independent columns; JPEG blocks, texture, blur and a
    shadow's penumbra make neighbouring crossings err together, so fewer columns count.
    Batch means: ``block`` times the variance of the residuals' means over runs of
    ``block`` columns, over the residuals' variance (1 for independent columns; >= 1).
    """
    n = pts.xy.shape[0] // block * block
    if n < 4 * block:
        return 1.0
    k = 1 if pts.vertical else 0
    r = pts.xy[:n, 1 - k] - ln.minor_at(pts.xy[:n, k])
    lim = 3.5 * max(ln.rms_px, 1e-6)
    r = np.clip(r, -lim, lim)  # outlying columns the fit rejected
    r = r - r.sum() / r.size
    v = float(r @ r)
    if v <= 0.0:
        return 1.0
    m = r.reshape(-1, block).mean(axis=1)
    return max(block * block * float(m @ m) / v, 1.0)
