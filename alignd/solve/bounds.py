"""Cramer-Rao lower bounds on the centre for a known sweep geometry.

The Fisher information is built from a numerically differentiated forward model, on purpose
independent of the solvers' analytic normal equations, so comparing a solver's error with
the bound also checks its algebra. Gaussian noise of ``sigma`` px per axis on every
detection in ``mask``.

Models:
- ``known``: angles known exactly (what ``rigid-known`` assumes).
- ``free``: angles unknown per frame (``rigid``); the common angle offset is a gauge and is
  fixed by holding one frame's angle, which leaves the centre's bound unchanged.
- ``circles``: each detection's position on its circle unknown (``circles``, ``thesis``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["MODELS", "crlb_center"]

MODELS = ("known", "free", "circles")


def _jacobian(fun: Callable[[np.ndarray], np.ndarray], theta: np.ndarray,
              h: float = 1e-4) -> np.ndarray:
    cols = []
    for i in range(theta.size):
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        cols.append((fun(tp) - fun(tm)) / (2 * h))
    return np.stack(cols, axis=1)


def crlb_center(center_px: np.ndarray, template_px: np.ndarray, angles_deg: np.ndarray,
                sigma_px: float, model: str = "known",
                mask: np.ndarray | None = None) -> np.ndarray:
    """2x2 lower bound on the covariance of any unbiased centre estimate."""
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; choose one of {MODELS}")
    c = np.asarray(center_px, dtype=float)
    q = np.asarray(template_px, dtype=float)
    a = np.deg2rad(np.asarray(angles_deg, dtype=float))
    F, K = a.size, q.shape[0]
    m = np.ones((F, K), bool) if mask is None else np.asarray(mask, bool)
    feats = np.flatnonzero(m.any(axis=0))
    frames = np.flatnonzero(m.any(axis=1))

    def rigid(cc: np.ndarray, qq: np.ndarray, aa: np.ndarray) -> np.ndarray:
        cs, sn = np.cos(aa)[:, None], np.sin(aa)[:, None]
        d = qq - cc
        x = cc[0] + cs * d[None, :, 0] - sn * d[None, :, 1]
        y = cc[1] + sn * d[None, :, 0] + cs * d[None, :, 1]
        return np.stack([x, y], axis=-1)[m].ravel()

    if model == "known":
        def fun(t: np.ndarray) -> np.ndarray:
            qq = q.copy()
            qq[feats] = t[2:].reshape(-1, 2)
            return rigid(t[:2], qq, a)
        theta = np.concatenate([c, q[feats].ravel()])
    elif model == "free":
        free_frames = frames[1:]  # frames[0] holds the gauge

        def fun(t: np.ndarray) -> np.ndarray:
            qq = q.copy()
            nq = 2 * feats.size
            qq[feats] = t[2:2 + nq].reshape(-1, 2)
            aa = a.copy()
            aa[free_frames] = t[2 + nq:]
            return rigid(t[:2], qq, aa)
        theta = np.concatenate([c, q[feats].ravel(), a[free_frames]])
    else:
        f_idx, k_idx = np.nonzero(m)
        p = (c + np.stack([np.cos(a)[:, None] * (q - c)[None, :, 0]
                           - np.sin(a)[:, None] * (q - c)[None, :, 1],
                           np.sin(a)[:, None] * (q - c)[None, :, 0]
                           + np.cos(a)[:, None] * (q - c)[None, :, 1]], axis=-1))[m]
        radii = np.hypot(*(q - c).T)
        phi = np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0])
        col = {k: i for i, k in enumerate(feats)}
        ridx = np.array([col[k] for k in k_idx])

        def fun(t: np.ndarray) -> np.ndarray:
            rr = t[2:2 + feats.size][ridx]
            ph = t[2 + feats.size:]
            return np.stack([t[0] + rr * np.cos(ph), t[1] + rr * np.sin(ph)], axis=-1).ravel()
        theta = np.concatenate([c, radii[feats], phi])
        del f_idx
    J = _jacobian(fun, theta)
    info = J.T @ J / sigma_px**2
    return np.linalg.inv(info)[:2, :2]
