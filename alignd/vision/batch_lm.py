"""Levenberg-Marquardt for many small least-squares problems at once (one a row).

The profile fits fit a few parameters to each of many short profiles (a holder's sides,
the several starts of each); numpy's per-call cost is most of such a fit, so the rows go
through each step together, and a row that stops improving leaves the batch.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

__all__ = ["Model", "best_starts", "fit_rows", "pixel_variance", "standard_error"]

# the model at parameters P (rows ``rows`` of the batch): its values (B, bins) and its
# Jacobian (B, bins, parameters)
Model = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def fit_rows(P: np.ndarray, model: Model, m: np.ndarray, w: np.ndarray, lo: np.ndarray,
             hi: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each row of ``P`` fitted to the data ``m`` (B, bins) of weights ``w`` within the
    bounds ``lo``, ``hi`` (P's shape): the parameters, the weighted residual sums of
    squares and the normal matrices at the end. A row stops when a step gains less than
    1e-4 of its cost or the damping grows past 1e4."""
    P = P.copy()
    all_rows = np.arange(len(P))
    lam = np.full(len(P), 1e-3)
    f, J = model(P, all_rows)
    cost = np.sum(w * (m - f) ** 2, axis=1)
    eye = np.eye(P.shape[1])[None]
    live = np.ones(len(P), bool)  # rows still improving
    for _ in range(iterations):
        b = np.flatnonzero(live)
        if b.size == 0:
            break
        Jw = J[b] * w[b, :, None]
        A = Jw.transpose(0, 2, 1) @ J[b]
        g = (Jw.transpose(0, 2, 1) @ (m[b] - f[b])[..., None])[..., 0]
        # a parameter at its bound that the descent pushes beyond it is held there (an
        # active set): clipped after every step instead, it crawled along the bound and
        # took all the iterations (a sharp side's blur at 0.2 px)
        held = ((P[b] <= lo[b]) & (g < 0)) | ((P[b] >= hi[b]) & (g > 0))
        if held.any():
            free = ~held
            A = A * (free[:, :, None] & free[:, None, :]) + held[:, :, None] * eye
            g = np.where(held, 0.0, g)
        diag = np.einsum("bii->bi", A)[:, :, None] * eye
        try:
            step = np.linalg.solve(A + lam[b, None, None] * diag + 1e-12 * eye,
                                   g[..., None])[..., 0]
        except np.linalg.LinAlgError:
            break
        Q = np.clip(P[b] + step, lo[b], hi[b])
        fq, Jq = model(Q, b)
        cq = np.sum(w[b] * (m[b] - fq) ** 2, axis=1)
        better = cq < cost[b]
        ib = b[better]
        small = better & (cost[b] - cq <= 1e-4 * cost[b])
        P[ib], f[ib], J[ib], cost[ib] = Q[better], fq[better], Jq[better], cq[better]
        lam[b] = np.where(better, lam[b] * 0.3, lam[b] * 10.0)
        live[b[small | (lam[b] > 1e4)]] = False
    Jw = J * w[..., None]
    return P, cost, Jw.transpose(0, 2, 1) @ J


def best_starts(cost: np.ndarray, n_starts: int) -> np.ndarray:
    """The row of each problem's cheapest start, its ``n_starts`` starts being consecutive
    rows with residual sums ``cost``."""
    per = cost.reshape(-1, n_starts)
    return np.argmin(per, axis=1) + n_starts * np.arange(len(per))


def pixel_variance(cnt: np.ndarray, within: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per binned profile (rows of ``cnt``, its bins' pixel counts; ``within``, the pixels'
    sum of squares about their bins' means): a pixel's noise variance and the bins held."""
    bins = np.count_nonzero(cnt > 0, axis=1)
    return within / np.maximum(cnt.sum(axis=1) - bins, 1.0), bins


def standard_error(A: np.ndarray, j: int, cost: float, within: float, pixels: float,
                   parameters: int) -> float:
    """Parameter ``j``'s standard error in a fit of ``parameters`` to a binned profile of
    ``pixels`` (its normal matrix ``A``): the inverse's diagonal scaled by a pixel's
    variance about the fit, its residual sum ``cost`` (the bins' about the model) plus
    ``within`` (the pixels' about their bins' means); inf where ``A`` is singular."""
    var_px = (cost + within) / max(pixels - parameters, 1.0)
    try:
        return math.sqrt(max(float(np.linalg.inv(A)[j, j]) * var_px, 0.0))
    except np.linalg.LinAlgError:
        return math.inf
