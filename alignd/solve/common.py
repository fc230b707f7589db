"""Shared checks and robust-statistics helpers for the solvers."""

from __future__ import annotations

import math

import numpy as np

from alignd.errors import SolveError

from .sweep import Sweep

# Huber threshold in units of the noise scale (about 95 % efficiency on Gaussian data).
HUBER_K = 2.0
# Rejection thresholds: chi-square 99.9 % points for a 2-D residual and a 1-D residual, so a
# clean sweep loses about 0.1 % of its points.
CUT_2D = math.sqrt(13.815510557964274)
CUT_1D = 3.2905267314919255
# median of a Rayleigh(1) variable: turns the median 2-D residual norm into a per-axis sigma
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
MIN_SPREAD_DEG = 1e-3

__all__ = ["CUT_1D", "CUT_2D", "HUBER_K", "SolveInputs", "WeightedMean", "check_sweep",
           "huber_weights", "paule_mandel", "robust_sigma_1d", "robust_sigma_2d", "rot",
           "weighted_mean"]


class SolveInputs:
    """Validated arrays: angles in rad, points (F, K, 2), detection mask (F, K)."""

    def __init__(self, angles_rad: np.ndarray, points: np.ndarray, valid: np.ndarray) -> None:
        self.angles_rad = angles_rad
        self.points = points
        self.valid = valid

    @property
    def n_frames(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_features(self) -> int:
        return int(self.points.shape[1])


def check_sweep(sweep: Sweep) -> SolveInputs:
    """Shapes, finiteness and the minimum data any method needs; SolveError otherwise."""
    pts = np.asarray(sweep.points, dtype=float)
    ang = np.asarray(sweep.angles_deg, dtype=float)
    if pts.ndim != 3 or pts.shape[2] != 2:
        raise SolveError(f"points must have shape (frames, features, 2), got {pts.shape}")
    if ang.ndim != 1 or ang.shape[0] != pts.shape[0]:
        raise SolveError(f"angles_deg must have shape ({pts.shape[0]},) to match the points, "
                         f"got {ang.shape}")
    if pts.shape[0] == 0 or pts.shape[1] == 0:
        raise SolveError(f"empty sweep: {pts.shape[0]} frames x {pts.shape[1]} features")
    if not np.all(np.isfinite(ang)):
        bad = np.flatnonzero(~np.isfinite(ang))
        raise SolveError(f"angle readback is NaN or infinite in frame(s) {bad[:10].tolist()}")
    if np.any(np.isinf(pts)):
        raise SolveError("points contain infinite coordinates")
    nan = np.isnan(pts)
    half = nan[..., 0] != nan[..., 1]
    if np.any(half):
        f, k = np.argwhere(half)[0]
        raise SolveError(f"point frame {f} feature {k} has one NaN coordinate; a missed "
                         "detection must be NaN in both")
    valid = ~nan[..., 0]
    usable = int(np.count_nonzero(valid.any(axis=1)))
    if usable < 3:
        raise SolveError(f"fewer than 3 usable frames ({usable} frames with any detection)")
    return SolveInputs(np.deg2rad(ang), pts, valid)


def rot(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of the angles (R(a) = [[c, -s], [s, c]] in y-down pixel coordinates)."""
    return np.cos(a), np.sin(a)


def robust_sigma_2d(norms: np.ndarray) -> float:
    """Per-axis sigma from 2-D residual norms via their median (Rayleigh)."""
    if norms.size == 0:
        return 0.0
    return float(np.median(norms)) / RAYLEIGH_MEDIAN


def robust_sigma_1d(e: np.ndarray) -> float:
    """Sigma of 1-D residuals from the median absolute value."""
    if e.size == 0:
        return 0.0
    return 1.482602218505602 * float(np.median(np.abs(e)))


def huber_weights(norms: np.ndarray, sigma: float, k: float = HUBER_K) -> np.ndarray:
    """IRLS weights of the Huber loss on residual norms."""
    t = k * max(sigma, 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(norms <= t, 1.0, t / np.maximum(norms, 1e-300))
    return w


class WeightedMean:
    """The inverse-covariance weighted mean of 2-D points, its covariance and chi-square
    ``q``, each point's covariance widened by ``tau2`` per axis."""

    __slots__ = ("cov", "mean", "q")

    def __init__(self, mean: np.ndarray, cov: np.ndarray, q: float) -> None:
        self.mean, self.cov, self.q = mean, cov, q


def weighted_mean(cs: list[np.ndarray], covs: list[np.ndarray], tau2: float = 0.0
                  ) -> WeightedMean:
    """See :class:`WeightedMean` (the sweeps' centres pooled, a feature's centres)."""
    Ws = [np.linalg.inv(cov + tau2 * np.eye(2)) for cov in covs]
    cov_m = np.linalg.inv(sum(Ws))
    m = cov_m @ sum(W @ c for W, c in zip(Ws, cs, strict=True))
    q = float(sum((c - m) @ W @ (c - m) for W, c in zip(Ws, cs, strict=True)))
    return WeightedMean(m, cov_m, q)


def paule_mandel(cs: list[np.ndarray], covs: list[np.ndarray]) -> float:
    """The excess variance tau^2 per axis at which the points' weighted scatter equals its
    degrees of freedom (Paule-Mandel; q falls as tau^2 grows); 0 where it already does.
    The caller decides first whether the scatter is significant."""
    dof = 2 * (len(cs) - 1)
    if dof <= 0 or weighted_mean(cs, covs).q <= dof:
        return 0.0
    lo, hi = 0.0, max(float(np.max([np.sum((c - cs[0]) ** 2) for c in cs])), 1e-12)
    while weighted_mean(cs, covs, hi).q > dof:
        hi *= 4.0
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if weighted_mean(cs, covs, mid).q > dof else (lo, mid)
    return hi
