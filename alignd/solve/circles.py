"""Concentric circle fit: one common centre, one radius per feature, no angles used.

For sweeps whose angles are unusable. Each detection constrains only its distance from the
centre (its position along the circle is free), so with a +-10 deg arc each feature fixes
the centre well across its radius and poorly along it; several features at different bearings
make the combination usable. Geometric (not algebraic) residuals |p - c| - r_k, started from
the algebraic (Kasa) concentric fit, with the same robust scheme as the rigid fit: Huber IRLS,
then hard rejection at the chi-square 99.9 % point and refits on the inliers.
"""

from __future__ import annotations

import logging

import numpy as np

from alignd.errors import SolveError

from .common import CUT_1D, SolveInputs, huber_weights, robust_sigma_1d
from .result import CentreResult

log = logging.getLogger(__name__)

__all__ = ["fit_circles"]

_MAX_HUBER = 40
_MAX_MASK = 8
_MAX_GN = 20


def _kasa(Px: np.ndarray, Py: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Algebraic concentric fit: |p|^2 = 2 c.p + d_k, linear in (c, d); returns c, r."""
    K = w.shape[1]
    rows = np.flatnonzero(w.ravel() > 0)
    fk = np.repeat(np.arange(K)[None, :], w.shape[0], axis=0).ravel()[rows]
    x, y, ww = Px.ravel()[rows], Py.ravel()[rows], np.sqrt(w.ravel()[rows])
    A = np.zeros((rows.size, 2 + K))
    A[:, 0], A[:, 1] = 2 * x, 2 * y
    A[np.arange(rows.size), 2 + fk] = 1.0
    b = x * x + y * y
    sol, *_ = np.linalg.lstsq(A * ww[:, None], b * ww, rcond=None)
    c = sol[:2]
    d = sol[2:]
    r = np.sqrt(np.maximum(d + c @ c, 0.0))
    return c, r


def _gn(Px: np.ndarray, Py: np.ndarray, w: np.ndarray, c: np.ndarray,
        r: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """One Gauss-Newton step on (c, r); radii eliminated by their Schur complement."""
    ux, uy = Px - c[0], Py - c[1]
    dist = np.hypot(ux, uy)
    dist = np.where(dist > 0, dist, 1.0)
    ux, uy = ux / dist, uy / dist
    e = dist - r[None, :]
    we = w * e
    # J = [-u, -1]; normal equations H delta = -J'W e
    Hcc = np.array([[np.sum(w * ux * ux), np.sum(w * ux * uy)],
                    [np.sum(w * ux * uy), np.sum(w * uy * uy)]])
    hk = np.stack([np.sum(w * ux, axis=0), np.sum(w * uy, axis=0)], axis=1)  # (K, 2)
    Wk = w.sum(axis=0)
    act = Wk > 0
    Wd = np.where(act, Wk, 1.0)
    bc = np.array([np.sum(we * ux), np.sum(we * uy)])
    bk = we.sum(axis=0)
    S = Hcc - (hk / Wd[:, None]).T @ hk
    try:
        dc = np.linalg.solve(S, bc - (hk / Wd[:, None]).T @ bk)
    except np.linalg.LinAlgError as exc:
        raise SolveError("circles: centre not determined (points collinear or no spread)") \
            from exc
    dr = np.where(act, (bk - hk @ dc) / Wd, 0.0)
    return c + dc, r + dr, S, float(np.hypot(*dc))


def fit_circles(inp: SolveInputs) -> CentreResult:
    """Concentric geometric circle fit (see module doc)."""
    method = "circles"
    valid = inp.valid & (inp.valid.sum(axis=0) >= 2)[None, :]
    F = valid.shape[0]
    if np.count_nonzero(valid.any(axis=1)) < 3:
        raise SolveError(f"{method}: fewer than 3 usable frames")
    n_used = int(np.count_nonzero(valid.any(axis=0)))
    if int(valid.sum()) < 3 + n_used:
        raise SolveError(f"{method}: {int(valid.sum())} detections cannot fix a centre and "
                         f"{n_used} radii")
    o = np.nanmean(inp.points[valid], axis=0)
    Px = np.where(valid, inp.points[..., 0] - o[0], 0.0)
    Py = np.where(valid, inp.points[..., 1] - o[1], 0.0)
    extent = float(np.max(np.hypot(Px, Py)[valid]))
    # exact collinearity (or no motion) of every path leaves no circle to fit
    curved = False
    for k in np.flatnonzero(valid.any(axis=0)):
        pk = np.stack([Px[valid[:, k], k], Py[valid[:, k], k]], axis=1)
        sv = np.linalg.svd(pk - pk.mean(axis=0), compute_uv=False)
        if sv.size >= 2 and sv[1] > 1e-9 * max(extent, 1e-300):
            curved = True
    if not curved:
        raise SolveError(f"{method}: the points of every feature are collinear (or do not "
                         "move): no circle to fit")
    vf = valid.astype(float)
    c, r = _kasa(Px, Py, vf)
    if not np.all(np.isfinite(c)):
        raise SolveError(f"{method}: centre not determined (collinear points)")
    n_obs = int(valid.sum())
    dof_corr = np.sqrt(n_obs / max(n_obs - 2 - n_used, 1))
    sigma = 0.0
    for _ in range(_MAX_HUBER):
        e = np.hypot(Px - c[0], Py - c[1]) - r[None, :]
        sigma = robust_sigma_1d(e[valid]) * dof_corr
        c, r, _, step = _gn(Px, Py, vf * huber_weights(np.abs(e), sigma), c, r)
        if step < 1e-2 * max(sigma, 1e-6):
            break
    e = np.hypot(Px - c[0], Py - c[1]) - r[None, :]
    sigma = robust_sigma_1d(e[valid]) * dof_corr
    mask = valid & (np.abs(e) <= CUT_1D * max(sigma, 1e-12))
    S = None
    for _ in range(_MAX_MASK):
        wm = mask.astype(float)
        for _ in range(_MAX_GN):
            c, r, S, step = _gn(Px, Py, wm, c, r)
            if step < 1e-4 * max(sigma, 1e-6) + 1e-12:
                break
        e = np.hypot(Px - c[0], Py - c[1]) - r[None, :]
        n_in = int(mask.sum())
        dof = n_in - 2 - int(np.count_nonzero(mask.any(axis=0)))
        if dof <= 0:
            raise SolveError(f"{method}: not enough inlier detections ({n_in})")
        sigma = float(np.sqrt(np.sum(e[mask] ** 2) / dof))
        new_mask = valid & (np.abs(e) <= CUT_1D * max(sigma, 1e-12))
        if np.array_equal(new_mask, mask):
            break
        mask = new_mask
    assert S is not None
    used_r = r[mask.any(axis=0)]
    if not np.all(np.isfinite(c)) or np.any(used_r > 1e4 * max(extent, 1.0)):
        raise SolveError(f"{method}: centre not determined: the paths are (nearly) straight "
                         "lines (collinear points)")
    try:
        cov = np.linalg.inv(S) * sigma**2
    except np.linalg.LinAlgError as exc:
        raise SolveError(f"{method}: centre not determined (singular normal equations)") from exc
    cov = 0.5 * (cov + cov.T)
    ev = np.linalg.eigvalsh(cov)
    if ev[0] < 0 or not np.all(np.isfinite(ev)) or np.sqrt(ev[-1]) > 1e3 * max(extent, 1.0):
        raise SolveError(f"{method}: centre not determined by the data (collinear points "
                         "or too little curvature)")
    outliers = int(np.count_nonzero(inp.valid & ~mask))
    # rms of the radial (geometric) residuals: the tangential noise leaves no residual here
    rms = float(np.sqrt(np.mean(e[mask] ** 2)))
    return CentreResult(center_px=c + o, cov_px2=cov, method=method, rms_residual_px=rms,
                        inliers=int(mask.sum()), outliers=outliers, inlier_mask=mask,
                        angles_deg=np.rad2deg(inp.angles_rad), n_frames=F,
                        extra={"sigma_px": sigma, "radii_px": r})
