"""A second step a few pixels from a found side, and an image without it.

A sample plate on the holder's face with its edge 2-8 px inside a side, or a light holder's
hard shadow a few px outside it, puts a second step in that side's edge windows (+-5 px,
+-9 px for soft edges). Neither edge model has one: the area method reads its levels from
the window's tails and their slope, so a step's tail there tilts the level it subtracts,
and a plate 3-6 px in moved sides by 0.2-1.4 px (docs/vision.md, "A second step beside a
side").

Here each side's pixels within 14 px of it are binned by their distance to it (as in
:mod:`alignd.vision.holder_bands`) and fitted by one blurred step. A side that step misfits
(by four times its pixels' scatter and 0.8 % of the step) is fitted by two: a grid of both
places and two blurs for the start, Levenberg-Marquardt with one blur, then the far step
with its own. It has a :class:`Neighbour` where two steps fit far better, the found side
on one of them, the other resolved from it, as sharp as an edge (a soft shadow's penumbra
is the profile fit's to model), a fair share of the whole and on flat ground beyond, and
where one edge defocused by a disc (a lens out of focus) does not fit about as well: two
Gaussian steps a disc's radius apart are the shape of such an edge.
:func:`without_neighbours` subtracts each neighbour's modelled step from a copy of the
image along its side's middle, so that the sides can be measured again on one step each.
The side's own step is never changed: only the far one is removed, and an error in its
model enters the windows through its tail alone.

Steps of the same sign with the found side between them or on the outer one are a band
beside the holder, :mod:`alignd.vision.holder_bands`, which runs first and decides which
step is the holder's edge.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from alignd.vision.holder_bands import (
    SideProfiles,
    band_levels,
    fit_steps,
    one_disc_edge,
    plate_rim,
    read_sides,
    steps_model,
)
from alignd.vision.holder_steps import side_frame
from alignd.vision.lens import Lens
from alignd.vision.profile_fit import step_response

__all__ = ["REACH", "Neighbour", "neighbour_steps", "without_neighbours"]

REACH = 14.0  # px either side of the found side: the profiles :func:`neighbour_steps` reads
# the decision: two steps fit _MIN_GAIN times better than one, the found side within _ON
# px of one of them, the other at least _MIN_SEP px and _RESOLVED blurs from it (a
# plateau between them) and within _FAR px of the side (beyond, no window reaches it), its
# height at least _MIN_SHARE of the side's step, and the profile beyond it within _FLAT of
# that height of the model (rms) over at least _BEYOND px (a texture line is not a step).
# _ON: a plate 4 px inside a side pulls the side found first by up to 1.9 px (through a
# distorting lens, off its centre; 1.5 px missed it and left the holder 1.9 px off)
_MIN_GAIN = 4.0
_ON = 2.5
_MIN_SEP = 1.5
_RESOLVED = 1.8
_FAR = 13.0
_MIN_SHARE = 0.08
_MISFIT = 0.008  # the screen: drawn clean sides 0.1-0.4 %, our renderer's 0.7 %, plates 2 px in
# 0.85 % (a plate 2 px in less than that is left as it was)
_FLAT = 0.1
_BEYOND = 1.5
# the far step at most _SHARP times the side's blur and _SHARP_PX more: a plate's edge or a
# hard shadow, not a soft shadow's penumbra (the profile fit's tails model those)
_SHARP, _SHARP_PX = 1.5, 0.3
_ITERATIONS = 15  # Levenberg-Marquardt steps of the one-step and one-blur fits
_BLURS = (0.7, 1.4)  # the grid's blurs (px)
_SOFT = 3.0  # a far step that fits better this many times softer is a penumbra
_GRID_GAIN = 1.1  # the grid's start must fit this many times better than one step
_D1 = np.arange(-_ON, _ON + 0.01, 0.5)  # the side's own step (px from the found side)
_D2 = np.arange(-REACH + 1.0, REACH - 0.99, 0.5)  # the other one's
_TABLE_T = np.arange(-2.0 * REACH - 2.0, 2.0 * REACH + 2.01, 0.02)  # see _grid_start


@dataclass(frozen=True)
class Neighbour:
    """Side ``side`` (corner ``side`` to ``side + 1``) has a second step ``at_px`` from its
    own (+ outward) of height ``step`` (DN, the level change going outward) and blur
    ``blur_px``; its own step, of height ``own_step``, is ``own_px`` from the found
    side."""

    side: int
    at_px: float
    own_px: float
    step: float
    blur_px: float
    gain: float
    own_step: float  # the side's own step (DN, going outward)


def _grid_start(x: np.ndarray, m: np.ndarray, w: np.ndarray, foot: np.ndarray
                ) -> tuple[np.ndarray, float] | None:
    """The best two-step start for one profile over a grid of both places and two blurs
    (the levels, slope and heights by linear least squares at each): (a, g, s, c1, d1,
    c2, d2) and its weighted residual sum of squares. A start, not a fit: the blur's grid
    is coarse, Levenberg-Marquardt follows.
    Each pair's normal equations are assembled from the basis' inner products (a few
    small matrix products for all pairs at once)."""
    best, out = math.inf, None
    B0 = np.stack([np.ones_like(x), x])  # the level and its slope
    for s in _BLURS:
        # the step's response tabulated once (0.02 px apart, linear interpolation errs by
        # under 1e-4 of the step), read at every place of the grid
        table = step_response(_TABLE_T, s, foot[0], foot[1])[0]
        S1 = np.interp(x[None, :] - _D1[:, None], _TABLE_T, table)
        S2 = np.interp(x[None, :] - _D2[:, None], _TABLE_T, table)
        i, j = np.nonzero(np.abs(_D2[None, :] - _D1[:, None]) >= max(_MIN_SEP, _RESOLVED * s))
        n = i.size
        A = np.empty((n, 4, 4))
        A[:, :2, :2] = (B0 * w) @ B0.T
        A[:, :2, 2] = ((B0 * w) @ S1.T).T[i]
        A[:, :2, 3] = ((B0 * w) @ S2.T).T[j]
        A[:, 2, 2] = ((S1 * w) * S1).sum(axis=1)[i]
        A[:, 3, 3] = ((S2 * w) * S2).sum(axis=1)[j]
        A[:, 2, 3] = ((S1 * w) @ S2.T)[i, j]
        A[:, 2:, :2] = A[:, :2, 2:].transpose(0, 2, 1)
        A[:, 3, 2] = A[:, 2, 3]
        rhs = np.broadcast_to(np.concatenate([(B0 * w) @ m, np.zeros(2)]), (n, 4)).copy()
        rhs[:, 2] = ((S1 * w) @ m)[i]
        rhs[:, 3] = ((S2 * w) @ m)[j]
        try:
            beta = np.linalg.solve(A + 1e-9 * np.eye(4), rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            continue
        # the residual sum of squares: m'Wm - beta'rhs at the least-squares solution
        cost = float((w * m) @ m) - np.einsum("nj,nj->n", beta, rhs)
        b = int(np.argmin(cost))
        if cost[b] < best:
            best = float(cost[b])
            a, g, c1, c2 = beta[b]
            out = np.array([a, g, s, c1, _D1[i[b]], c2, _D2[j[b]]])
    return None if out is None else (out, best)


def neighbour_steps(gray: np.ndarray, corners: np.ndarray, lens: Lens | None = None,
                    profiles: SideProfiles | None = None) -> list[Neighbour]:
    """The sides of the quadrilateral ``corners`` (4, 2, frame pixels, cyclic order) with
    a second step near them (module docstring); [] when none has. ``profiles``: these
    sides' profiles already read (:func:`alignd.vision.holder_bands.read_sides`, a reach
    of :data:`REACH` or more)."""
    prof = (profiles if profiles is not None else read_sides(gray, corners, lens, REACH)
            ).within_reach(REACH)
    x, m, cnt, foot = prof.x, prof.m, prof.cnt, prof.foot
    within = prof.within.sum(axis=1)
    held = cnt > 0
    out = held & (x > 2.0) & (x < 4.0)  # one step, started from the levels 2-4 px either
    inn = held & (x < -2.0) & (x > -4.0)  # side of the found side
    todo = np.flatnonzero((cnt.sum(axis=1) >= 200) & out.any(axis=1) & inn.any(axis=1))
    if todo.size == 0:
        return []
    lo = np.array([np.average(m[k, inn[k]], weights=cnt[k, inn[k]]) for k in todo])
    hi = np.array([np.average(m[k, out[k]], weights=cnt[k, out[k]]) for k in todo])
    P1 = np.column_stack([lo, np.zeros(todo.size), np.full(todo.size, 0.8), hi - lo,
                          np.zeros(todo.size)])
    P1, cost1, _ = fit_steps(P1, x[todo], m[todo], cnt[todo], foot[todo], 1,
                             iterations=_ITERATIONS, reach=REACH)
    # only a side one step misfits by _MIN_GAIN times its pixels' scatter within the bins
    # can gain that much from two, and only one it misfits by _MISFIT of its step (rms)
    # has a step beside it worth the fit (clean sides: 0.1-0.4 %; plates 3-12 px in,
    # 2-11 %): most sides fit one
    n_px = cnt[todo].sum(axis=1)
    nbins = held[todo].sum(axis=1)
    var = within[todo] / np.maximum(n_px - nbins, 1.0)
    keep = (cost1 >= _MIN_GAIN * nbins * np.maximum(var, 1e-6)) & (
        cost1 >= (_MISFIT * P1[:, 3]) ** 2 * n_px)
    todo, cost1 = todo[keep], cost1[keep]
    # the grid's start, unless it gains less than _GRID_GAIN on one step (plates 3-6 px
    # in: 1.7 and more; a plate 2 px in with the side found between its steps, where the
    # grid's places are too coarse: 1.1-1.3, and the fit below gains 15) or its far step
    # fits better _SOFT times softer (a penumbra, which the profile fit's tails model):
    # the fits below cost 3-8 ms
    grids = [_grid_start(x[k], m[k], cnt[k], foot[k]) for k in todo]
    starts = [gr[0] if gr is not None and c1 >= _GRID_GAIN * gr[1]
              and not _soft_far(x[k], m[k], cnt[k], foot[k], gr[0]) else None
              for k, gr, c1 in zip(todo, grids, cost1, strict=True)]
    have = np.array([st is not None for st in starts], bool)
    if not have.any():
        return []
    todo, cost1 = todo[have], cost1[have]
    fits = _two_steps(x[todo], m[todo], cnt[todo], foot[todo],
                      np.array([st for st in starts if st is not None]), cost1)
    found, rims = [], set()
    for k, c1cost, fit in zip(todo, cost1, fits, strict=True):
        if fit is None:
            continue
        xk, mk, wk = x[k], m[k], cnt[k]
        a, g, s1, c1, d1, c2, d2, s2 = fit[:8]
        gain = float(c1cost / max(fit[8], 1e-12))
        if not (gain >= _MIN_GAIN and abs(d1) <= _ON and abs(d2) <= _FAR
                and abs(d2 - d1) >= max(_MIN_SEP, _RESOLVED * max(s1, s2))
                and abs(c2) >= _MIN_SHARE * abs(c1) and s2 <= _SHARP * s1 + _SHARP_PX):
            continue
        # beyond the far step, the profile must be the model's plateau (not a texture)
        far = (wk > 0) & ((xk - d2) * np.sign(d2 - d1) >= _BEYOND * max(s2, 1.0))
        if far.sum() < 5:
            continue
        f = steps_model(fit[None, :8], xk[None, far], foot[None, k], 2, own_blur=True)[0][0]
        rms = math.sqrt(float(np.sum(wk[far] * (mk[far] - f) ** 2) / np.sum(wk[far])))
        if rms > _FLAT * abs(c2):
            continue
        if one_disc_edge(xk, mk, wk, foot[k], (c1, d1, c2, d2), float(fit[8])):
            continue
        found.append(Neighbour(int(k), float(d2 - d1), float(d1), float(c2), float(s2), gain,
                               float(c1)))
        if d2 < d1 and plate_rim(prof, int(k), band_levels(a, g, d2, d1, c2)):
            rims.add(int(k))
    # a far step inside the side stepping its way is a band: the holder's edge is the inner
    # step (:mod:`alignd.vision.holder_bands`, taken on trust), unless the opposite side has
    # one too (a band all round lies inside the face: a plate) or the face just inside the
    # opposite side is at the band's level (a plate's rim, :func:`plate_rim`); removing it
    # would leave the side on the outer one (a hard shadow's band 2-3 px wide: 2.1-3.1 px
    # off)
    banded = {n.side for n in found if n.at_px < 0 and n.step * n.own_step > 0}
    found = [n for n in found
             if n.side not in banded or (n.side + 2) % 4 in banded or n.side in rims]
    return found


# where _soft_far places the side's own step: within half the grid's spacing of the start's
_NEAR_D1 = np.arange(-0.25, 0.2501, 0.05)


def _soft_far(x: np.ndarray, m: np.ndarray, w: np.ndarray, foot: np.ndarray,
              start: np.ndarray) -> bool:
    """Whether the far step of a two-step ``start`` (:func:`_grid_start`) fits the profile
    better blurred _SOFT times more than the side's own (the far step's place held, the
    side's own placed best within half the grid's spacing of the start's, the levels,
    slope and heights by linear least squares). The grid places the side's own step to
    0.5 px: a side found 0.2 px off it (a plate 4 px inside, its sides measured with a
    penumbra fit that did not take the plate's edge) misfits there by ten times its
    best, and a far step three times softer spreads to cover that."""
    _a, _g, s, _c1, d1, _c2, d2 = start
    S1 = step_response(x[None, :] - (d1 + _NEAR_D1)[:, None], s, foot[0], foot[1])[0]
    cost = []
    for s2 in (s, _SOFT * s):
        S2 = np.broadcast_to(step_response(x - d2, s2, foot[0], foot[1])[0], S1.shape)
        X = np.stack([np.ones_like(S1), np.broadcast_to(x, S1.shape), S1, S2], axis=1)
        # each place's weighted normal equations (places, 4, 4), solved together
        Xw = X * w
        beta = np.linalg.solve(Xw @ X.transpose(0, 2, 1) + 1e-9 * np.eye(4),
                               (Xw @ m)[..., None])[..., 0]
        r = m - np.einsum("pk,pkn->pn", beta, X)
        cost.append(float(np.min((r * r) @ w)))
    return cost[1] < cost[0]


def _two_steps(x: np.ndarray, m: np.ndarray, w: np.ndarray, foot: np.ndarray,
               starts: np.ndarray, cost1: np.ndarray) -> list[np.ndarray | None]:
    """Two steps, the far one with its own blur (a penumbra is wider than an edge), fitted
    to each profile (rows) from its start (the grid's, one blur): (a, g, s1, c1, d1, c2,
    d2, s2, cost) with step 1 the one nearer the found side, or None where two steps of
    one blur fit less than half ``_MIN_GAIN`` times better than one (``cost1``: their own
    blurs then gain too little as well, or the far step is softer than an edge) or the
    steps swap places. All profiles in one batch: a fit costs what one profile's does."""
    # one blur first: from the grid's start, the far step's own blur went astray
    P, cost, _ = fit_steps(starts, x, m, w, foot, 2, iterations=_ITERATIONS, reach=REACH)
    ok = cost1 >= 0.5 * _MIN_GAIN * cost
    out: list[np.ndarray | None] = [None] * len(P)
    if not ok.any():
        return out
    one = P[ok]
    swap = np.abs(one[:, 6]) < np.abs(one[:, 4])  # the side's own step first
    one[swap] = one[swap][:, [0, 1, 2, 5, 6, 3, 4]]
    P2, cost2, _ = fit_steps(np.column_stack([one, one[:, 2]]), x[ok], m[ok], w[ok],
                             foot[ok], 2, iterations=_ITERATIONS, reach=REACH, own_blur=True)
    for i, p, c in zip(np.flatnonzero(ok), P2, cost2, strict=True):
        if abs(p[6]) >= abs(p[4]):
            out[i] = np.append(p, c)
    return out


def without_neighbours(gray: np.ndarray, corners: np.ndarray, steps: list[Neighbour],
                       lens: Lens | None = None, ends_px: float = 10.0) -> np.ndarray:
    """A float32 copy of ``gray`` with each neighbour's step subtracted beyond it, over
    its side's length but ``ends_px`` at either end (the corners, where the sides' own
    windows stop and a neighbouring side's begin) and within the reach of the side."""
    out = np.asarray(gray, np.float32).copy()
    c = np.asarray(corners, float)
    ci = c if lens is None else lens.undistort(c)
    edge, length, n = side_frame(ci)
    u = edge / np.maximum(length, 1e-9)[:, None]
    h, w = out.shape
    for nb in steps:
        k = nb.side
        box = np.concatenate([ci[k] + o * n[k] for o in (-REACH - 2, REACH + 2)]
                             + [ci[(k + 1) % 4] + o * n[k] for o in (-REACH - 2, REACH + 2)])
        box = box.reshape(-1, 2) if lens is None else lens.distort(box.reshape(-1, 2))
        x0, y0 = np.maximum(np.floor(box.min(axis=0)).astype(int) - 2, 0)
        x1, y1 = np.minimum(np.ceil(box.max(axis=0)).astype(int) + 2, (w - 1, h - 1))
        if x1 < x0 or y1 < y0:
            continue
        yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
        px = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
        pi = px if lens is None else lens.undistort(px)
        d = (pi - ci[k]) @ n[k]
        along = (pi - ci[k]) @ u[k]
        sel = (np.abs(d) <= REACH) & (along >= ends_px) & (along <= length[k] - ends_px)
        at = nb.own_px + nb.at_px
        foot = np.sort(np.abs(n[k]))[::-1]
        S = step_response(d[sel] - at, nb.blur_px, foot[0], foot[1])[0]
        # the step rises by nb.step going outward (+d): beyond an inner step (d < at) the
        # level is nb.step lower than the side's plateau, beyond an outer one higher
        fix = nb.step * (S - (1.0 if nb.at_px < 0 else 0.0))
        out[yy.ravel()[sel], xx.ravel()[sel]] -= fix.astype(np.float32)
    return out
