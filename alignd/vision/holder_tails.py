"""A side at a cast shadow's soft edge: the shadow's tail just beyond the holder's edge.

Where the lamp stands nearly above a side, the holder's cast shadow has its edge within a
pixel or two of that side, blurred by the lamp's penumbra (2-10 px). The holder covers
the shadow's part inside; outside, the floor rises from shadowed to lit over a few pixels
right at the side. One blurred step and a slope misread that side by 0.1-0.3 px, and so
do two steps (the shadow's edge may lie under the holder, where its step is not seen):
corpus 9100 #811, a light holder whose shadow's edge lies 0.8 px inside both short sides,
read both 0.27 px inside, at a stated corner sigma of 0.03 px.

The profile across such a side is fitted as the holder's edge (a step at the blur of the
other sides: one lens blurs the flat face's four sides alike) and the shadow's soft step
seen only beyond it: the camera's blur of the product of the edge's coverage and the
shadow's step, a bivariate normal orthant probability (:func:`tail_response`). The fit is
taken for the holder's edge where it explains the profile and one step does not
(:func:`shadow_tails`; docs/vision.md, "A shadow's edge at a side").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, owens_t

from alignd.vision.batch_lm import best_starts, fit_rows, pixel_variance, standard_error
from alignd.vision.profile_fit import step_response

__all__ = ["Tail", "shadow_tails", "tail_response"]

_INV_2PI = 1.0 / (2.0 * math.pi)
# the decision (docs/vision.md, "A shadow's edge at a side"): a side whose one step
# misfits its profile by _TAIL_MISFIT times the pixels' noise or more (reduced chi-square)
# is fitted where one or more other sides fit one step within _TAIL_CLEAN, their blurs
# within _TAIL_BLUR_AGREE px of each other and _TAIL_MIN_CAM px or more; the fit is taken
# where it gains _TAIL_GAIN in chi-square over one step, fits within _TAIL_FITS (reduced),
# its edge steps the side's way, the floor beyond brightens outward (a shadow darkens) and
# no parameter is at its bound (the edge within _TAIL_REACH px of the found side, the
# shadow's edge within _TAIL_UNDER / _TAIL_BEYOND of it, its blur under _TAIL_MAX_SOFT);
# the side is moved where that is _TAIL_SIGNIFICANT standard errors or more
_TAIL_MISFIT = 2.0
_TAIL_CLEAN = 1.5  # ... where the others misfit under this
_TAIL_BLUR_AGREE = 0.1
_TAIL_GAIN = 25.0
_TAIL_FITS = 1.5
_TAIL_REACH = 1.5
_TAIL_STARTS = (-1.0, 1.0, 3.0)  # the shadow's edge this far beyond the holder's, to start
_TAIL_MAX_SOFT = 8.0  # px: the shadow's edge's blur is fitted up to this, ...
_TAIL_SOFTER, _TAIL_MIN_SOFT = 0.5, 1.0  # ... from this more than the camera's, 1 px or more
# on an edge sharper than this (px), a pixel's box or a JPEG coder's ringing beside it
# misfits one step as a shadow's tail does (sharp corpus frames' sides moved 0.01-0.1 px)
_TAIL_MIN_CAM = 0.6
_TAIL_UNDER, _TAIL_BEYOND = 6.0, 3.0  # px: the shadow's edge so far under / beyond the edge
_AT_BOUND = 0.05  # px: a parameter this near its bound is at it
_TAIL_SIGNIFICANT = 1.0  # the edge is moved where it lies this many standard errors off


@dataclass(frozen=True)
class Tail:
    """Side ``side``'s holder edge lies ``edge_px`` from the found side (+ outward; 0
    where the fit's place is within its noise of it), a shadow's soft edge ``shadow_px``
    beyond it (negative: under the holder)."""

    side: int
    edge_px: float
    shadow_px: float
    sigma_px: float  # standard error of edge_px
    gain: float  # the one step's residual sum of squares over this fit's


def _orthant(h: np.ndarray, k: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """P(A < h, B < k) for standard normals A, B of correlation ``rho`` (0 <= rho < 1),
    by Owen's T function."""
    h = np.where(np.abs(h) < 1e-12, 1e-12, h)
    k = np.where(np.abs(k) < 1e-12, 1e-12, k)
    r = np.sqrt(1.0 - rho * rho)
    beta = np.where(h * k < 0, 0.5, 0.0)
    return (0.5 * (ndtr(h) + ndtr(k)) - owens_t(h, (k - rho * h) / (h * r))
            - owens_t(k, (h - rho * k) / (k * r)) - beta)


def tail_response(x: np.ndarray, shadow: np.ndarray, soft: np.ndarray, s: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """At distances ``x`` from an edge (+ beyond it), the camera's blur (``s``, a
    Gaussian's width) of the edge's coverage (0 before it, 1 beyond) times a soft step
    Phi((t - shadow) / soft): P(X > 0, X - soft Z > shadow) for X ~ N(x, s^2) and Z ~ N(0,
    1). Returns it and its derivatives by x, shadow and soft."""
    sw = np.sqrt(s * s + soft * soft)
    rho = s / sw
    r = np.sqrt(1.0 - rho * rho)
    h, k = x / s, (x - shadow) / sw
    T = _orthant(h, k, rho)
    phi_h = np.exp(-0.5 * h * h) * math.sqrt(_INV_2PI)
    phi_k = np.exp(-0.5 * k * k) * math.sqrt(_INV_2PI)
    along_h = phi_h * ndtr((k - rho * h) / r)  # dT/dh
    along_k = phi_k * ndtr((h - rho * k) / r)  # dT/dk
    density = np.exp(-(h * h - 2 * rho * h * k + k * k) / (2 * r * r)) * _INV_2PI / r
    d_x = along_h / s + along_k / sw
    d_shadow = -along_k / sw
    d_soft = -along_k * k * soft / (sw * sw) - density * s * soft / sw ** 3
    return T, d_x, d_shadow, d_soft


def _tails_model(P: np.ndarray, x: np.ndarray, foot: np.ndarray, cam: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """a + g x + c1 S(x - d1) + c2 T(x - d1) for each row of P = (a, g, c1, d1, c2,
    shadow, soft) at the distances ``x`` (rows): S the pixel's response to the edge at
    the blur ``cam`` (:func:`step_response`, footprint ``foot``), T the shadow's tail
    (:func:`tail_response`, the footprint taken as a blur of its variance). Its values
    and Jacobian."""
    a, g, c1, d1, c2, shadow, soft = (P[:, i:i + 1] for i in range(7))
    s = cam[:, None]
    S, S1, _ = step_response(x - d1, s, foot[:, 0:1], foot[:, 1:2])
    s_eff = np.sqrt(s * s + (foot[:, 0:1] ** 2 + foot[:, 1:2] ** 2) / 12.0)
    T, T_x, T_shadow, T_soft = tail_response(x - d1, shadow, soft, s_eff)
    f = a + g * x + c1 * S + c2 * T
    J = np.stack([np.ones_like(f), x * np.ones_like(f), S, -c1 * S1 - c2 * T_x, T,
                  c2 * T_shadow, c2 * T_soft], axis=2)
    return f, J


def _fit(P: np.ndarray, x: np.ndarray, m: np.ndarray, w: np.ndarray, foot: np.ndarray,
         cam: np.ndarray, lo: np.ndarray, hi: np.ndarray, iterations: int
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_tails_model` fitted to each row's profile (:func:`fit_rows`)."""

    def model(Q: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _tails_model(Q, x[r], foot[r], cam[r])

    return fit_rows(P, model, m, w, lo, hi, iterations)


def shadow_tails(x: np.ndarray, m: np.ndarray, cnt: np.ndarray, foot: np.ndarray,
                 P1: np.ndarray, cost1: np.ndarray, within: np.ndarray, usable: np.ndarray
                 ) -> list[Tail]:
    """The sides at a cast shadow's soft edge (module docstring) among four sides'
    profiles (``x`` distances to the found side, + outward, ``m`` levels, ``cnt`` their
    pixels, ``foot`` the footprints), given their one-step fits ``P1`` = (a, g, s, c, d)
    and residual sums ``cost1``, the pixels' scatter ``within`` the bins and the
    ``usable`` sides."""
    var, bins = pixel_variance(cnt, within)
    misfit = cost1 / np.maximum(var * np.maximum(bins - 5, 1), 1e-12)
    clean = usable & (misfit < _TAIL_CLEAN)
    todo, cams = [], []
    # (a side misfitting 1.5-2 times its noise was fitted 40 % more often, its fit taken
    # in 3 of 390 fitted sides of two corpora, one moved by 0.06 px)
    # one clean side is enough: a cast shadow is the holder's outline shifted, so where
    # its edge lies at a side it lies at the opposite side too, and of the two sides
    # between, one has the shadow under it and the other its band beside it, which
    # misfits one step as well within reach (a shadow shifted 8 px along the holder: its
    # long sides were 0.2-0.3 px off where two clean sides were asked for)
    for k in np.flatnonzero(usable & (misfit >= _TAIL_MISFIT)):
        others = P1[[j for j in np.flatnonzero(clean) if j != k], 2]
        if (others.size >= 1 and float(np.ptp(others)) <= _TAIL_BLUR_AGREE
                and float(np.mean(others)) >= _TAIL_MIN_CAM):
            todo.append(int(k))
            cams.append(float(np.mean(others)))
    if not todo:
        return []
    sides, cam = np.array(todo), np.array(cams)
    n = len(_TAIL_STARTS)
    P = np.array([[a, g, 0.8 * c, d, 0.2 * abs(c), shadow, 2.0 * s_cam]
                  for (a, g, _s, c, d), s_cam in zip(P1[sides], cam, strict=True)
                  for shadow in _TAIL_STARTS])
    rows = np.repeat(sides, n)
    cam_r = np.repeat(cam, n)
    lo = np.tile([-np.inf, -np.inf, -np.inf, -_TAIL_REACH, -np.inf, -_TAIL_UNDER, 0.0],
                 (len(P), 1))
    hi = np.tile([np.inf, np.inf, np.inf, _TAIL_REACH, np.inf, _TAIL_BEYOND, _TAIL_MAX_SOFT],
                 (len(P), 1))
    lo[:, 6] = np.maximum(cam_r + _TAIL_SOFTER, _TAIL_MIN_SOFT)
    P[:, 6] = np.maximum(P[:, 6], lo[:, 6])

    # a few steps from every start, then each side's best start to the end
    P, cost, _ = _fit(P, x[rows], m[rows], cnt[rows], foot[rows], cam_r, lo, hi, 5)
    best = best_starts(cost, n)
    P, cost, A = _fit(P[best], x[sides], m[sides], cnt[sides], foot[sides], cam, lo[best],
                      hi[best], 40)
    tails = []
    for i, k in enumerate(sides):
        _a, _g, c1, d1, c2, shadow, soft = (float(v) for v in P[i])
        c0 = float(P1[k, 3])
        gain = float((cost1[k] - cost[i]) / max(var[k], 1e-12))
        fits = float(cost[i] / max(var[k] * max(bins[k] - 7, 1), 1e-12))
        # (a fit with the shadow's edge or blur at a bound found no shadow's edge: it
        # bends a sloping floor, 0.05-0.19 px off in the corpus)
        inside = (abs(d1) < _TAIL_REACH - _AT_BOUND
                  and -_TAIL_UNDER + _AT_BOUND < shadow < _TAIL_BEYOND - _AT_BOUND
                  and soft < _TAIL_MAX_SOFT - _AT_BOUND)
        if not (gain >= _TAIL_GAIN and fits <= _TAIL_FITS and c1 * c0 > 0 and c2 > 0
                and inside):
            continue
        sigma = standard_error(A[i], 3, float(cost[i]), float(within[k]),
                               float(cnt[k].sum()), 7)
        # a move within its own noise is not made (one step's place is as good), but the
        # side is as uncertain as the fit says; the standard error is a generous one (the
        # shadow's place and blur trade off with the edge's): moves of 1-2 of it were
        # right to 0.03 px in the corpus, and the one wrong (5100 #790, a camera out of
        # focus as far as the shadow: 0.19 +- 0.18 px) is within it
        edge = d1 if abs(d1) >= _TAIL_SIGNIFICANT * sigma else 0.0
        tails.append(Tail(int(k), edge, shadow, sigma,
                          float(cost1[k] / max(float(cost[i]), 1e-12))))
    return tails
