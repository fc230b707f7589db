"""A check of a found holder's sides: does a side's edge step twice within a few pixels?

A sharp dark holder lit by a small lamp casts a hard shadow: a band 1-7 px wide, darker
than the disc, along the sides facing away from the lamp (a sample strip or a perspective
wall darker than the disc beside a dark holder is such a band too). Across that side the
image steps twice the same way (holder -> band -> disc), and both steps fall in the edge
windows: the area method and the profile fit each put the side somewhere between the two
steps (a 1.5-4 px band moved corners by 1.1-2.7 px, and passed every other check). Wider
bands are the coarse search's and :mod:`alignd.vision.holder_steps`' (the side taken on
the band's outer edge).

Here the pixels within 8 px of each side's middle 70 % are binned by their exact distance
to it (0.2 px bins: the edge spread function, super-resolved by the side's slant) and
fitted by one blurred step and by two steps of one blur, each with the levels' linear slope
and a pixel's exact response (:func:`alignd.vision.profile_fit.step_response`; an erf
instead read a sharp edge's pixel squares as two steps 1 px apart). A side whose profile
two steps of the same sign fit far better, resolved, the smaller a fair share of both, lies
beside a band when the found side is 0.3 px or more outside the inner step: between the
two, or on the outer one (a band nearly as dark as the holder merges with it) with the
inner one at most 4.5 px in, and the face beyond the inner step is flat (a brushed face's
lines along a side make such steps too, one after another). The holder's own edge is the
inner step: a shadow, a strip or a wall lies outside the top face. (A band inside the face
along one side reads the same way, and is cut off: a chamfer lit apart, a label flush with
the edge. Its inner edge is then a rigid edge of the holder all the same, while a shadow's
outer edge moves with the light. A band along opposite sides is taken for such and left
alone, see :func:`side_bands`; so is a band at the level of the face just inside the
opposite side: the holder's face round a sample plate, :func:`plate_rim`.) A side along
the pixel rows samples its profile once a pixel, and there a blur not quite Gaussian fits
two steps about 1 px apart far better than one: such a side must also misfit one step by
more than a blur's shape can. A band narrower than about 1 px is not resolved from the
edge's own blur and still moves the side by up to half a pixel.

A soft band (a cast shadow 1-3 px beyond a side, its edge blurred by the lamp's penumbra
as well as the lens) lies about one blur from the edge: two steps of one blur do not
resolve it. Where no band is found so, a side fitted softer than the other three is
fitted again with its inner step held at their blur (one lens blurs the flat face's four
sides alike) and its outer step at least as soft (:func:`_soft_bands`). Where there is no
soft band either, a side one step misfits may lie at a cast shadow's soft edge, the shadow
seen only beyond the holder's edge (:mod:`alignd.vision.holder_tails`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from alignd.vision.batch_lm import best_starts, fit_rows, pixel_variance, standard_error
from alignd.vision.holder_steps import side_frame
from alignd.vision.holder_tails import Tail, shadow_tails
from alignd.vision.lens import Lens
from alignd.vision.profile_fit import disc_edge, step_response

__all__ = ["REACH", "Band", "SideProfiles", "band_levels", "fit_steps", "one_disc_edge",
           "plate_rim", "profile_bins", "read_sides", "side_bands", "side_profiles",
           "steps_model"]

REACH = 8.0  # px either side of the found side: the profiles :func:`side_bands` reads
_BIN = 0.2  # px: the pixels are binned by their distance to the side
_MAX_BLUR = 4.0  # px: the steps' blur is fitted within 0.2 and this (:func:`fit_steps`)
_ALONG = (0.15, 0.85)  # the part of the side read (corners and their shadows left out)
# the decision (docs/vision.md, "A side between two steps"): two steps of one sign fit a
# side _MIN_GAIN times better than one, their sum within _WHOLE of the side's whole step
# (tails to tails), their blur at most _SHARPER px over the one step's, at least _MIN_SEP
# px and _RESOLVED blurs apart (1.5 once: seed 6100 #654, an edge blurred 1.5 px,
# fitted two steps 1.3 blurs apart 5 times better than one; the misfit rule below now
# holds it even at 1.2, and a soft band 3 px wide in a 2.2 px blur is 1.34-1.49 blurs:
# 1.3 px wrong at 1.5), the smaller at least _MIN_SHARE of both (bands nearly as dark
# as the holder: 0.18-0.20), and the found side at least _MIN_OFF px outside the inner
# one and either _MIN_IN px inside the outer one or within _ON_OUTER px of it with the
# inner one at most _MAX_IN px in (farther in, a second step 5-7 px inside a corpus face
# is not a band). A side not sampled finely (_GAP) must misfit one step by _MIN_MISS of
# its step: our renderer's holder at 0 deg, one sample a pixel, misfits by 0.8-0.9 %
# (two steps 0.9 px apart fit it 55 times better), bands of 1.5-3 px by 2.2-8.5 %.
# Synthetic hard bands 1.5-4 px: gains 6-8000; eight corpora of 1001 scenes: one scene
# moved, 0.59 -> 0.31 px.
_MIN_GAIN = 3.0
_WHOLE = 0.3
_SHARPER = 0.3
_MIN_SEP = 0.6
_RESOLVED = 1.3
_MIN_SHARE = 0.15
# ... or at least _MIN_SHARE_CLEAR where two steps fit _CLEAR_GAIN times better than one:
# a band 1.5 px wide along a side square to the pixel grid, sampled once a pixel, reads
# its smaller step at 11-14 % (gain 4600, 1.4 px wrong before); the renderer's blur that
# is not Gaussian, read as two steps on such a side, 8 % (gain 57)
_MIN_SHARE_CLEAR = 0.10
_CLEAR_GAIN = 1000.0
_MIN_OFF = 0.3
_MIN_IN = 0.2
_ON_OUTER = 0.5
_MAX_IN = 4.5
_GAP = 0.6  # of a pixel's footprint across the side: the largest gap between distances
_MIN_MISS = 0.015
_WORSE = 2.0  # only sides one step fits this many times worse than the best side get two


@dataclass(frozen=True)
class Band:
    """Side ``side`` (corner ``side`` to ``side + 1``) steps twice: its inner step lies
    ``inner_px`` from the found side (negative: inside) and is the holder's edge. (At a
    shadow's soft edge, :func:`_soft_or_tails`, the edge may lie outside; no share and
    no band level.)"""

    side: int
    inner_px: float
    outer_px: float
    share: float  # the smaller step over both
    gain: float  # the one step's residual sum of squares over the two steps'
    sigma_px: float  # standard error of inner_px (from the fit's residuals)
    levels: tuple[float, float]  # DN: the band's level and the face's beyond its inner step
    tail: bool = False  # a shadow's soft edge at the side, no band (:func:`_soft_or_tails`)


@dataclass(frozen=True)
class SideProfiles:
    """The four sides' profiles across them (:func:`side_profiles`): the bins' mean
    distances to the side (+ outward), mean levels, pixel counts and the pixels' spread
    within them (sums of squares about the bin's mean), each (4, bins); the bins' edges;
    the sides' footprint widths (4, 2), a pixel's square seen across the side
    (:func:`step_response`); and each bin's count of clipped pixels (at the sensor's full
    scale or at zero). Read once, the band check and the neighbour look share it."""

    x: np.ndarray
    m: np.ndarray
    cnt: np.ndarray
    within: np.ndarray
    bins: np.ndarray
    foot: np.ndarray
    clipped: np.ndarray

    def within_reach(self, reach: float) -> SideProfiles:
        """The bins within ``reach`` px of the side (the edges a multiple of ``_BIN``)."""
        i = np.flatnonzero(np.abs(self.bins) <= reach + 1e-9)
        a, b = int(i[0]), int(i[-1])
        return SideProfiles(self.x[:, a:b], self.m[:, a:b], self.cnt[:, a:b],
                            self.within[:, a:b], self.bins[a:b + 1], self.foot,
                            self.clipped[:, a:b])


def profile_bins(reach: float) -> np.ndarray:
    """Bin edges ``_BIN`` px apart from -``reach`` to ``reach``: those of a smaller reach
    are exactly a slice of a larger one's (:meth:`SideProfiles.within_reach`)."""
    n = round(reach / _BIN)
    return _BIN * np.arange(-n, n + 1)


def read_sides(gray: np.ndarray, corners: np.ndarray, lens: Lens | None, reach: float
               ) -> SideProfiles:
    """:func:`side_profiles` of the quadrilateral ``corners`` (frame pixels) within
    ``reach`` px of its sides, in ``_BIN`` px bins."""
    c = np.asarray(corners, float)
    return side_profiles(gray, c if lens is None else lens.undistort(c), lens,
                         profile_bins(reach))


def side_profiles(gray: np.ndarray, ci: np.ndarray, lens: Lens | None,
                  bins: np.ndarray) -> SideProfiles:
    """Each side's pixels within the ``bins``' reach of it along its middle (``_ALONG``),
    binned by their distance to it in the ideal image (``ci``: the corners there; +
    outward; ``bins``: the bins' edges), as :class:`SideProfiles`."""
    h, w = gray.shape
    flat = gray.reshape(-1) if gray.flags.c_contiguous else np.ascontiguousarray(gray).reshape(-1)
    edge, length, n = side_frame(ci)
    u = edge / np.maximum(length, 1e-9)[:, None]
    nb = bins.size - 1
    far = float(np.max(np.abs(bins)))
    mids = 0.5 * (bins[:-1] + bins[1:])
    xs, ms, cnt = np.tile(mids, (4, 1)), np.zeros((4, nb)), np.zeros((4, nb))
    within, clipped = np.zeros((4, nb)), np.zeros((4, nb))
    for k in range(4):
        # the side's middle, traced in the frame one pixel column (row) at a time
        t = np.linspace(_ALONG[0], _ALONG[1], 16) * length[k]
        q = ci[k] + t[:, None] * u[k]
        q = q if lens is None else lens.distort(q)
        across = 0 if abs(u[k, 0]) >= abs(u[k, 1]) else 1  # columns (0) or rows (1)
        order = np.argsort(q[:, across])
        lo, hi = math.ceil(q[order[0], across]), math.floor(q[order[-1], across])
        if hi - lo < 8:
            continue
        major = np.arange(lo, hi + 1, dtype=float)
        minor = np.interp(major, q[order, across], q[order, 1 - across])
        reach = math.ceil(far / max(abs(u[k, across]), 0.5)) + 2
        mi = np.rint(minor)[:, None] + np.arange(-reach, reach + 1, dtype=float)[None, :]
        ma = major[:, None]
        xx, yy = (ma, mi) if across == 0 else (mi, ma)  # (rows, 1) and (rows, offsets)
        if lens is None:
            d = (xx - ci[k, 0]) * n[k, 0] + (yy - ci[k, 1]) * n[k, 1]
            along = (xx - ci[k, 0]) * u[k, 0] + (yy - ci[k, 1]) * u[k, 1]
        else:
            px = np.stack(np.broadcast_arrays(xx, yy), axis=-1).reshape(-1, 2)
            pi = lens.undistort(px) - ci[k]
            d = (pi @ n[k]).reshape(mi.shape)
            along = (pi @ u[k]).reshape(mi.shape)
        keep = ((xx >= 0) & (xx < w) & (yy >= 0) & (yy < h) & (d >= bins[0]) & (d < bins[-1])
                & (along >= _ALONG[0] * length[k]) & (along <= _ALONG[1] * length[k]))
        d = d[keep]
        at = (np.broadcast_to(yy, keep.shape)[keep] * w
              + np.broadcast_to(xx, keep.shape)[keep]).astype(np.intp)
        v = flat[at].astype(float)
        idx = np.clip(np.searchsorted(bins, d) - 1, 0, nb - 1)
        c = np.bincount(idx, minlength=nb).astype(float)
        m = np.bincount(idx, v, nb) / np.maximum(c, 1)
        held = c > 0
        xs[k, held] = np.bincount(idx, d, nb)[held] / c[held]
        ms[k], cnt[k] = m, c
        within[k] = np.bincount(idx, v * v, nb) - c * m * m
        if v.size and float(v.max()) <= 255.0 + 1e-3:  # (a float frame above: unclipped)
            clipped[k] = np.bincount(idx, (v >= 254.5) | (v <= 0.5), nb)
    foot = np.sort(np.abs(n), axis=1)[:, ::-1]
    return SideProfiles(xs, ms, cnt, within, bins, foot, clipped)


def steps_model(P: np.ndarray, x: np.ndarray, foot: np.ndarray, steps: int,
                own_blur: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The profile a + g x + sum_j c_j S(x - d_j) for each row of P = (a, g, s, c_1, d_1,
    ...) at the distances ``x`` (rows), S a pixel's response to a step blurred by s
    (:func:`step_response`, the footprint ``foot``), and its Jacobian: (B, bins) and
    (B, bins, 3 + 2 steps). ``own_blur``: the last step has its own blur, P's last
    column (a penumbra beside an edge)."""
    s = P[:, 2:3]
    f = P[:, 0:1] + P[:, 1:2] * x
    cols = [np.ones_like(f), x, np.zeros_like(f)]
    last = []
    # every step's response in one call (B, steps, bins): the arrays are small
    blurs = np.repeat(s, steps, axis=1)
    if own_blur:
        blurs[:, -1] = P[:, -1]
    SS, SS1, SS2 = step_response(x[:, None, :] - P[:, 4:4 + 2 * steps:2, None],
                                 blurs[:, :, None], foot[:, None, 0:1], foot[:, None, 1:2])
    for j in range(steps):
        c = P[:, 3 + 2 * j:4 + 2 * j]
        S, S1, S2 = SS[:, j], SS1[:, j], SS2[:, j]
        f = f + c * S
        if own_blur and j == steps - 1:
            last = [c * P[:, -1:] * S2]
        else:
            cols[2] = cols[2] + c * s * S2  # dS/ds = s d2S/dd2
        cols += [S, -c * S1]
    return f, np.stack(cols + last, axis=2)


def fit_steps(P: np.ndarray, x: np.ndarray, m: np.ndarray, w: np.ndarray, foot: np.ndarray,
              steps: int, iterations: int = 40, reach: float = REACH, own_blur: bool = False,
              held_blur: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt for many profiles at once (rows of ``P``; ``x``, ``m`` the
    profiles, ``w`` their weights, ``foot`` the pixels' footprints; the steps kept within
    ``reach`` - 0.5 px of the side; ``own_blur``: see :func:`steps_model`): the
    parameters, the weighted residual sums of squares and the normal matrices at the end.
    ``held_blur`` (one a row): the shared blur held there, and with ``own_blur`` the last
    step's kept at least as wide (an edge of a known blur with a softer step beside it)."""
    P = P.copy()
    # the bounds (one row a profile): the blurs within 0.2-4 px, the steps within reach
    lo, hi = np.full(P.shape, -np.inf), np.full(P.shape, np.inf)
    lo[:, 2], hi[:, 2] = 0.2, _MAX_BLUR
    if own_blur:
        lo[:, -1], hi[:, -1] = 0.2, _MAX_BLUR
    if held_blur is not None:
        lo[:, 2] = hi[:, 2] = P[:, 2] = held_blur
        if own_blur:
            lo[:, -1] = held_blur
            P[:, -1] = np.clip(P[:, -1], lo[:, -1], hi[:, -1])
    lo[:, 4::2], hi[:, 4::2] = -reach + 0.5, reach - 0.5

    def model(Q: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return steps_model(Q, x[rows], foot[rows], steps, own_blur)

    return fit_rows(P, model, m, w, lo, hi, iterations)


def _one_step_residuals(prof: SideProfiles, P1: np.ndarray, k: int) -> np.ndarray:
    """Side ``k``'s profile less its one-step fit (row ``k`` of ``P1``)."""
    return prof.m[k] - steps_model(P1[k:k + 1], prof.x[k:k + 1], prof.foot[k:k + 1], 1)[0][0]


def _best_of_starts(P: np.ndarray, sides: np.ndarray, n_starts: int, prof: SideProfiles,
                    cnt: np.ndarray, own_blur: bool = False,
                    held_blur: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two steps fitted to each of ``sides`` (``prof``'s profiles, ``cnt`` their weights)
    from its ``n_starts`` rows of ``P`` (side by side): a few iterations from every start,
    then the best start of each side to the end (most starts of a side end in the same
    place; the others wander and cost iterations). ``own_blur``, ``held_blur`` (one a
    side of the four) as :func:`fit_steps`. Returns its parameters, residual sums and
    normal matrices, a row a side."""
    x, m, foot = prof.x, prof.m, prof.foot
    rows = np.repeat(sides, n_starts)
    held = None if held_blur is None else held_blur[rows]
    P, cost, _ = fit_steps(P, x[rows], m[rows], cnt[rows], foot[rows], 2, iterations=5,
                           own_blur=own_blur, held_blur=held)
    best = best_starts(cost, n_starts)
    held = None if held_blur is None else held_blur[sides]
    return fit_steps(P[best], x[sides], m[sides], cnt[sides], foot[sides], 2,
                     own_blur=own_blur, held_blur=held)


def _resolvable(x: np.ndarray, r: np.ndarray, cnt: np.ndarray, inner: float, outer: float,
                foot: np.ndarray, step: float) -> bool:
    """Whether two steps at ``inner`` and ``outer`` can be told from one on these bins
    (``x`` distances, ``r`` the one step's residuals, ``cnt`` pixels), over the band and
    1.5 px either side of it: the pixels sample it at least twice a pixel's footprint
    across the side (no gap between their distances over ``_GAP`` of it, as on a slanted
    side), or the one step misfits it by ``_MIN_MISS`` of ``step`` (rms). A side along
    the pixel rows samples its profile once a footprint, and there a blur not quite
    Gaussian misfits a clean edge by up to about 1 % of its step, which two steps about
    1 px apart fit far better (our renderer's holder at 0 deg: 0.8-0.9 %, 55 times
    better); a band of 1.5 px or more misfits by 2 % and more."""
    near = (cnt > 0) & (x > inner - 1.5) & (x < outer + 1.5)
    if not near.any():
        return False
    d = np.sort(x[near])
    gaps = np.diff(np.concatenate([[inner - 1.5], d, [outer + 1.5]]))
    if d.size >= 2 and float(np.max(gaps)) <= _GAP * float(foot[0] + foot[1]):
        return True
    miss = math.sqrt(float(np.sum(cnt[near] * r[near] ** 2) / np.sum(cnt[near])))
    return miss >= _MIN_MISS * abs(step)


# one disc-defocused edge fitting within _DISC_SLACK times two Gaussian steps' residual sum
# is a lens out of focus, not two steps (:func:`one_disc_edge`: a disc's edge 0.36-0.37,
# 2.5 through JPEG q 60; the drawn plates', shadows' and strips' steps 4.4-14000); the fit
# runs where one of _DISC_SCREEN_RADII (of 1.25 times the steps' distance) at their place
# fits within _DISC_SCREEN times
_DISC_SLACK = 3.0
_DISC_SCREEN, _DISC_SCREEN_RADII = 10.0, (0.8, 1.0, 1.25)


def _disc_cost(q: np.ndarray, x: np.ndarray, m: np.ndarray, sw: np.ndarray,
               foot: np.ndarray) -> np.ndarray:
    """The weighted residuals of one disc-defocused step at (place, radius) ``q``, its
    level, slope and height by linear least squares."""
    X = np.stack([np.ones_like(x), x, disc_edge(x - q[0], q[1], foot)])
    beta = np.linalg.lstsq((X * sw).T, m * sw, rcond=None)[0]
    return (m - beta @ X) * sw


def one_disc_edge(x: np.ndarray, m: np.ndarray, w: np.ndarray, foot: np.ndarray,
                  steps: tuple[float, float, float, float], cost2: float) -> bool:
    """Whether one step defocused by a disc fits a side's profile (``x``, ``m``, weights
    ``w``, footprint ``foot``) nearly as well as two Gaussian steps (``steps``: heights and
    places c1, d1, c2, d2; residual sum ``cost2``): within _DISC_SLACK times. A lens out
    of focus blurs by a disc, not a Gaussian: its edge ends abruptly a radius out on
    either side, and two Gaussian steps a radius apart, each half the edge's, fit it far
    better than one (a 4 px radius: 7-8 times). The neighbour look took each side of
    such a holder for a step with a second one 3.2 px from it and measured it again
    1.5 px off, and the band check (:func:`side_bands`) took a side for one between two
    steps and moved it in 1.1-1.5 px. A plate's edge or a shadow's beside the side is a
    level between two steps, which no one step fits."""
    c1, d1, c2, d2 = (float(v) for v in steps)
    if c1 * c2 <= 0:
        return False  # two steps opposite ways: no one step of any blur makes them
    sw = np.sqrt(w)
    # (the two steps' heights' mean place, and a radius 1.25 times their distance: a
    # disc's edge fits two Gaussian steps 0.8 of its radius apart)
    at, radius = (c1 * d1 + c2 * d2) / (c1 + c2), max(1.25 * abs(d2 - d1), 1.0)
    # a few radii there first: a plate's or a shadow's step misfits every one by far (the
    # fit below costs 1-3 ms a side)
    near = min(float(np.sum(_disc_cost(np.array([at, radius * f]), x, m, sw, foot) ** 2))
               for f in _DISC_SCREEN_RADII)
    if near > _DISC_SCREEN * cost2:
        return False
    try:
        res = least_squares(_disc_cost, np.array([at, radius]), args=(x, m, sw, foot),
                            method="trf", bounds=([-REACH, 0.5], [REACH, REACH]),
                            max_nfev=60)
    except (ValueError, np.linalg.LinAlgError):
        return False
    cost = float(np.sum(res.fun ** 2))
    return cost <= _DISC_SLACK * cost2


# the face beyond a band's inner step, read _DEEP px deep from _DEEP_FROM px plus
# _DEEP_BLURS of the steps' blur inside it, must vary (rms about a line) by less than _FLAT
# of the band's smaller step: a brushed face's lines parallel to a side (15 DN rms, 4 px
# apart) made a second step 4 px inside a dark holder's side, and the side was moved onto
# it (3.7-3.9 px); such a face varies by 0.29 of that step, the face behind the synthetic
# hard shadows by 0.001-0.003. The blur's share keeps the inner step's own tail out: read
# from 1.5 px in, a soft band's face (blur 2.2 px: a third of the step still to come
# there) read as rough, and the side stayed between the steps, 1.0-1.3 px off
_DEEP, _DEEP_FROM, _DEEP_BLURS, _FLAT = 12.0, 1.5, 2.5, 0.05
_DEEP_BINS = np.arange(-REACH - _DEEP - _DEEP_FROM - _DEEP_BLURS * _MAX_BLUR, 0.0, 0.5)


def _rough_face(deep: SideProfiles, k: int, inner: float, step: float, blur: float
                ) -> bool:
    """Whether the face inside side ``k``'s inner step (blurred ``blur`` px) varies as much
    as a band: texture (:data:`_DEEP`, :data:`_FLAT`), whose inner step is one more of its
    lines. ``deep``: the sides' profiles read over :data:`_DEEP_BINS`
    (:func:`side_profiles`)."""
    x, m, cnt = deep.x, deep.m, deep.cnt
    start = inner - _DEEP_FROM - _DEEP_BLURS * blur
    use = (cnt[k] > 0) & (x[k] >= start - _DEEP) & (x[k] <= start)
    if use.sum() < 8:
        return False
    wts = cnt[k, use]
    fit = np.polyval(np.polyfit(x[k, use], m[k, use], 1, w=np.sqrt(wts)), x[k, use])
    rms = math.sqrt(float(np.sum(wts * (m[k, use] - fit) ** 2) / np.sum(wts)))
    return rms > _FLAT * step


# a band along a side may be the holder's own face round a sample plate whose edge lies a
# few px inside that side and farther than this check reaches inside the opposite one (2
# and 12 px: the side was moved onto the plate's edge, 2.8 px off). Then the face just
# inside the opposite side (_RIM_IN px in) is at the band's level, where beside a hard
# shadow it is the face's beyond the band's inner step (a band is the floor in shade)
_RIM_IN = (-6.0, -3.0)
_RIM_NEAR = 0.25  # of the two levels' difference
_RIM_DEEP = 4.5  # px beyond the inner step: where the face's level is taken


def band_levels(a: float, g: float, inner: float, outer: float, c_inner: float
                ) -> tuple[float, float]:
    """The levels (DN) between two steps at ``inner`` < ``outer`` and beyond the inner one
    of a profile a + g x + steps (:func:`steps_model`; ``c_inner`` the inner step's
    height, going outward)."""
    return a + g * (inner + outer) / 2 + c_inner, a + g * (inner - _RIM_DEEP)


def plate_rim(prof: SideProfiles, k: int, levels: tuple[float, float]) -> bool:
    """Whether a band along side ``k`` (``levels``: its own and the face's beyond it, DN)
    is the holder's face round a plate: the level just inside the opposite side is the
    band's (within ``_RIM_NEAR`` of the levels' difference), not the face's."""
    o = (k + 2) % 4
    use = (prof.cnt[o] > 0) & (prof.x[o] >= _RIM_IN[0]) & (prof.x[o] <= _RIM_IN[1])
    if not use.any():
        return False
    near = float(np.average(prof.m[o, use], weights=prof.cnt[o, use]))
    band, beyond = levels
    return abs(near - band) <= _RIM_NEAR * abs(beyond - band)


def _softer_outer(p: np.ndarray, cost: float, x: np.ndarray, m: np.ndarray,
                  cnt: np.ndarray, foot: np.ndarray, within: float
                  ) -> tuple[float, float] | None:
    """A band's inner step placed again with the outer step's own blur, from the two
    steps of one blur ``p`` (residual sum ``cost``) on one side's profile (``x``, ``m``,
    ``cnt``, ``foot``; ``within``: the pixels' scatter within the bins): the inner step
    and its standard error, or None where the outer step is not the softer or the fit is
    no better. A cast shadow's outer edge is its penumbra, the camera's blur and the
    shadow's own, softer than the holder's edge; one blur for both, a soft band's inner
    step (blur 2.2 px, the shadow's 2 px) was read 0.3-0.5 px outside the holder's
    edge."""
    a, g, s, c1, d1, c2, d2 = (float(v) for v in p)
    if d1 > d2:
        c1, d1, c2, d2 = c2, d2, c1, d1
    q, cq, A = fit_steps(np.array([[a, g, s, c1, d1, c2, d2, s]]), x[None], m[None],
                         cnt[None], foot[None], 2, own_blur=True)
    _a, _g, s_in, c_in, d_in, c_out, d_out, s_out = (float(v) for v in q[0])
    if not (float(cq[0]) < cost and c_in * c_out > 0 and s_out >= s_in
            and d_out - d_in >= _MIN_SEP):
        return None
    sigma = standard_error(A[0], 4, float(cq[0]), within, float(cnt.sum()), 8)
    return None if math.isinf(sigma) else (d_in, sigma)


# a soft band (docs/vision.md, "A soft band"): a side fitted _SOFT_WIDER px or more softer
# than the camera's blur (the other sides' median) is fitted with two steps, the inner one
# at that blur and the outer one at least as soft, from the _SOFT_SEPS x _SOFT_SPLITS
# starts; the band is taken where they fit _SOFT_GAIN times better than one step, each the
# same way and together the side's whole step, the smaller at least _MIN_SHARE_CLEAR of
# both, _MIN_SEP px or more apart, the inner one _MIN_OFF_SOFT to _SOFT_MAX_IN px inside
# the found side
_SOFT_WIDER = 0.05
_SOFT_GAIN = 2.0
_SOFT_MISFIT = 1.5  # ... tried only where one step misfits beyond the noise this much
_SOFT_SEPS, _SOFT_SPLITS = (1.5, 3.0), (0.0, 0.5)
_MIN_OFF_SOFT, _SOFT_MAX_IN = 0.05, 1.5


def _soft_bands(prof: SideProfiles, cnt: np.ndarray, P1: np.ndarray, cost1: np.ndarray,
                usable: np.ndarray, within: np.ndarray) -> list[Band]:
    """The sides beside a soft band: a cast shadow 1-3 px beyond a side, its edge softer
    than the holder's (the camera's blur and the lamp's penumbra), too near to resolve as
    two steps of one blur (:func:`side_bands`). One lens blurs all four sides of the flat
    face alike, so the other sides tell the holder's edge's blur: held at that, the inner
    step is the edge and the outer one the band's (corpus frames whose side was 0.4-0.5
    px outside the holder's edge: 0.1 px). ``cnt``: ``prof``'s pixel counts, clipped
    bins left out; ``P1``, ``cost1``: the one-step fits of ``prof`` with them;
    ``usable``: sides with enough pixels; ``within``: the pixels' scatter within the bins.
    A band along opposite sides, or at the level of the face just inside the opposite
    side, is left alone (see :func:`side_bands`)."""
    live = np.flatnonzero(usable)
    if live.size < 3:
        return []
    blur = P1[:, 2]
    cam = np.array([float(np.median(blur[live[live != k]])) for k in range(4)])
    x, foot = prof.x, prof.foot
    # only a side one step misfits beyond its noise can fit two steps _SOFT_GAIN times
    # better: its residual sum over what the pixels' scatter within the bins gives
    # (a fit costs about 5 ms a side)
    var, bins = pixel_variance(cnt, within)
    noise = var * np.maximum(bins - 8, 1)
    todo = np.array([k for k in live if blur[k] >= cam[k] + _SOFT_WIDER
                     and cost1[k] >= _SOFT_MISFIT * noise[k]], int)
    if todo.size == 0:
        return []
    starts = [(sep, split) for sep in _SOFT_SEPS for split in _SOFT_SPLITS]
    P2 = np.array([[a, g, cam[k], 0.7 * cc, d - split * sep, 0.3 * cc,
                    d - split * sep + sep, 1.3 * cam[k]]
                   for k in todo for (a, g, _s, cc, d) in P1[k:k + 1]
                   for sep, split in starts])
    P2, cost2, A2 = _best_of_starts(P2, todo, len(starts), prof, cnt, own_blur=True,
                                    held_blur=cam)
    bands = []
    for b, k in enumerate(todo):
        a, g, _s, c1, d1, c2, d2, _s2 = (float(v) for v in P2[b])
        c0 = float(P1[k, 3])
        share = min(abs(c1), abs(c2)) / max(abs(c1) + abs(c2), 1e-9)
        gain = float(cost1[k] / max(cost2[b], 1e-12))
        if not (gain >= _SOFT_GAIN and c1 * c2 > 0 and c0 != 0
                and abs((c1 + c2) / c0 - 1.0) <= _WHOLE and share >= _MIN_SHARE_CLEAR
                and d2 - d1 >= _MIN_SEP and -_SOFT_MAX_IN <= d1 <= -_MIN_OFF_SOFT
                and _resolvable(x[k], _one_step_residuals(prof, P1, k), cnt[k], d1, d2,
                                foot[k], c0)):
            continue
        # the inner step's standard error, as a hard band's (the blur held: the other 7
        # parameters' normal matrix)
        free = [0, 1, 3, 4, 5, 6, 7]
        sigma = standard_error(A2[b][np.ix_(free, free)], 3, float(cost2[b]),
                               float(within[k]), float(cnt[k].sum()), 7)
        bands.append(Band(int(k), d1, d2, share, gain, sigma,
                          band_levels(a, g, d1, d2, c1)))
    if any((bd.side + 2) % 4 in {o.side for o in bands} for bd in bands):
        return []
    if any(plate_rim(prof, bd.side, bd.levels) for bd in bands):
        return []
    return bands


def _soft_or_tails(prof: SideProfiles, cnt: np.ndarray, P1: np.ndarray, cost1: np.ndarray,
                   usable: np.ndarray, within: np.ndarray) -> list[Band]:
    """The sides beside a soft band (:func:`_soft_bands`, arguments as there) and the
    sides at a cast shadow's soft edge (:func:`alignd.vision.holder_tails.shadow_tails`:
    their edge lies inside or outside the found side; no band level, no share), a side
    that is both taken as whichever gains more over one step."""
    bands = {b.side: b for b in _soft_bands(prof, cnt, P1, cost1, usable, within)}
    # (a soft band's outer step a pixel or so beyond the side is a shadow's soft edge as
    # well: a dark holder whose shadow's edge lies 0.8 px beyond a short side at 3 deg,
    # drawn as a camera forms it, was moved 0.21 px in as beside a soft band, and its
    # other short side stayed 0.05 px off; the tails read both within 0.02 px)
    for t in shadow_tails(prof.x, prof.m, cnt, prof.foot, P1, cost1, within, usable):
        if t.side not in bands or t.gain > bands[t.side].gain:
            bands[t.side] = _as_band(t)
    return [bands[k] for k in sorted(bands)]


def _as_band(t: Tail) -> Band:
    """A side at a shadow's soft edge as :func:`side_bands` returns it."""
    return Band(t.side, t.edge_px, t.edge_px + t.shadow_px, 0.0, t.gain, t.sigma_px,
                (math.nan, math.nan), tail=True)


_SEPS = (1.5, 3.0, 5.0)  # the two-step fit's starts: the steps this far apart, ...
_SPLITS = (0.0, 0.5, 1.0)  # ... the one step's place at the inner, middle, outer one


def side_bands(gray: np.ndarray, corners: np.ndarray, lens: Lens | None = None,
               profiles: SideProfiles | None = None) -> list[Band]:
    """The sides of the quadrilateral ``corners`` (4, 2, frame pixels, cyclic order; in a
    frame with ``lens`` distortion, measured in the ideal image) found between two steps
    the same way or on the outer one, outside the inner one (module docstring); [] when
    none is, or when the side opposite one that is steps twice the same way as well,
    wherever its found side lies (a band all round lies inside the face, not beside it),
    or the face just inside it is at the band's level (:func:`plate_rim`). Where none is
    found, the sides beside a soft band and those at a shadow's soft edge
    (:func:`_soft_or_tails`).
    ``profiles``: these sides' profiles already read (:func:`read_sides`, a reach of
    ``REACH`` or more)."""
    c = np.asarray(corners, float)
    ci = c if lens is None else lens.undistort(c)
    prof = (profiles if profiles is not None else read_sides(gray, c, lens, REACH)
            ).within_reach(REACH)
    x, m, foot = prof.x, prof.m, prof.foot
    # bins with clipped pixels are left out: a step blurred and clipped at full scale
    # flattens abruptly, which two steps fit far better than one (a white sample strip
    # clipped beside a holder's side read as a band, and the side moved 0.95 px in)
    cnt = np.where(prof.clipped > 0, 0.0, prof.cnt)
    within = np.where(prof.clipped > 0, 0.0, prof.within).sum(axis=1)
    usable = cnt.sum(axis=1) >= 200
    if not usable.any():
        return []
    # the bins weigh as many pixels as they hold: a least-squares fit to the pixels
    lo = np.array([np.average(m[k, :20], weights=cnt[k, :20] + 1e-9) for k in range(4)])
    hi = np.array([np.average(m[k, -20:], weights=cnt[k, -20:] + 1e-9) for k in range(4)])
    c0 = hi - lo
    held = cnt > 0
    mid = np.where(held, (m - lo[:, None]) / np.where(c0 == 0, 1.0, c0)[:, None], 0.0)
    d0 = np.array([x[k, held[k]][np.argmin(np.abs(mid[k, held[k]] - 0.5))] if held[k].any()
                   else 0.0 for k in range(4)])  # where the profile is half-way
    P1 = np.column_stack([lo, np.zeros(4), np.full(4, 0.7), c0, d0])
    P1, cost1, _ = fit_steps(P1, x, m, cnt, foot, 1)
    # one step fits a side between two steps worse than the others: only sides whose
    # misfit (per pixel, over the step squared) is _WORSE times the best side's are
    # fitted with two (a band all round is left alone anyway; that fit costs 2-3 ms a
    # side)
    misfit = cost1 / np.maximum(cnt.sum(axis=1) * P1[:, 3] ** 2, 1e-12)
    usable_any = usable.copy()
    usable &= misfit >= _WORSE * float(np.min(misfit[usable]))
    deep: SideProfiles | None = None

    def examine(todo: np.ndarray) -> tuple[list[Band], set[int]]:
        """The sides ``todo`` fitted with two steps: the bands beside them, and every
        side that steps twice the same way, wherever its found side lies."""
        nonlocal deep
        starts = [(sep, split) for sep in _SEPS for split in _SPLITS]
        P2 = np.array([[a, 0.0, 0.6 * s1, cc / 2, d - split * sep, cc / 2,
                        d - split * sep + sep]
                       for (a, _g, s1, cc, d) in P1[todo] for sep, split in starts])
        P2, cost2, A2 = _best_of_starts(P2, todo, len(starts), prof, cnt)
        bands, twice = [], set()
        for b, k in enumerate(todo):
            _a, _g, s2, c1, d1, c2, d2 = P2[b]
            inner, outer = (d1, d2) if d1 <= d2 else (d2, d1)
            share = min(abs(c1), abs(c2)) / max(abs(c1) + abs(c2), 1e-9)
            gain = float(cost1[k] / max(cost2[b], 1e-12))
            # two steps that make the side's whole step between them (not two large ones
            # cancelling each other over a sloping floor), each as sharp as one edge
            whole = abs((c1 + c2) / c0[k] - 1.0) <= _WHOLE if c0[k] != 0 else False
            if not (c1 * c2 > 0 and whole and s2 <= P1[k, 2] + _SHARPER
                    and (share >= _MIN_SHARE
                         or (share >= _MIN_SHARE_CLEAR and gain >= _CLEAR_GAIN))
                    and gain >= _MIN_GAIN
                    and outer - inner >= max(_MIN_SEP, _RESOLVED * s2)
                    and _resolvable(x[k], _one_step_residuals(prof, P1, k), cnt[k], inner,
                                    outer, foot[k], float(c0[k]))):
                continue
            # (or one edge through a lens out of focus)
            if one_disc_edge(x[k], m[k], cnt[k], foot[k], (c1, d1, c2, d2), float(cost2[b])):
                continue
            twice.add(int(k))
            # the found side between the steps, or on the outer one with the inner one near
            between = outer >= _MIN_IN or (abs(outer) <= _ON_OUTER and inner >= -_MAX_IN)
            if not (inner <= -_MIN_OFF and between):
                continue
            if deep is None:  # read once, for the first side that gets this far
                deep = side_profiles(gray, ci, lens, _DEEP_BINS)
            if _rough_face(deep, int(k), inner, min(abs(c1), abs(c2)), float(s2)):
                continue
            # inner's standard error: the normal matrix scaled by the pixels' scatter
            # about the fit (within the bins and the bins' about the model)
            sigma = standard_error(A2[b], 4 if d1 <= d2 else 6, float(cost2[b]),
                                   float(within[k]), float(cnt[k].sum()), 7)
            levels = band_levels(_a, _g, inner, outer, c1 if d1 <= d2 else c2)
            softer = _softer_outer(P2[b], float(cost2[b]), x[k], m[k], cnt[k], foot[k],
                                   float(within[k]))
            if softer is not None:
                inner, sigma = softer
            bands.append(Band(int(k), float(inner), float(outer), float(share), gain,
                              sigma, levels))
        return bands, twice

    if not usable.any():
        return _soft_or_tails(prof, cnt, P1, cost1, usable_any, within)
    bands, twice = examine(np.flatnonzero(usable))
    if not bands:
        return _soft_or_tails(prof, cnt, P1, cost1, usable_any, within)
    # a band along opposite sides lies inside the face (a plate, a chamfer all round): left
    # alone whether or not the found side passed as beside it there too (a dark plate 4 px
    # inside both long sides: the found sides 0.45 and 0.53 px outside the outer steps, one
    # within _ON_OUTER and one not, and the one moved 4.45 px in). The opposite side is
    # fitted with two steps here if the screen above left it out (a plate all round
    # misfits every side alike: one 2 px inside was cut off along one side, 2 px)
    facing = np.array(sorted({(b.side + 2) % 4 for b in bands}), int)
    facing = facing[usable_any[facing] & ~usable[facing]] if facing.size else facing
    if facing.size:
        twice |= examine(facing)[1]
    if any((b.side + 2) % 4 in twice for b in bands):
        return []
    # nor is a band at the level just inside the opposite side (a plate's rim, above)
    if any(plate_rim(prof, b.side, b.levels) for b in bands):
        return []
    return bands
