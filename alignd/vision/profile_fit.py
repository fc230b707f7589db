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
the position most of its precision. The fit starts from the area method's crossing (good to
a tenth of a pixel), so a few Gauss-Newton iterations suffice.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

from alignd.vision.edges import EdgePoints, _adaptive_slope

__all__ = ["fit_crossings", "step_response"]

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
_TAILS = 3
_MISFIT = 2.5  # columns fitted worse than this many times the edge's median are dropped


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
    shape = np.broadcast_shapes(np.shape(d), np.shape(s), np.shape(wa), np.shape(wb))
    S, S1, S2 = np.zeros(shape), np.zeros(shape), np.zeros(shape)
    for off, sign in ((p, 1.0), (q, -1.0), (-q, -1.0), (-p, 1.0)):
        t = d + off
        z = t / s
        Phi = ndtr(z)
        phi = np.exp(-0.5 * z * z) * _INV_SQRT_2PI
        tsphi = t * s * phi
        if sign > 0:
            S += (t * t + s * s) * Phi + tsphi
            S1 += t * Phi + s * phi
            S2 += Phi
        else:
            S -= (t * t + s * s) * Phi + tsphi
            S1 -= t * Phi + s * phi
            S2 -= Phi
    inv = 1.0 / (wa * wb)
    return S * (0.5 * inv), S1 * inv, S2 * inv


def _windows(gray: np.ndarray, pts: EdgePoints, half_width: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixel windows (N, 2 hw + 1) centred on each crossing: the windows, their centres,
    the crossings relative to the centres and the indices of the crossings kept."""
    h, w = gray.shape
    if pts.vertical:
        t, c = pts.xy[:, 1], pts.xy[:, 0]
        limit = w
    else:
        t, c = pts.xy[:, 0], pts.xy[:, 1]
        limit = h
    ti = np.rint(t).astype(int)
    centre = np.rint(c).astype(int)
    ok = (centre - half_width >= 0) & (centre + half_width < limit)
    ti, centre = ti[ok], centre[ok]
    idx = centre[:, None] + np.arange(-half_width, half_width + 1)[None, :]
    P = (gray[ti[:, None], idx] if pts.vertical else gray[idx, ti[:, None]]).astype(np.float64)
    return P, centre.astype(float), c[ok] - centre, np.flatnonzero(ok)


def _tail_slopes(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Illumination slope on either side of each window, one value per edge except where
    it changes along the edge by more than its noise (a penumbra crossing the edge)."""
    wts = np.arange(_TAILS) - (_TAILS - 1) / 2
    wts = wts / float(wts @ wts)
    return (_adaptive_slope(P[:, :_TAILS] @ wts, 3),
            _adaptive_slope(P[:, -_TAILS:] @ wts, 3))


def _start(P: np.ndarray, x: np.ndarray, b1: np.ndarray, b2: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray]:
    a1 = P[:, :2].mean(axis=1) - b1 * x[:2].mean()
    return a1, P[:, -2:].mean(axis=1) - b2 * x[-2:].mean() - a1


def _fit(P: np.ndarray, x: np.ndarray, u: np.ndarray, s: np.ndarray, nu: np.ndarray,
         wa: np.ndarray, wb: np.ndarray, b1: np.ndarray, b2: np.ndarray, iterations: int
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton fit of every row of P with its own blur; returns u, D and s."""
    n = P.shape[0]
    X = x[None, :]
    sv = s.astype(float).copy()
    a1, D = _start(P, x, b1, b2)
    db = (b2 - b1)[:, None]
    base1 = P - b1[:, None] * X
    nu_c, wa_c, wb_c = nu[:, None], wa[:, None], wb[:, None]
    for _ in range(iterations):
        S, S1, S2 = step_response(nu_c * (X - u[:, None]), sv[:, None], wa_c, wb_c)
        amp = D[:, None] + db * X
        r = base1 - a1[:, None] - amp * S
        cols = [np.ones_like(S), S, -nu_c * amp * S1, amp * sv[:, None] * S2]
        A = np.empty((n, 4, 4))
        b = np.empty((n, 4))
        for i in range(4):
            b[:, i] = np.einsum("nm,nm->n", cols[i], r)
            for j in range(i, 4):
                A[:, i, j] = A[:, j, i] = np.einsum("nm,nm->n", cols[i], cols[j])
        A[:, range(4), range(4)] += 1e-9
        step = np.linalg.solve(A, b[:, :, None])[:, :, 0]
        a1 += step[:, 0]
        D += step[:, 1]
        u = u + np.clip(step[:, 2], -1.0, 1.0)
        sv = np.clip(sv + np.clip(step[:, 3], -0.5, 0.5), 0.15, 6.0)
    return u, D, sv


_H = 0.02  # the step tables' spacing (px of normal distance)


def _fit_tabulated(P: np.ndarray, x: np.ndarray, u: np.ndarray, row: np.ndarray,
                   blur: np.ndarray, geo: np.ndarray, b1: np.ndarray, b2: np.ndarray,
                   iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_fit` with s fixed per edge, S and S' read from one table per edge and the
    3 x 3 normal equations of (a1, D, u) solved in closed form; returns u, D and each
    row's residual RMS (of the last iteration's start)."""
    reach = float(np.max(np.abs(x))) + 2.5
    grid = np.arange(-reach, reach + _H, _H)
    ng = grid.size
    tS, tS1, _ = step_response(grid[None, :], blur[:, None], geo[:, 2:3], geo[:, 3:4])
    tabS, tabS1 = tS.ravel(), tS1.ravel()
    base_idx = (row * ng)[:, None]
    X = x[None, :]
    nu_c = geo[row, 1][:, None]
    a1, D = _start(P, x, b1, b2)
    db = (b2 - b1)[:, None]
    base1 = P - b1[:, None] * X
    m = float(P.shape[1])
    for _ in range(iterations):
        f = np.clip((nu_c * (X - u[:, None]) + reach) / _H, 0.0, ng - 1.001)
        i = f.astype(np.intp)
        f -= i
        i += base_idx
        S = tabS[i] * (1.0 - f) + tabS[i + 1] * f
        S1 = tabS1[i] * (1.0 - f) + tabS1[i + 1] * f
        amp = D[:, None] + db * X
        r = base1 - a1[:, None] - amp * S
        g = -nu_c * amp * S1
        sS, sg = S.sum(axis=1), g.sum(axis=1)
        sSS, sSg, sgg = (S * S).sum(axis=1), (S * g).sum(axis=1), (g * g).sum(axis=1)
        r0, rS, rg = r.sum(axis=1), (r * S).sum(axis=1), (r * g).sum(axis=1)
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
    misfit = np.sqrt(np.maximum((r * r).sum(axis=1) - r0 * r0 / m, 0.0) / m)
    return u, D, misfit


def fit_crossings(gray: np.ndarray, edges: list[EdgePoints], *, half_width: int = 5,
                  iterations: int = 2, max_half_width: int = 10) -> list[EdgePoints]:
    """Refine the area-method crossings of straight edges (one EdgePoints each) by the
    profile fit, all edges in one batch.

    Each edge's Gaussian width is the median of per-column fits of a few of its columns;
    the window is widened (up to ``max_half_width``) to hold the whole transition and the
    tails beyond it, and the ends of each edge trimmed as much. Columns whose fit left the
    window's middle are dropped.
    """
    empty = [EdgePoints(np.empty((0, 2)), np.empty(0), e.vertical) for e in edges]
    use = [i for i, e in enumerate(edges) if e.xy.shape[0] >= 8]
    if not use:
        return empty
    geo = []
    for i in use:
        e = edges[i]
        major = e.xy[:, 1] if e.vertical else e.xy[:, 0]
        minor = e.xy[:, 0] if e.vertical else e.xy[:, 1]
        slope = float(np.polyfit(major, minor, 1)[0])
        nu = 1.0 / math.hypot(1.0, slope)  # |normal . minor axis|
        geo.append((slope, nu, nu, abs(slope) * nu))  # the pixel's footprint: |n_x|, |n_y|
    # the blur: a few columns of each edge, width free
    x = np.arange(-half_width, half_width + 1, dtype=float)
    Ps, u0s, rows, b1s, b2s = [], [], [], [], []
    first = []
    for k, i in enumerate(use):
        P, centre, u0, keep = _windows(gray, edges[i], half_width)
        sub = slice(None, None, max(1, P.shape[0] // 8))
        b1, b2 = _tail_slopes(P) if P.shape[0] else (np.empty(0), np.empty(0))
        first.append((P, centre, u0, keep, b1, b2))
        b1s.append(b1[sub])
        b2s.append(b2[sub])
        Ps.append(P[sub])
        u0s.append(u0[sub])
        rows.append(np.full(len(u0[sub]), k))
    row = np.concatenate(rows)
    g = np.array(geo)
    _, _, s_each = _fit(np.concatenate(Ps), x, np.concatenate(u0s), np.ones(row.size),
                        g[row, 1], g[row, 2], g[row, 3], np.concatenate(b1s),
                        np.concatenate(b2s), 4)
    blur = np.array([float(np.median(s_each[row == k])) if np.any(row == k) else 1.0
                     for k in range(len(use))])
    reach = (3.0 * blur + 0.5 * (g[:, 2] + g[:, 3])) / g[:, 1]  # transition, minor px
    hw = int(min(max(half_width, math.ceil(float(reach.max())) + _TAILS), max_half_width))
    x = np.arange(-hw, hw + 1, dtype=float)
    Ps, u0s, rows, cents, keeps, b1s, b2s = [], [], [], [], [], [], []
    trimmed = []
    for k, i in enumerate(use):
        e = edges[i]
        if hw > half_width:
            # a wider window reaches further toward the corners: trim the ends as much
            major = e.xy[:, 1] if e.vertical else e.xy[:, 0]
            trim = (hw - half_width) * (1.0 + abs(geo[k][0]))
            inner = (major >= major.min() + trim) & (major <= major.max() - trim)
            e = EdgePoints(e.xy[inner], e.contrast[inner], e.vertical)
        trimmed.append(e)
        if hw == half_width:  # the windows of the blur's fit serve
            P, centre, u0, keep, b1, b2 = first[k]
        else:
            P, centre, u0, keep = _windows(gray, e, hw)
            b1, b2 = _tail_slopes(P) if P.shape[0] else (np.empty(0), np.empty(0))
        b1s.append(b1)
        b2s.append(b2)
        Ps.append(P)
        u0s.append(u0)
        cents.append(centre)
        keeps.append(keep)
        rows.append(np.full(len(u0), k))
    row = np.concatenate(rows)
    if row.size == 0:
        return empty
    u, D, misfit = _fit_tabulated(np.concatenate(Ps), x, np.concatenate(u0s), row, blur, g,
                                  np.concatenate(b1s), np.concatenate(b2s), iterations)
    ok = np.isfinite(u) & (np.abs(u) < hw - _TAILS) & (np.abs(D) > 1e-6)
    # a column the model does not fit (a hole, a screw or a shadow's edge in its window)
    for k in range(len(use)):
        sel = row == k
        if np.any(sel):
            ok[sel] &= misfit[sel] <= _MISFIT * float(np.median(misfit[sel])) + 0.5
    pos = np.concatenate(cents) + u
    out = list(empty)
    for k, i in enumerate(use):
        e, sel = trimmed[k], row == k
        keep, good = keeps[k], ok[sel]
        t = (e.xy[:, 1] if e.vertical else e.xy[:, 0])[keep][good]
        p = pos[sel][good]
        xy = np.column_stack([p, t]) if e.vertical else np.column_stack([t, p])
        out[i] = EdgePoints(xy, e.contrast[keep][good], e.vertical)
    return out
