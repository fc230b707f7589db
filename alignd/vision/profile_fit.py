"""Sub-pixel edge crossings by fitting the exact pixel model of a blurred step to each
column's (row's) profile.

The area method (:mod:`alignd.vision.edges`) weighs every pixel of its window alike, so the
noise and texture of pixels far from the edge, which carry no position information, enter
its sum in full. Here each column crossing a straight edge is fitted by least squares with

    I(x) = a1 + b1 x + (D + (b2 - b1) x) * S(nu (x - u)),

x the pixel position from the window centre, u the crossing, nu the cosine between the
column and the edge normal (so nu (x - u) is the normal distance), a1 and a1 + D the levels
at the crossing, b1 and b2 the illumination slopes on either side (a lighting gradient,
vignetting, a soft shadow's penumbra on one side). S is the exact response of a camera
pixel to a Gaussian-blurred straight step: the Gaussian edge (width s, one value per edge)
convolved with the pixel square's footprint across the edge, a trapezoid of the widths
|n_x| and |n_y|. With the right shape no sampling phase is favoured (no pixel locking), and
the position information comes from the transition pixels, where the model's slope is, so
the crossing has about half the area method's noise at the blurs of the corpus.

The slopes b1 and b2 come from the window's tails, as in the area method (one value per
edge, followed locally only where a penumbra crosses it): free per column they would cost
the position most of its precision. On a soft edge they are measured again after a first
fit, with the fitted step's own tail taken off and from longer tails: there a slope's error
moves the crossing most (about 16 px per (DN/px) / DN of contrast at a blur of 2 px). The
camera blurs the levels with the step, so a height that changes along the window by A' per
px adds A' Q(d) / nu, Q the blur kernel's first moment beyond d (a bell of area s^2 + the
footprint's variance): left out, it moved the edge by A' (s^2 + ...) / D, 0.03 px at
0.3 DN/px, a 2 px blur and 40 DN. Where a cast shadow's penumbra lies beside a side, its
shoulder bends the floor between the tails and the edge: a blurred step fitted to the
side's floor profile beyond the window tells it, and where it reaches into the window it
is fitted again together with the edge over the whole profile, which places the edge
(:func:`_penumbra_bend`, :func:`_joint_penumbra`). Pixels clipped at the sensor's full
scale (or at zero) say only that the level is beyond the clip and are left out where the
model is beyond it too (:func:`_censored`): read as levels they made a saturated
holder's step look smaller and sharper. The window's residuals are not independent: a
texture coarser than the blur, the lighting's curvature or a penumbra bends it smoothly
where the straight levels do not, so the fit is generalised least squares with such
clutter counted as correlated noise (:func:`_clutter_weights`). The fit starts from the
area method's crossing (good to a tenth of a pixel), so a few Gauss-Newton iterations
suffice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np
from scipy.optimize import leastsq
from scipy.special import expit, ndtr

from alignd.vision.edges import (
    EdgePoints,
    adaptive_slopes,
    edge_rows,
    segment_median,
    xy_columns,
)

__all__ = ["ProfileFit", "disc_edge", "fit_crossings", "fit_crossings_blur", "fit_profiles",
           "step_response"]

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_TAILS = 3
# the position fit's window: the transition out to this many blur widths, then the tails.
# The blur is estimated in a window holding 3 widths (narrower, the tails read part of the
# transition as illumination slope and the blur as 10-20 % smaller at 1.2-2 px); the
# positions fare better in the narrower one (fewer trimmed columns at the corners, less
# floor texture and fewer floor holes in the window): corpus optics scenes 0.085 -> 0.073 px
_FIT_REACH = 1.5
# the tails' slopes are measured again with the fitted step's own tail taken off
# (:func:`_refit_slopes`); on a side softer than _WIDE_BLUR px from tails _EXTRA px longer
# (corpus, uncompressed corner RMS 0.0461 -> 0.0444 px, 1001 scenes)
_WIDE_BLUR, _EXTRA = 1.0, 3
_MISFIT = 2.5  # columns fitted worse than this many times the edge's median are dropped
# the window's smooth clutter (see :func:`_clutter_weights`): its correlation length (px)
# and its variance over the noise's. Corpus, bench seed, 787 uncompressed scenes, corner
# RMS: 0.0377 px without it; lengths 1.5-4 px at ratios 0.5-2 all gave 0.0350-0.0362
# (seed 177: 0.0395 -> 0.0366 at 3 / 1, 0.0373 at 3 / 0.5). The price on a scene without
# clutter (our renderer): white noise weighed as if part were clutter, 0.0058 -> 0.0068 px
_CLUTTER_PX, _CLUTTER_RATIO = 3.0, 1.0


@lru_cache(maxsize=16)
def _clutter_weights(half_width: int) -> np.ndarray:
    """The inverse covariance of a window's residuals, ``(I + r K)^-1`` with K a Gaussian
    correlation of length ``_CLUTTER_PX`` and r ``_CLUTTER_RATIO``, scaled to sum to the
    window's pixel count.

    A column's residuals are not independent: textures of the floor and the holder
    coarser than the blur, the lighting's curvature and a penumbra's shoulder bend its
    window smoothly where the model's straight levels do not, and a plain least-squares
    fit reads part of such a bend as a shift of the crossing. Counted as correlated noise
    (generalised least squares), the bends weigh less than the transition's sharp
    signature, which they do not resemble.
    """
    x = np.arange(-half_width, half_width + 1, dtype=float)
    K = np.exp(-0.5 * ((x[:, None] - x[None, :]) / _CLUTTER_PX) ** 2)
    W = np.linalg.inv(np.eye(x.size) + _CLUTTER_RATIO * K)
    W *= x.size / W.sum()
    W.setflags(write=False)
    return W


def step_response(d: np.ndarray, s: float | np.ndarray, wa: float | np.ndarray,
                  wb: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A pixel's response S to a unit step at normal distance ``d`` (px, + toward the
    step's high side) blurred by a Gaussian of width ``s``, the pixel's footprint across
    the edge being a trapezoid of the widths ``wa`` >= ``wb``; returns S, dS/dd, d2S/dd2.

    S = T * Phi_s with T the trapezoid (box wa * box wb): by the second antiderivative of
    Phi_s, G(t) = ((t^2 + s^2) Phi(t/s) + t s phi(t/s)) / 2, S is the second difference
    of G over the box widths (and dS/ds = s d2S/dd2, the heat equation).
    """
    wb = np.maximum(wb, 0.02)
    p, q = (wa + wb) / 2, (wa - wb) / 2
    # the four corners of the trapezoid at once (a leading axis), signs +, -, -, +; written
    # in place (the arrays are small: numpy's per-call cost is most of this function's)
    d = np.asarray(d, float)
    t = np.empty((4, *np.broadcast(d, s, p).shape))  # (np.broadcast_shapes: 4x the cost)
    np.add(d, p, out=t[0])
    np.add(d, q, out=t[1])
    np.subtract(d, q, out=t[2])
    np.subtract(d, p, out=t[3])
    z = t / s
    Phi = ndtr(z)
    sphi = np.exp(-0.5 * z * z) * (s * _INV_SQRT_2PI)
    G = (t * t + s * s) * Phi + t * sphi
    G1 = t * Phi + sphi

    def second_difference(a: np.ndarray) -> np.ndarray:
        return (a[0] + a[3]) - (a[1] + a[2])

    S, S1, S2 = second_difference(G), second_difference(G1), second_difference(Phi)
    inv = 1.0 / (wa * wb)
    return S * (0.5 * inv), S1 * inv, S2 * inv


def disc_edge(x: np.ndarray, radius: float, foot: np.ndarray) -> np.ndarray:
    """A pixel's response to a unit step defocused by a disc of ``radius`` px (a lens out of
    focus: the fraction of the disc beyond the edge, which ends a radius out on either
    side, where a Gaussian's tails go on), at the pixels' distances ``x`` from the edge,
    the pixel's footprint across it ``foot`` (its two widths, as :func:`step_response`'s)
    sampled 4 x 4."""
    u = (np.arange(4) + 0.5) / 4 - 0.5
    t = (u[:, None] * foot[0] + u[None, :] * foot[1]).ravel()
    z = np.clip((x[:, None] - t[None, :]) / max(radius, 1e-6), -1.0, 1.0)
    return (0.5 + (z * np.sqrt(1.0 - z * z) + np.arcsin(z)) / math.pi).mean(axis=1)


@dataclass(frozen=True)
class _Rows:
    """Every crossing of every edge as one row: its edge (non-decreasing), its column
    (row) ``t``, the area method's crossing ``c`` and how to read its pixel window from
    the flattened image (index ``base + minor * stride``)."""

    edge: np.ndarray
    t: np.ndarray
    c: np.ndarray
    contrast: np.ndarray
    base: np.ndarray
    stride: np.ndarray
    limit: np.ndarray  # the minor coordinate's size (image width or height)

    def take(self, sel: np.ndarray) -> _Rows:
        return _Rows(self.edge[sel], self.t[sel], self.c[sel], self.contrast[sel],
                     self.base[sel], self.stride[sel], self.limit[sel])


def _windows(flat: np.ndarray, rows: _Rows, half_width: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel windows (N, 2 hw + 1) centred on each row's crossing, one gather for all
    edges: the windows, their centres and the mask of the rows whose window fits."""
    centre = np.rint(rows.c).astype(np.intp)
    ok = (centre >= half_width) & (centre + half_width < rows.limit)
    centre = centre[ok]
    j = np.arange(-half_width, half_width + 1)
    idx = rows.base[ok, None] + (centre[:, None] + j[None, :]) * rows.stride[ok, None]
    return flat.take(idx).astype(np.float64), centre.astype(float), ok


def _tail_slopes(P: np.ndarray, edge: np.ndarray, n_edges: int,
                 each: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Illumination slope on either side of each window, one value per edge except where
    it changes along the edge by more than its noise (a penumbra crossing the edge);
    ``each``: every row's own slopes on either side, to use instead of the 3-pixel tails
    of P (see :func:`_refit_slopes`)."""
    n = edge.size
    if each is None:
        each = (_slope_of(P[:, :_TAILS]), _slope_of(P[:, -_TAILS:]))
    # both sides in one batch: the far sides as edges n_edges .. 2 n_edges - 1
    both = adaptive_slopes(np.concatenate(each), np.concatenate([edge, edge + n_edges]),
                           2 * n_edges, 3)
    return both[:n], both[n:]


def _slope_of(tail: np.ndarray) -> np.ndarray:
    """Each row's least-squares slope over its (equally spaced) pixels."""
    wts = np.arange(tail.shape[1]) - (tail.shape[1] - 1) / 2
    return tail @ (wts / float(wts @ wts))


def _step_free_tails(lo: np.ndarray, xlo: np.ndarray, hi: np.ndarray, xhi: np.ndarray,
                     u: np.ndarray, D: np.ndarray, row: np.ndarray,
                     table: tuple[np.ndarray, float, int], geo: np.ndarray, b1: np.ndarray,
                     b2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The tail pixels ``lo`` (``hi``) at positions ``xlo`` (``xhi``) on the low (high)
    side with the fitted step's own tail taken off: at 2.5-3.5 blur widths from the edge
    (the position window at 1.5-2 px) the transition still climbs by a few tenths of a DN
    per px, which the tails' slopes read as illumination; and a slope on one side moves a
    soft edge's fitted crossing by about 16 px per (DN/px) / DN of contrast at a blur of
    2 px."""
    xt = np.concatenate([xlo, xhi])[:, None]  # pixel-major, as the table is read
    S = _table_step(table, row, geo[row, 1] * (xt - u)).T
    amp = D[:, None] + (b2 - b1)[:, None] * xt.T
    k = xlo.size
    return lo - amp[:, :k] * S[:, :k], hi + amp[:, k:] * (1.0 - S[:, k:])


def _refit_slopes(flat: np.ndarray, P: np.ndarray, x: np.ndarray, r1: _Rows,
                  u: np.ndarray, D: np.ndarray, blur: np.ndarray,
                  table: tuple[np.ndarray, float, int], geo: np.ndarray, b1: np.ndarray,
                  b2: np.ndarray, hw: int, n_edges: int) -> tuple[np.ndarray, np.ndarray]:
    """The tails' illumination slopes again, the fitted step's own tail taken off; on a
    soft edge (blur over _WIDE_BLUR px) from tails _EXTRA px longer, since there a slope
    error moves the crossing most (as the blur squared) and 3 pixels' slope is noisy."""
    k = _TAILS
    lo, hi = _step_free_tails(P[:, :k], x[:k], P[:, -k:], x[-k:], u, D, r1.edge, table, geo,
                              b1, b2)
    vlo, vhi = _slope_of(lo), _slope_of(hi)
    soft = blur[r1.edge] > _WIDE_BLUR
    if _EXTRA and soft.any():
        # (a row whose longer window leaves the frame keeps its 3-pixel tails)
        Pw, _cw, okw = _windows(flat, r1, hw + _EXTRA)
        nt = k + _EXTRA
        xw = np.arange(-hw - _EXTRA, hw + _EXTRA + 1, dtype=float)
        lo, hi = _step_free_tails(Pw[:, :nt], xw[:nt], Pw[:, -nt:], xw[-nt:], u[okw], D[okw],
                                  r1.edge[okw], table, geo, b1[okw], b2[okw])
        wide = soft[okw]
        vlo[okw] = np.where(wide, _slope_of(lo), vlo[okw])
        vhi[okw] = np.where(wide, _slope_of(hi), vhi[okw])
    return _tail_slopes(P, r1.edge, n_edges, (vlo, vhi))


_EVERY = 3  # the columns read for a side's floor profile: every _EVERY-th
_LONG = 20  # px beyond the window's tails over which a side's floor profile is read
# a penumbra's step must explain the profile this much better than a line (in units of
# the mean profile's noise; 200 caught one more penumbra under a side in the corpus, and
# read a hard shadow's band 2 px wide beside a side as one: the holder 2.6 px off, ok)
_BEND_CHI2 = 400.0
_BEND_MIN_DN = 0.1  # a penumbra's bend smaller than this everywhere in the window is none
_BEND_CLIP = 0.01  # a side's profile with more of its pixels clipped is not read for a bend
_PEN_WIDER = 1.5  # a penumbra's width, at least this many times the edge's blur
_SG_MAX = 15.0  # a penumbra's width, at most (px)
# a joint fit that ends with its width within _CRAWL of the bound is fitted once more
# with the bound written into the width (its logistic from _CRAWL_START: 0.05 of the way
# up) and taken only where that lifts the width off the bound. The data may hold a right
# penumbra near the bound, which the penalty's wall stops short of: a penumbra centred on
# a side (the shadow under a holder, blurred 3 px in a frame blurred 1.6 px) crawled along
# the bound until out of evaluations, 2 sides of 4 read 0.28 px out, and from the bound
# written in they came out 4.6 and 30 % above it. A penumbra that stays at its least
# width is something narrower than a shadow's penumbra, which the profile does not place:
# a lens's disc edge's shoulders (centred 0.5 widths out: sides 0.6-0.7 px off at a
# corner sigma of 0.03 px, bench "lens out of focus"), a rounded corner's arc (2.5 widths
# inside), a plate's step as sharp as the edge (3.4 widths out, which the neighbour look
# then finds), penumbrae 11-17 px out through a disc (corpus 2124 #118, #657, #923)
_CRAWL, _CRAWL_START = 1e-3, -3.0
# the joint fit's evaluations of its residuals, at most: with its Jacobian about one an
# iteration, more where a step is refused (the finite-difference Jacobian's fit took five
# an iteration, of 200; at 40, corpus 6100 #856 stopped 3 short of converging)
_MAX_ITER = 60
# the joint fit's range of the edge's offset and blur and the penumbra's centre (px); a
# penumbra whose centre or width ends within _AT_END px of its range's end is not one the
# profile places (2124 #300: centred 12 px under the holder, 667 DN deep: the large-scale
# shape of the profile), and the fit is not taken
_Q_RANGE = ((-1.5, 1.5), (0.2, 4.0), (-12.0, 30.0))
_AT_END = 1e-3
_MU = np.arange(-6.0, 20.25, 0.5)  # the penumbra's centre, px out from the window's tail
_SG = np.arange(1.5, 12.25, 0.5)  # its width


def _penumbra_grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The penumbra's shapes over the profile's pixels for every (centre, width) of the
    grid, less their means (a level is fitted with each), their squared norms and the
    pixels' positions (px out from the innermost tail pixel)."""
    out = np.arange(_LONG + _TAILS, dtype=float)
    z = ndtr((out[None, None, :] - _MU[:, None, None]) / _SG[None, :, None])
    zc = (z - z.mean(axis=2, keepdims=True)).reshape(-1, out.size)
    return zc, np.maximum((zc * zc).sum(axis=1), 1e-12), out


_GRID = _penumbra_grid()
_GRID_MU = np.repeat(_MU, _SG.size)
_GRID_SG = np.tile(_SG, _MU.size)


def _penumbra_bend(flat: np.ndarray, r1: _Rows, u: np.ndarray, D: np.ndarray, hw: int,
                   table: tuple[np.ndarray, float, int], geo: np.ndarray, b1: np.ndarray,
                   b2: np.ndarray, n_edges: int, blur: np.ndarray
                   ) -> _Bend | None:
    """The floor's bend toward each side on either side of it where a penumbra (a blurred
    step of the floor's brightness, parallel to the side: a cast shadow) lies beside it,
    or None where no side has one.

    The tails see the penumbra's slope a few pixels out, but its shoulder bends the floor
    between there and the edge, which moves the crossing (a side 0.4 px off, corpus). Each
    side's mean profile out to _LONG px beyond the window tells a penumbra (a blurred step
    on a level, by a grid over its centre and width, where it explains the profile clearly
    better than a line); where it reaches into the window, it is fitted again together
    with the edge over the whole profile (:func:`_joint_penumbra`), which gives the edge's
    offset from the columns' crossings and its blur."""
    hl = hw + _LONG
    # every _EVERY-th column: the mean profile needs no more, and costs less
    sub = np.flatnonzero(np.arange(r1.edge.size) % _EVERY == 0)
    Pw, _cw, okw = _windows(flat, r1.take(sub), hl)
    okw = sub[okw]
    if okw.size == 0:
        return None
    row = r1.edge[okw]
    xw = np.arange(-hl, hl + 1, dtype=float)
    k = _LONG + _TAILS  # the tails and beyond, on either side
    lo, hi = _step_free_tails(Pw[:, :k], xw[:k], Pw[:, -k:], xw[-k:], u[okw], D[okw], row,
                              table, geo, b1[okw], b2[okw])
    counts = np.bincount(row, minlength=n_edges).astype(float)
    # each edge's mean profile and its rows' variance, by a one-hot product
    one = np.zeros((n_edges, row.size))
    one[row, np.arange(row.size)] = 1.0 / np.maximum(counts, 1.0)[row]
    x_in = float(hw - _TAILS + 1)  # the innermost tail pixel's distance from the centre
    bends = []
    found = False
    shifts = np.full((2, n_edges), np.nan)
    blurs = np.full((2, n_edges), np.nan)
    x = np.arange(-hw, hw + 1, dtype=float)
    zc, den, out = _GRID
    cl = _clipped(Pw)
    # the share of each edge's profile pixels on either side clipped at full scale or
    # zero: such a profile's shape is the clip's (a saturated holder reads flat near
    # the edge and falls off inside it), not a penumbra's
    clip_share = np.zeros((2, n_edges))
    if cl is not None:
        c = cl[0] | cl[1]
        clip_share = np.stack([one @ c[:, :k].mean(axis=1), one @ c[:, -k:].mean(axis=1)])
    for side, vals in ((0, lo[:, ::-1]), (1, hi)):
        d_win = (x if side else -x) - x_in  # each window pixel's distance out from the tails
        prof = one @ vals
        # the noise of the mean profile's shape: the rows' scatter about their own
        # levels (along a side the light and the floor's texture move a row's whole
        # profile up or down, which the level fitted with each shape takes up; counted
        # as noise, it hid a penumbra 17 DN deep under a side, corpus)
        vc = vals - vals.mean(axis=1, keepdims=True)
        mc = one @ vc
        noise = np.maximum(one @ (vc * vc) - mc ** 2, 1e-6).mean(axis=1) / np.maximum(
            counts, 1.0)
        pc = prof - prof.mean(axis=1, keepdims=True)  # (edge, k)
        oc = out - out.mean()
        ss_all = (pc * pc).sum(axis=1)
        ss_lin = ss_all - (pc @ oc) ** 2 / float(oc @ oc)  # the line's misfit
        # the step's: every (centre, width) of the grid, level and height by least squares
        num = pc @ zc.T  # (edge, grid)
        ss_step = ss_all[:, None] - num * num / den[None, :]
        # a step hardly wider than the edge's own blur is the edge model's error
        ss_step = np.where(_GRID_SG[None, :] >= _PEN_WIDER * blur[:, None], ss_step, np.inf)
        best = ss_step.argmin(axis=1)
        e = np.arange(n_edges)
        gain = (ss_lin - ss_step[e, best]) / noise
        use = ((gain > _BEND_CHI2) & (counts >= 8) & np.isfinite(gain)
               & (clip_share[side] <= _BEND_CLIP))
        height = num[e, best] / den[best]
        mu, sg = _GRID_MU[best], _GRID_SG[best]
        g = np.where(use[:, None], _bend_shape(d_win, mu, sg, height, out), 0.0)
        # a penumbra that does not reach into the window (a plate's edge 20 px out read as
        # one) changes nothing there, and its rows keep their clutter weights
        g[np.abs(g).max(axis=1) < _BEND_MIN_DN] = 0.0
        # where the bend reaches the edge's transition, the penumbra with the edge
        for j in np.flatnonzero(use & (np.abs(g[:, hw]) > _JOINT_DN)):
            mine = row == j
            fit = _joint_penumbra(Pw[mine], xw, u[okw][mine], side, float(geo[j, 1]),
                                  float(geo[j, 2]), float(geo[j, 3]), float(blur[j]),
                                  float(mu[j]) + x_in, float(sg[j]), float(height[j]), hw)
            if fit is None:
                # (the grid's penumbra is then not one the edge's profile bears out: a
                # rounded corner's arc beyond the window read as a step of 600 DN)
                g[j] = 0.0
                continue
            mu[j], sg[j], height[j] = fit[0] - x_in, fit[1], fit[2]
            shifts[side, j], blurs[side, j] = fit[3], fit[4]
            g[j] = _bend_shape(d_win, mu[j:j + 1], sg[j:j + 1], height[j:j + 1], out)[0]
        found |= bool(np.any(g != 0.0))
        bends.append(g)
    if not found:
        return None
    # an edge's offset and blur where one side's penumbra was fitted with it (with one on
    # either side, neither model holds: the bends stand)
    one_side = np.isnan(shifts[0]) != np.isnan(shifts[1])
    return _Bend(bends[0][r1.edge].T.copy(), bends[1][r1.edge].T.copy(),
                 np.where(one_side, np.fmax(shifts[0], shifts[1]), np.nan),
                 np.where(one_side, np.fmax(blurs[0], blurs[1]), np.nan))


def _bend_shape(d_win: np.ndarray, mu: np.ndarray, sg: np.ndarray, height: np.ndarray,
                out: np.ndarray) -> np.ndarray:
    """Each edge's penumbra (centre ``mu`` px out from the innermost tail pixel, width
    ``sg``, ``height``) in the window, less its line through the tail pixels (the tails'
    own level and slope stand): what the floor does beyond the line, toward the edge;
    zero beyond the tails. (edge, pixels) at the distances ``d_win`` out from the tails."""
    zw = ndtr((d_win[None, :] - mu[:, None]) / sg[:, None])
    zt = ndtr((out[None, :_TAILS] - mu[:, None]) / sg[:, None])
    slope_t = (zt[:, -1] - zt[:, 0]) / (_TAILS - 1)
    level_t = zt.mean(axis=1) - slope_t * (_TAILS - 1) / 2
    g = height[:, None] * (zw - (level_t[:, None] + slope_t[:, None] * d_win[None, :]))
    return np.where((d_win < 0)[None, :], g, 0.0)


@dataclass(frozen=True)
class _Bend:
    """A penumbra's bend of the floor on the low and high side of each row's window
    (pixel-major, for :func:`_fit_tabulated`), and per edge the offset of the edge from
    its columns' crossings and its blur where the penumbra was fitted with the edge (NaN
    elsewhere)."""

    lo: np.ndarray
    hi: np.ndarray
    shift: np.ndarray
    blur: np.ndarray


_JOINT_BIN = 0.25  # px: the side's mean profile, binned by distance from each column's crossing
# a penumbra whose bend at the window's centre is below this (DN) moves the edge too
# little to be fitted with it (the joint fit costs 3-5 ms). Low, because the grid sees
# only the penumbra's outer half: a narrow step near the tails (0.4 DN at the centre)
# fits it as well as the wide one centred at the edge that the joint fit finds (a
# contact shadow under uneven light, tests/test_vision_holder_penumbra.py: 0.36 px off
# at 0.5 DN, 0.025 at 0.2)
_JOINT_DN = 0.2
# the joint fit places an edge only where it moves it by at least this much (px along
# the column): its Gaussian edge is not every camera's (a 0.6 px blur drawn by a discrete
# kernel: 0.03 px off beside a penumbra 6.5 px out), and below this the columns' own fits
# with the penumbra's bend do as well (corpus corners, uncompressed: 0.0335 px with no
# threshold, 0.0334 at 0.05, 0.0340 at 0.1)
_SHIFT_MIN = 0.05


def _joint_penumbra(Pw: np.ndarray, xw: np.ndarray, u: np.ndarray, side: int, nu: float,
                    wa: float, wb: float, blur: float, m0: float, sg0: float, h0: float,
                    hw: int) -> tuple[float, float, float, float, float] | None:
    """A penumbra's centre (px out from the edge, along the column), width and height,
    fitted together with the edge on one side's mean profile: the long windows ``Pw`` (at
    the column offsets ``xw``) binned by their distance from each column's crossing
    ``u``, the penumbra on the high (``side`` 1) or low side. The floor beyond the tails
    alone (the grid's fit, the start here) sees half a penumbra that reaches the edge: its
    width and height trade off and the level it extrapolates to the edge erred by 5 DN
    (corpus). Returns (centre, width, height, the edge's offset from the columns'
    crossings, its blur) or None where the fit fails or holds the penumbra at its least
    width (``_CRAWL``)."""
    d = (xw[None, :] - u[:, None]).ravel()
    y = Pw.ravel().astype(float)
    # the far side's profile out to the window's tails only: beyond them it holds the
    # holder's face or the floor's own make (a sample strip, a label, texture)
    near = float(hw)
    ok = np.isfinite(d) & np.isfinite(y) & ((d <= near) if side == 0 else (d >= -near))
    if not ok.any():
        return None
    idx = np.floor(d[ok] / _JOINT_BIN).astype(np.intp)
    idx -= idx.min()
    n = np.bincount(idx)
    keep = n >= 2
    if np.count_nonzero(keep) < 20:
        return None
    db_ = (np.bincount(idx, d[ok]) / np.maximum(n, 1))[keep]
    yb = (np.bincount(idx, y[ok]) / np.maximum(n, 1))[keep]
    w = np.sqrt(n[keep])
    sg_min = _PEN_WIDER * blur
    model = _JointModel(db_, w[:, None], yb * w, side, nu, (wa * wa + wb * wb) / 12.0, sg_min)
    resid, jac = model.resid, model.jac

    def off_the_bound(p: np.ndarray) -> np.ndarray:
        # (the width as the bound plus a logistic of p[3]: a width the data hold near the
        # bound is reached without the penalty's wall)
        return np.array([p[0], p[1], p[2], sg_min + (_SG_MAX - sg_min) * expit(p[3])])

    q0 = np.array([0.0, max(blur, 0.3), m0, max(sg0, sg_min)])
    scale = np.array([10.0, 10.0, 1.0, 1.0])
    try:
        q, _cov, info, _msg, ier = leastsq(resid, q0, Dfun=jac, full_output=True,
                                           maxfev=_MAX_ITER, diag=scale)
        if (q[3] <= sg_min * (1.0 + _CRAWL)
                and np.all(np.abs(info["fvec"][-4:-1]) <= 1e-6)):
            # it ended at the width's bound, converged or out of evaluations (with a
            # finite-difference Jacobian such a fit crawled along the bound until out
            # of them: the penalty lets a step past the bound only where the cost falls
            # more than the wall rises): once more from there, the bound written into
            # the width
            p0 = np.array([q[0], q[1], q[2], _CRAWL_START])
            p, _cov, info, _msg, ier = leastsq(
                lambda p: resid(off_the_bound(p)), p0,
                Dfun=lambda p: jac(off_the_bound(p)) * np.array([1.0, 1.0, 1.0, (
                    _SG_MAX - sg_min) * expit(p[3]) * (1.0 - expit(p[3]))]),
                full_output=True, maxfev=_MAX_ITER // 2, diag=scale)
            q = off_the_bound(p)
            if q[3] <= sg_min * (1.0 + _CRAWL):
                return None  # back at the bound: as narrow as it may be, wherever it lies
    except (ValueError, np.linalg.LinAlgError):
        return None
    if ier not in (1, 2, 3, 4) or not np.all(np.isfinite(q)) or np.any(
            np.abs(info["fvec"][-4:]) > 1e-6):
        return None
    if min(abs(q[2] - _Q_RANGE[2][0]), abs(q[2] - _Q_RANGE[2][1]),
           abs(q[3] - _SG_MAX)) <= _AT_END:
        return None  # a penumbra as far out or as wide as the range allows
    try:
        coef = model.fitted(q)[2]  # the levels at the fit's end
    except np.linalg.LinAlgError:
        return None
    return float(q[2]), float(q[3]), float(coef[4]), float(q[0]), float(q[1])


@dataclass
class _JointModel:
    """:func:`_joint_penumbra`'s model of one side's binned mean profile (the bins'
    distances ``db`` from the columns' crossings, their weights ``wcol`` (bins, 1), the
    weighted levels ``yw``): an edge and a penumbra beside it on ``side``, for the
    nonlinear q = (the edge's offset, its blur, the penumbra's centre and width), the
    levels by linear least squares; ``nu`` the column's cosine to the edge normal,
    ``foot`` the pixel footprint's variance across it, ``sg_min`` the penumbra's least
    width."""

    db: np.ndarray
    wcol: np.ndarray
    yw: np.ndarray
    side: int
    nu: float
    foot: float
    sg_min: float
    # the last point's fit (see fitted): its q's bytes, A, A'A, the levels, the residuals
    _key: bytes = field(default=b"", repr=False)
    _fit: tuple[np.ndarray, ...] = field(default=(), repr=False)

    def basis(self, q: np.ndarray) -> np.ndarray:
        """The model's columns: the lower level and slope, the step, its slope (with the
        blur's spread of it, see _fit_tabulated) and the penumbra (with its own spread)."""
        db_, nu, sgn = self.db, self.nu, 1.0 if self.side else -1.0
        delta, s_, m, sg = q
        sd = math.sqrt(s_ * s_ + self.foot)
        dn = nu * (db_ - delta)
        S = ndtr(dn / sd)
        Qn = np.exp(-0.5 * (dn / sd) ** 2) * (sd * _INV_SQRT_2PI) / nu  # Q(d) / nu
        zo = (sgn * db_ - m) / sg
        Z = ndtr(zo)
        Z1 = sgn * np.exp(-0.5 * zo * zo) * (_INV_SQRT_2PI / sg)  # dZ / dx
        pen = Z * S + Z1 * Qn if self.side else Z * (1.0 - S) - Z1 * Qn
        return np.column_stack([np.ones_like(db_), db_, S, db_ * S + Qn, pen])

    def derivatives(self, q: np.ndarray) -> np.ndarray:
        """The step's, its slope's and the penumbra's columns (basis' last three)
        differentiated by each of q: (bins, 4 (q), 3 (columns))."""
        db_, nu, sgn = self.db, self.nu, 1.0 if self.side else -1.0
        delta, s_, m, sg = q
        sd = math.sqrt(s_ * s_ + self.foot)
        z = nu * (db_ - delta) / sd
        ph = np.exp(-0.5 * z * z) * _INV_SQRT_2PI
        S, Qn = ndtr(z), ph * (sd / nu)
        zo = (sgn * db_ - m) / sg
        pho = np.exp(-0.5 * zo * zo) * _INV_SQRT_2PI
        Z, Z1 = ndtr(zo), sgn * pho / sg
        # S and Q / nu by the offset and the blur (d sd / d s = s / sd)
        dS = (-ph * (nu / sd), -ph * z * (s_ / (sd * sd)))
        dQ = (z * ph, ph * (1.0 + z * z) * (s_ / (sd * nu)))
        # Z and its slope Z1 by the centre and the width
        dZ = (-pho / sg, -pho * zo / sg)
        dZ1 = (sgn * zo * pho / (sg * sg), sgn * pho * (zo * zo - 1.0) / (sg * sg))
        zero = np.zeros_like(db_)
        cols = []
        for k in range(2):
            cols += [dS[k], db_ * dS[k] + dQ[k], sgn * (Z * dS[k] + Z1 * dQ[k])]
        for k in range(2):
            cols += [zero, zero, (dZ[k] * S + dZ1[k] * Qn if self.side
                                  else dZ[k] * (1.0 - S) - dZ1[k] * Qn)]
        return np.stack(cols, axis=1).reshape(db_.size, 4, 3)

    def clamped(self, q: np.ndarray) -> np.ndarray:
        """q within its range ('lm' has no bounds: the residuals hold it there by a
        penalty)."""
        (o0, o1), (s0, s1), (m0, m1) = _Q_RANGE
        return np.array([min(max(float(q[0]), o0), o1), min(max(float(q[1]), s0), s1),
                         min(max(float(q[2]), m0), m1),
                         min(max(float(q[3]), self.sg_min), _SG_MAX)])

    def fitted(self, qc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """At q (in range): the weighted columns A, their Gram matrix, the levels and
        the weighted residuals (the levels by the normal equations: a few well-scaled
        columns, whose small Gram matrix solves at a tenth of an SVD's cost); the last
        point's kept (the Jacobian is asked for where the residuals were)."""
        key = qc.tobytes()
        if self._key != key:
            A = self.basis(qc) * self.wcol
            G = A.T @ A
            c = np.linalg.solve(G, A.T @ self.yw)
            self._key, self._fit = key, (A, G, c, A @ c - self.yw)
        A, G, c, r = self._fit
        return A, G, c, r

    def resid(self, q: np.ndarray) -> np.ndarray:
        """The weighted residuals, and the penalty of q beyond its range."""
        qc = self.clamped(q)
        return np.concatenate([self.fitted(qc)[3], 1e3 * (q - qc)])

    def jac(self, q: np.ndarray) -> np.ndarray:
        """The residuals' Jacobian, the linear levels projected out exactly (Golub and
        Pereyra): with A c the fit, r its residuals and dA a parameter's derivative of A,
        dr = dA c - A (A'A)^-1 (A' dA c + dA' r). A finite-difference one cost four more
        evaluations of the residuals an iteration, a quarter of the slowest frames'
        time."""
        qc = self.clamped(q)
        inside = qc == q
        A, G, c, r = self.fitted(qc)
        n = r.size
        dA = (self.derivatives(qc) * self.wcol[:, :, None]).reshape(n, 12)  # A's last 3, by q
        v = (dA.reshape(n * 4, 3) @ c[2:]).reshape(n, 4)  # dA c, by q
        t = np.zeros((5, 4))
        t[2:] = (r @ dA).reshape(4, 3).T  # dA' r, by q
        J = np.empty((n + 4, 4))
        J[:n] = (v - A @ np.linalg.solve(G, A.T @ v + t)) * inside
        J[n:] = np.diag(1e3 * ~inside)
        return J


def _start(P: np.ndarray, x: np.ndarray, b1: np.ndarray, b2: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    a1 = (P[:, 0] + P[:, 1]) / 2 - b1 * x[:2].mean()  # (as .mean(axis=1), at less cost)
    return a1, (P[:, -2] + P[:, -1]) / 2 - b2 * x[-2:].mean() - a1


def _fit(P: np.ndarray, x: np.ndarray, u: np.ndarray, s: np.ndarray, nu: np.ndarray,
         wa: np.ndarray, wb: np.ndarray, b1: np.ndarray, b2: np.ndarray, iterations: int,
         clipped: tuple[np.ndarray, np.ndarray] | None = None
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton fit of every row of P with its own blur; returns u, D and s.
    ``clipped``: the pixels at the sensor's full scale and at zero (see
    :func:`_censored`)."""
    X = x[None, :]
    sv = s.astype(float).copy()
    a1, D = _start(P, x, b1, b2)
    db = (b2 - b1)[:, None]
    base1 = P - b1[:, None] * X
    nu_c, wa_c, wb_c = nu[:, None], wa[:, None], wb[:, None]
    J = np.empty((P.shape[0], 4, P.shape[1]))  # (row, parameter, pixel): matmul order
    J[:, 0] = 1.0
    JT = J.transpose(0, 2, 1)
    ridge = 1e-9 * np.eye(4)
    for _ in range(iterations):
        S, S1, S2 = step_response(nu_c * (X - u[:, None]), sv[:, None], wa_c, wb_c)
        amp = D[:, None] + db * X
        r = base1 - a1[:, None] - amp * S
        J[:, 1] = S
        J[:, 2] = -nu_c * amp * S1
        J[:, 3] = amp * sv[:, None] * S2
        if clipped is None:
            A = J @ JT + ridge
            step = np.linalg.solve(A, J @ r[:, :, None])[:, :, 0]
        else:
            Jw = J * _censored(clipped, r)[:, None, :]
            step = np.linalg.solve(Jw @ JT + ridge, Jw @ r[:, :, None])[:, :, 0]
        a1 += step[:, 0]
        D += step[:, 1]
        u = u + np.clip(step[:, 2], -1.0, 1.0)
        sv = np.clip(sv + np.clip(step[:, 3], -0.5, 0.5), 0.15, 6.0)
    return u, D, sv


_H = 0.04  # the step tables' spacing (px of normal distance; linear interpolation errs < 1e-3)


def _step_table(x_max: float, blur: np.ndarray, geo: np.ndarray
                ) -> tuple[np.ndarray, float, int]:
    """One table per edge of S, S' and Q at the nodes of a grid of normal distances
    (spacing _H) and their steps to the next node (linear interpolation): six rows, each
    every edge's nodes in turn (one contiguous gather a row: gathering whole nodes of six
    and reading them strided cost the tabulated fit about 10 % more); its reach (px) and
    its number of nodes per edge."""
    # beyond 4 blur widths and the footprint the step is flat: the table stops there
    reach = min(x_max + 2.5,
                4.0 * float(np.max(blur)) + float(np.max(geo[:, 2] + geo[:, 3])) + 1.0)
    grid = np.arange(-reach, reach + _H, _H)
    tS, tS1, _ = step_response(grid[None, :], blur[:, None], geo[:, 2:3], geo[:, 3:4])
    # Q(d) = the kernel's first moment beyond d, int_d^inf t K(t) dt (K = dS/dd), by the
    # trapezoid rule from the far end: the slope term's shape (see _fit_tabulated)
    tk = grid[None, :] * tS1
    tQ = np.zeros_like(tS1)
    tQ[:, :-1] = np.cumsum(((tk[:, 1:] + tk[:, :-1]) * (_H / 2))[:, ::-1], axis=1)[:, ::-1]
    tab = np.stack([tS, np.diff(tS, axis=1, append=tS[:, -1:]),
                    tS1, np.diff(tS1, axis=1, append=tS1[:, -1:]),
                    tQ, np.diff(tQ, axis=1, append=tQ[:, -1:])]).reshape(6, -1)
    return tab, reach, grid.size


def _table_step(table: tuple[np.ndarray, float, int], row: np.ndarray, d: np.ndarray
                ) -> np.ndarray:
    """S of each ``row``'s edge at normal distances ``d`` (rows along the last axis),
    read from its table (flat beyond the table's reach)."""
    tab, reach, ng = table
    f = (d + reach) / _H
    np.minimum(np.maximum(f, 0.0, out=f), ng - 1.001, out=f)
    i = f.astype(np.intp)
    f -= i
    i = i + row * ng
    return tab[0].take(i) + tab[1].take(i) * f


def _fit_tabulated(P: np.ndarray, x: np.ndarray, u: np.ndarray, row: np.ndarray,
                   blur: np.ndarray, geo: np.ndarray, b1: np.ndarray, b2: np.ndarray,
                   iterations: int, table: tuple[np.ndarray, float, int] | None = None,
                   bend: tuple[np.ndarray, np.ndarray] | None = None,
                   clipped: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_fit` with s fixed per edge, S and S' read from one table per edge
    (:func:`_step_table`, built here unless given) and the 3 x 3 normal equations of
    (a1, D, u) solved in closed form; returns u, D and each row's residual RMS (of the
    last iteration's start). ``bend``: the floor's departure from its tails' line on
    either side at each pixel (pixel-major, see :func:`_penumbra_bend`); ``clipped``:
    the pixels at the sensor's full scale and at zero, pixel-major (see
    :func:`_censored`)."""
    tab, reach, ng = table if table is not None else _step_table(
        float(np.max(np.abs(x))), blur, geo)
    # pixel-major arrays (pixel, row): each row's parameters then broadcast along the long
    # axis and a window's sum over its pixels adds whole rows (with the few pixels of a
    # window along the last axis, numpy runs both as a short loop per row)
    xc = x[:, None]
    nu = geo[row, 1]
    # the normal distance's table index is (nu (x - u) + reach) / H: its u-free part once
    lead = (xc * nu + reach) / _H
    nu_h = nu / _H
    base_idx = row * ng
    a1, D = _start(P, x, b1, b2)
    db = b2 - b1
    base1 = np.ascontiguousarray(P.T) - xc * b1
    dbend: np.ndarray | float = 0.0
    # the step's height changes along the window (amp' per px): the blur spreads that
    # slope across the edge as amp' Q(d) / nu (the levels' convolution with the step, to
    # first order), which a step of the local height alone leaves out; a penumbra's
    # slope at the edge moved the crossing by amp' (s^2 + footprint) / D, 0.1-0.4 px
    ramp: np.ndarray = np.broadcast_to(db, P.T.shape)
    if bend is not None:
        base1 -= bend[0]
        dbend = bend[1] - bend[0]
        ramp = ramp + np.gradient(dbend, axis=0)
    ramp_nu = ramp / nu
    ones = np.ones(P.shape[1])  # sums over the pixels as a product
    # unclipped windows: generalised least squares against the windows' smooth clutter
    # (:func:`_clutter_weights`); a censored fit keeps its diagonal weights
    # (but plain least squares on a side whose penumbra's bend is modelled: the clutter
    # weights would count that bend twice; our renderer's cast shadow 0.031 -> 0.041 px)
    W = _clutter_weights(P.shape[1] // 2)
    plain = np.zeros(P.shape[0], bool)
    if bend is not None:
        plain = np.any(bend[0] != 0, axis=0) | np.any(bend[1] != 0, axis=0)
    any_plain = bool(plain.any())
    w1 = np.where(plain[None, :], 1.0, (W @ ones)[:, None])
    m: float | np.ndarray = ones @ w1
    # the windows with a clipped pixel (a censored fit, :func:`_censored`); only those:
    # one dead pixel at zero in one window turned every window's fit to the censored
    # one's plain weights (corpus frames with 0.1 % dead pixels: all four corners moved)
    crow = np.zeros(P.shape[0], bool)
    if clipped is not None:
        crow = np.asarray(np.any(clipped[0] | clipped[1], axis=0))
    xdb = xc * db
    for _ in range(iterations):
        f = lead - nu_h * u
        np.minimum(np.maximum(f, 0.0, out=f), ng - 1.001, out=f)
        i = f.astype(np.intp)
        f -= i
        i += base_idx
        S = tab[0].take(i) + tab[1].take(i) * f
        S1 = tab[2].take(i) + tab[3].take(i) * f
        Q = tab[4].take(i) + tab[5].take(i) * f
        amp = D + xdb + dbend
        r = base1 - a1 - amp * S - ramp_nu * Q
        # (dQ/du = nu d K(d), d = nu (x - u) the normal distance)
        g = -nu * amp * S1 + ramp * (nu * (xc - u)) * S1
        if clipped is None or not crow.all():
            WS, Wg = W @ S, W @ g
            if any_plain:
                WS[:, plain], Wg[:, plain] = S[:, plain], g[:, plain]
            sS, sg = ones @ WS, ones @ Wg  # (W is symmetric: 1' W S)
            sSS, sSg, sgg = ones @ (S * WS), ones @ (S * Wg), ones @ (g * Wg)
            r0, rS, rg = ones @ (w1 * r), ones @ (r * WS), ones @ (r * Wg)
            m = ones @ w1
        if clipped is not None:
            w = _censored(clipped, r)
            Sw, gw = S * w, g * w
            rw = r * w
            sums = (ones @ w, ones @ Sw, ones @ gw, ones @ (S * Sw), ones @ (S * gw),
                    ones @ (g * gw), ones @ rw, ones @ (rw * S), ones @ (rw * g))
            if crow.all():
                m, sS, sg, sSS, sSg, sgg, r0, rS, rg = sums
            else:  # (the windows without a clipped pixel keep their weights)
                m, sS, sg, sSS, sSg, sgg, r0, rS, rg = (
                    np.where(crow, c, np.broadcast_to(f, crow.shape)) for c, f in zip(
                        sums, (m, sS, sg, sSS, sSg, sgg, r0, rS, rg), strict=True))
            r = np.where(crow[None, :], rw, r)
        # the symmetric [[m, sS, sg], [sS, sSS, sSg], [sg, sSg, sgg]] by its cofactors
        c00 = sSS * sgg - sSg * sSg
        c01 = sSg * sg - sS * sgg
        c02 = sS * sSg - sSS * sg
        c11 = m * sgg - sg * sg
        c12 = sS * sg - m * sSg
        c22 = m * sSS - sS * sS
        det = m * c00 + sS * c01 + sg * c02
        det = np.where(np.abs(det) > 1e-12, det, np.inf)
        a1 += (c00 * r0 + c01 * rS + c02 * rg) / det
        D += (c01 * r0 + c11 * rS + c12 * rg) / det
        u = u + np.clip((c02 * r0 + c12 * rS + c22 * rg) / det, -1.0, 1.0)
    # (the misfit: the residuals' plain scatter; a censored fit's over its kept pixels)
    if clipped is None:
        r0, m = ones @ r, float(ones.size)
    else:
        r0 = np.where(crow, r0, ones @ r)
        m = np.where(crow, m, float(ones.size))
    misfit = np.sqrt(np.maximum(ones @ (r * r) - r0 * r0 / m, 0.0) / np.maximum(m, 1.0))
    return u, D, misfit


_FULL, _ZERO = 254.5, 0.5  # a pixel at or beyond these (8-bit DN) is clipped


def _clipped(P: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The pixels of the windows P at the sensor's full scale and at zero (frames are
    in 8-bit DN of the sensor's full scale, :func:`alignd.vision.edges.as_gray`), or
    None where none is (a float frame of another scale is not clipped at all)."""
    hi, lo = float(P.max()), float(P.min())
    full = _FULL <= hi <= 255.0 + 1e-3
    zero = -1e-3 <= lo <= _ZERO
    if not (full or zero):
        return None
    return ((P >= _FULL) if full else np.zeros(P.shape, bool),
            (P <= _ZERO) if zero else np.zeros(P.shape, bool))


def _unclipped_blur(blur_e: np.ndarray, s_each: np.ndarray, ks: np.ndarray,
                    cl: tuple[np.ndarray, np.ndarray], sub: np.ndarray, ne: int) -> np.ndarray:
    """Each edge's blur from its columns without a clipped pixel (at least 3 of them), or
    else the median of the edges that have them (one lens blurs them all alike), or else
    the median of ``blur_e`` (every edge clipped: their censored fits). With its step's
    top (or foot) clipped away, a column's blur trades off against its contrast: on a
    synthetic edge clipped at 42 % of its height the fitted blur was 0.7-0.9 of the
    true one; a clipped side of a holder (tests/test_vision_holder_clip.py) 1.10 px for
    1.3."""
    clean = ~(cl[0][sub] | cl[1][sub]).any(axis=1)
    n_clean = np.bincount(ks, weights=clean.astype(float), minlength=ne)
    med = segment_median(s_each[clean], ks[clean], ne, upper=False) if clean.any() else \
        np.full(ne, np.nan)
    have = (n_clean >= 3) & np.isfinite(med)
    if not have.any():
        # every edge clipped: their censored fits' median (one side's alone scattered
        # by 0.2 px at a blur of 0.8 px on a synthetic holder 15 DN beyond full scale)
        return np.full(ne, float(np.median(blur_e)))
    return np.where(have, med, float(np.median(med[have])))


def _censored(clipped: tuple[np.ndarray, np.ndarray], r: np.ndarray) -> np.ndarray:
    """Each pixel's weight in the fit: 0 where it is clipped and the model lies beyond
    the clip as well (the residual ``r`` = data - model <= 0 at full scale, >= 0 at
    zero: the data say only that the level is beyond the clip, which it is), else 1.

    A clipped pixel read as a level pulls a soft edge's step toward the clipped side's
    flat top: a light holder saturating the sensor (half of its edge pixels at full
    scale) had its profile sides 0.2-0.3 px inward and the area method's 0.35 px
    outward."""
    hi, lo = clipped
    return (~((hi & (r <= 0.0)) | (lo & (r >= 0.0)))).astype(np.float64)


_MIN_GAP = 4.0  # px along an edge from its corner: the closest any position window reaches
# the corner clearance in blur widths: at 2 widths the neighbour's blurred step has 2.3 %
# of its height left in the nearest window pixel (0.6 % at 2.5), and the end columns, the
# corners' lever, reach half a width further on a soft side. Corpus corners, uncompressed
# (px): bench seed 0.0352 at 2.5, 0.0347 at 2 and at 1.5, 0.0346 at 1; seed 177 (raw and
# JPEG) 0.0366 / 0.0361 / 0.0359 at 2.5 / 2 / 1.5. Our renderer's sides (blur 0.6 px) are
# held by _MIN_GAP either way
_CLEAR_BLUR = 2.0


def _corner_clearance(blur: np.ndarray, slope: np.ndarray, nu: np.ndarray, hw: int
                      ) -> np.ndarray:
    """Each edge's distance (px along it) from its corner beyond which its position window
    (+-hw px across, minor axis) stays clear of most of the neighbouring side's
    transition: _CLEAR_BLUR blur widths and a pixel from the nearest window pixel, which a
    tilted edge's window brings hw |sin| nearer the neighbour (a perpendicular side)."""
    return np.maximum(_MIN_GAP, _CLEAR_BLUR * blur + 1.0 + hw * np.abs(slope) * nu)


def _line_through(t: np.ndarray, c: np.ndarray) -> tuple[float, float, float]:
    """Least-squares line through a few points: its value at their mean t, its slope and
    that mean t (closed form: np.polyfit's SVD costs 0.1 ms a call)."""
    tm = float(t.sum()) / t.size  # (np.mean's own sum and division, without its overhead)
    d = t - tm
    b = float(d @ c) / max(float(d @ d), 1e-12)
    return float(c.sum()) / c.size, b, tm


def _extended(e: EdgePoints, by_px: float, shape: tuple[int, ...]) -> EdgePoints:
    """``e`` with columns (rows) added at each end out to ``by_px`` further along the edge,
    their crossings extrapolated from the line through the end's 16 nearest (the profile
    fit starts there and corrects it), as many at each end."""
    t, c = (e.xy[:, 1], e.xy[:, 0]) if e.vertical else (e.xy[:, 0], e.xy[:, 1])
    order = np.argsort(t, kind="stable")
    t, c, con = t[order], c[order], e.contrast[order]
    a0, b0, m0 = _line_through(t[:16], c[:16])
    a1, b1, m1 = _line_through(t[-16:], c[-16:])
    k = int(by_px / math.hypot(1.0, (b0 + b1) / 2))  # columns per end
    limit = shape[0] if e.vertical else shape[1]
    k = min(k, int(t[0]), int(limit - 1 - t[-1]))  # (as many at each end, in the frame)
    if k < 1:
        return e
    th = t[0] - np.arange(k, 0, -1)
    tt = t[-1] + np.arange(1, k + 1)
    t2 = np.concatenate([th, t, tt])
    c2 = np.concatenate([a0 + b0 * (th - m0), c, a1 + b1 * (tt - m1)])
    con2 = np.concatenate([np.full(k, con[0]), con, np.full(k, con[-1])])
    xy = xy_columns(c2, t2) if e.vertical else xy_columns(t2, c2)
    return EdgePoints(xy, con2, e.vertical)


_END_FIT = 24  # given crossings nearest an end whose line an extended end must follow


def _ends_follow(t: np.ndarray, q: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The crossings to keep of an edge extended beyond its given ones (``lo`` .. ``hi``;
    ``t`` ascending): all, except an end whose added crossings stray as a group from the
    line through the nearest given ones (by more than 3 standard errors and 0.02 px):
    something other than the side's own straight edge near its corner (a rounded corner,
    a cast shadow's corner, a screw) that a single column's misfit does not show."""
    i0, i1 = int(np.searchsorted(t, lo, "left")), int(np.searchsorted(t, hi, "right"))
    keep = np.ones(t.size, bool)
    if i1 - i0 < _END_FIT:
        keep[:i0] = keep[i1:] = False
        return keep
    for added, near in ((slice(0, i0), slice(i0, i0 + _END_FIT)),
                        (slice(i1, t.size), slice(i1 - _END_FIT, i1))):
        ta = t[added]
        if ta.size == 0:
            continue
        a, b, tm = _line_through(t[near], q[near])
        tn = t[near] - tm
        resid = q[near] - a - b * tn
        sigma2 = float(resid @ resid) / (_END_FIT - 2)
        off = float((q[added] - a - b * (ta - tm)).sum()) / ta.size
        # the mean of the added crossings' residuals and the line's error at their mean
        dt = float(ta.sum()) / ta.size - tm
        se2 = sigma2 * (1.0 / ta.size + 1.0 / _END_FIT + dt * dt / float(tn @ tn))
        if abs(off) > 3.0 * math.sqrt(se2) + 0.02:
            keep[added] = False
    return keep


def _rows(gray: np.ndarray, edges: list[EdgePoints], use: list[int]) -> _Rows:
    h, w = gray.shape
    parts = []
    for k, i in enumerate(use):
        e = edges[i]
        n = e.xy.shape[0]
        t, c = (e.xy[:, 1], e.xy[:, 0]) if e.vertical else (e.xy[:, 0], e.xy[:, 1])
        ti = np.rint(t).astype(np.intp)
        parts.append((np.full(n, k), ti, c, e.contrast, ti * w if e.vertical else ti,
                      np.full(n, 1 if e.vertical else w, np.intp),
                      np.full(n, w if e.vertical else h, np.intp)))
    cols = [np.concatenate(p) for p in zip(*parts, strict=True)]
    return _Rows(*cols)


def _edge_slopes(rows: _Rows, n_edges: int) -> np.ndarray:
    """Each edge's slope d(minor)/d(major) by least squares, all edges at once."""
    n = np.bincount(rows.edge, minlength=n_edges).astype(float)
    t = rows.t.astype(float)
    st, sc = (np.bincount(rows.edge, weights=v, minlength=n_edges) for v in (t, rows.c))
    stt = np.bincount(rows.edge, weights=t * t, minlength=n_edges)
    stc = np.bincount(rows.edge, weights=t * rows.c, minlength=n_edges)
    den = n * stt - st * st
    return np.where(np.abs(den) > 1e-9, (n * stc - st * sc) / np.where(den == 0, 1.0, den),
                    0.0)


def fit_crossings(gray: np.ndarray, edges: list[EdgePoints], *, half_width: int = 5,
                  iterations: int = 2, max_half_width: int = 10) -> list[EdgePoints]:
    """Refine the area-method crossings of straight edges (one EdgePoints each) by the
    profile fit, all edges in one batch; see :func:`fit_crossings_blur`."""
    return fit_crossings_blur(gray, edges, half_width=half_width, iterations=iterations,
                              max_half_width=max_half_width)[0]


@dataclass(frozen=True)
class ProfileFit:
    """The refined crossings of each edge, its Gaussian width (px; NaN where it had too few
    crossings) and how far the area method, which has no penumbra in its model, may err
    where a penumbra was fitted with the edge beside it (px along the normal, the median
    over its columns of the larger of the fit's move and the bend's weight in the area
    method's balance; 0 elsewhere)."""

    edges: list[EdgePoints]
    widths: np.ndarray
    bend_px: np.ndarray
    penumbra: bool = False  # a penumbra beside an edge was modelled


def fit_crossings_blur(gray: np.ndarray, edges: list[EdgePoints], *, half_width: int = 5,
                       iterations: int = 2, max_half_width: int = 10,
                       blur: np.ndarray | None = None, corner_gap_px: float | None = None
                       ) -> tuple[list[EdgePoints], np.ndarray]:
    """:func:`fit_profiles`' crossings and widths."""
    fit = fit_profiles(gray, edges, half_width=half_width, iterations=iterations,
                       max_half_width=max_half_width, blur=blur, corner_gap_px=corner_gap_px)
    return fit.edges, fit.widths


def fit_profiles(gray: np.ndarray, edges: list[EdgePoints], *, half_width: int = 5,
                 iterations: int = 2, max_half_width: int = 10,
                 blur: np.ndarray | None = None, corner_gap_px: float | None = None,
                 penumbra: bool = True) -> ProfileFit:
    """Refine the area-method crossings of straight edges (one EdgePoints each) by the
    profile fit, all edges in one batch (every step is a few array operations for all the
    columns of all the edges together: the cost is that of the arithmetic, not of the
    calls); returns the refined crossings and each edge's Gaussian width (NaN where the
    edge had too few crossings).

    Each edge's Gaussian width is the median of per-column fits of a few of its columns,
    in a window widened (up to ``max_half_width``) to hold the whole transition and the
    tails beyond it, or, given ``blur`` (one finite width per edge: a tracked frame's
    previous widths, where its sides did not move), that width, which skips its estimate
    (a third of the cost). The positions are fitted in a window holding the transition's
    core (``_FIT_REACH`` widths) and the tails; the ends of each edge are trimmed as much
    as a window is widened. Columns whose fit
    left the window's middle are dropped. The refined crossings' ``contrast`` is the fitted
    step's height (the area method's, read from the window's tails, is the clip's where the
    edge's pixels are clipped).

    ``corner_gap_px``: the given crossings stop this far (along the edge) short of its
    ends, the corners, where a neighbouring side's transition would enter an area
    window. The positions then reach further, as close to the corners as the edge's own
    blur and slope let the position window stay clear of the neighbour
    (:func:`_corner_clearance`; the end columns are the corners' lever).

    ``penumbra``: whether to look for a cast shadow's penumbra beside the edges
    (:func:`_penumbra_bend`; a tracked frame whose sides held, where the previous one had
    none, does not); ``penumbra`` of the result: whether one was modelled.
    """
    empty = [EdgePoints(np.empty((0, 2)), np.empty(0), e.vertical) for e in edges]
    given_n = [e.xy.shape[0] for e in edges]
    bend_px = np.zeros(len(edges))
    gap_px = 0.0 if corner_gap_px is None else float(corner_gap_px)
    extend = gap_px > _MIN_GAP
    if extend:
        edges = [_extended(e, gap_px - _MIN_GAP, gray.shape) if e.xy.shape[0] >= 8 else e
                 for e in edges]
    widths = np.full(len(edges), np.nan)
    use = [i for i, e in enumerate(edges) if given_n[i] >= 8]
    if not use:
        return ProfileFit(empty, widths, bend_px)
    ne = len(use)
    flat = np.ascontiguousarray(gray).ravel()
    rows = _rows(gray, edges, use)
    slope = _edge_slopes(rows, ne)
    nu = 1.0 / np.hypot(1.0, slope)  # |normal . minor axis|
    wa, wb = nu, np.abs(slope) * nu  # the pixel's footprint across the edge: |n_x|, |n_y|
    given = None if blur is None else np.asarray(blur, float)[use]
    n_all = np.bincount(rows.edge, minlength=ne)  # >= 8 each
    lo = np.minimum.reduceat(rows.t, np.cumsum(n_all) - n_all)
    hi = np.maximum.reduceat(rows.t, np.cumsum(n_all) - n_all)
    added = np.zeros(ne, np.intp)  # columns (major px) added at each end (corner_gap_px)
    if extend:
        added = np.array([(edges[i].xy.shape[0] - given_n[i]) // 2 for i in use])
        lo, hi = lo + added, hi - added

    def window(hw: int, trim_ends: bool = True, reach: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, _Rows, np.ndarray, np.ndarray]:
        """Every row's window of +-hw px and the tails' slopes, over the given crossings
        (``reach``: and that many major px beyond each end of an extended edge); a window
        wider than ``half_width`` reaches further toward the corners: with ``trim_ends``
        the ends are trimmed as much."""
        trim = np.zeros(ne) if reach is None else -reach
        if hw > half_width and trim_ends:
            trim = trim + (hw - half_width) * (1.0 + np.abs(slope))
        # (an extended edge's added columns are left out unless ``reach`` takes them in)
        r0 = rows if not (extend or np.any(trim)) else rows.take(
            (rows.t >= lo[rows.edge] + trim[rows.edge])
            & (rows.t <= hi[rows.edge] - trim[rows.edge]))
        P, centre, ok = _windows(flat, r0, hw)
        r1 = r0.take(ok)
        b1, b2 = _tail_slopes(P, r1.edge, ne)
        return P, centre, r1, b1, b2

    def needed(blur_e: np.ndarray, k: float = 3.0) -> int:
        """The half width holding the widest edge's transition out to ``k`` blur widths
        and the tails beyond it."""
        reach = (k * blur_e + 0.5 * (wa + wb)) / nu  # transition, minor px
        return int(min(max(half_width, math.ceil(float(reach.max())) + _TAILS),
                       max_half_width))

    built = -1  # the half width of the windows P holds
    if given is not None and np.all(np.isfinite(given)):
        blur_e = given
    else:
        # the blur: a few columns of each edge (every n/8-th), width free; estimated
        # again in the wider window it calls for (in +-5 px the tails lie inside a soft
        # transition, read part of it as illumination slope and the blur as 10-20 %
        # smaller at 1.2-2 px)
        est = half_width
        for _ in range(3):
            P, centre, r1, b1, b2 = window(est)
            built = est
            if r1.edge.size == 0:
                return ProfileFit(empty, widths, bend_px)
            counts = np.bincount(r1.edge, minlength=ne)
            pos = np.arange(r1.edge.size) - (np.cumsum(counts) - counts)[r1.edge]
            sub = pos % np.maximum(counts // 8, 1)[r1.edge] == 0
            ks = r1.edge[sub]
            x = np.arange(-est, est + 1, dtype=float)
            cl = _clipped(P)
            _, _, s_each = _fit(P[sub], x, (r1.c - centre)[sub], np.ones(ks.size), nu[ks],
                                wa[ks], wb[ks], b1[sub], b2[sub], 4,
                                None if cl is None else (cl[0][sub], cl[1][sub]))
            blur_e = np.nan_to_num(segment_median(s_each, ks, ne, upper=False), nan=1.0)
            if cl is not None:
                blur_e = _unclipped_blur(blur_e, s_each, ks, cl, sub, ne)
            wider = needed(blur_e)
            if wider <= est:
                break
            est = wider
    # the positions: in the window the transition's core needs (see _FIT_REACH)
    hw = needed(blur_e, _FIT_REACH)
    # (its ends untrimmed: the position window holds 1.5 widths, the adjacent side's
    # transition stays out of the end columns' windows or they misfit and are dropped,
    # and the end columns are the corners' lever; trimmed as the blur window is, the
    # corpus corners were worse: uncompressed 0.0427 -> 0.0444 px, optics 0.058 -> 0.062)
    # an extended edge: as close to its corners as its clearance lets the window reach
    reach = None
    if np.any(added > 0):
        reach = np.clip((gap_px - _corner_clearance(blur_e, slope, nu, hw)) * nu, 0.0, added)
    if hw != built or hw > half_width or reach is not None:
        P, centre, r1, b1, b2 = window(hw, trim_ends=False, reach=reach)
    if r1.edge.size == 0:
        return ProfileFit(empty, widths, bend_px)
    x = np.arange(-hw, hw + 1, dtype=float)
    widths[use] = blur_e
    geo = np.column_stack([slope, nu, wa, wb])
    table = _step_table(float(hw), blur_e, geo)
    # pixels clipped at the sensor's full scale or at zero say only that the level is
    # beyond the clip (:func:`_censored`); the levels then start off, hence more steps
    cl = _clipped(P)
    clipped = None if cl is None else (np.ascontiguousarray(cl[0].T),
                                       np.ascontiguousarray(cl[1].T))
    if clipped is not None:
        iterations += 2
    u, D, misfit = _fit_tabulated(P, x, r1.c - centre, r1.edge, blur_e, geo, b1, b2,
                                  iterations, table, clipped=clipped)
    if np.any(blur_e > _WIDE_BLUR):
        # a soft side: the tails' slopes once more, the fitted step's own tail taken off,
        # and the positions again from there (on a sharp one the step's tail is gone
        # within the window and a slope's error moves the crossing little)
        ok0 = np.isfinite(u) & np.isfinite(D)
        u0 = np.where(ok0, u, r1.c - centre)
        b1, b2 = _refit_slopes(flat, P, x, r1, u0, np.where(ok0, D, 0.0), blur_e, table,
                               geo, b1, b2, hw, ne)
        u, D, misfit = _fit_tabulated(P, x, u0, r1.edge, blur_e, geo, b1, b2, iterations,
                                      table, clipped=clipped)
    ok1 = np.isfinite(u) & np.isfinite(D)
    u1 = np.where(ok1, u, r1.c - centre)
    bend = _penumbra_bend(flat, r1, u1, np.where(ok1, D, 0.0), hw, table, geo, b1, b2, ne,
                          blur_e) if penumbra else None
    if bend is not None:
        u, D, misfit = _fit_tabulated(P, x, u1, r1.edge, blur_e, geo, b1, b2, iterations,
                                      table, (bend.lo, bend.hi), clipped)
        # where the penumbra was fitted with the edge and that fit moves it clearly, it
        # places the edge (and it has the blur, which a penumbra across the edge widens)
        sh = np.where(np.abs(bend.shift) >= _SHIFT_MIN, bend.shift, np.nan)[r1.edge]
        u = np.where(np.isfinite(sh) & ok1, u1 + sh, u)
        widths[use] = np.where(np.isfinite(bend.blur), bend.blur, blur_e)
        # (only where the penumbra was fitted with the edge: a bend from the floor beyond
        # the window alone is an extrapolation that may be wrong; a narrow shadow band
        # read as a 2.2 px blur, synthetic holder 0.6 px off, had one)
        both = (ok1 & np.isfinite(u) & np.isfinite(D) & (np.abs(D) > 1e-6)
                & np.isfinite(bend.shift)[r1.edge])
        # what the area method, which reads the window's levels as step, makes of the
        # bend: each DN of it over a pixel moves its balance by 1 / D px
        Sb = _table_step(table, r1.edge, nu[r1.edge] * (x[:, None] - np.where(both, u, 0.0)))
        area = np.abs((bend.lo * (1.0 - Sb) + bend.hi * Sb).sum(axis=0)
                      / np.where(both, D, 1.0)) * nu[r1.edge]
        moved = np.maximum(np.abs(u - u1) * nu[r1.edge], area)
        bend_px[use] = np.nan_to_num(segment_median(moved[both], r1.edge[both], ne,
                                                    upper=False))
    good = np.isfinite(u) & (np.abs(u) < hw - _TAILS) & (np.abs(D) > 1e-6)
    # a column the model does not fit (a hole, a screw or a shadow's edge in its window)
    typical = segment_median(misfit, r1.edge, ne, upper=False)
    good &= misfit <= _MISFIT * typical[r1.edge] + 0.5
    p = centre + u
    out = list(empty)
    for k, sel in enumerate(edge_rows(good, r1.edge, ne)):
        i = use[k]
        t, q = r1.t[sel].astype(float), p[sel]
        if added[k] > 0:
            keep = _ends_follow(t, q, float(lo[k]), float(hi[k]))
            t, q, sel = t[keep], q[keep], sel[keep]
        vertical = edges[i].vertical
        xy = xy_columns(q, t) if vertical else xy_columns(t, q)
        out[i] = EdgePoints(xy, D[sel], vertical)
    return ProfileFit(out, widths, bend_px, bend is not None)
