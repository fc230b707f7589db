"""The thesis baseline (Kivi 2014, sec. 3.3), reproduced faithfully but memory-bounded.

1. For every pair of points (i, j) of a feature's path: the perpendicular bisector through
   the midpoint, slope ``k = -(xj - xi) / (yj - yi)`` (eqs. 3.2-3.4).
2. Filtering: drop slopes farther than T1 from the path's median slope; fit a curve (a
   quadratic in the pair's mean frame index) to the rest; drop slopes farther than T2 from it.
   The thesis set T1/T2 by hand; here they are multiples of the robust spread so the
   defaults carry over between geometries.
3. Keep a seeded random subset of the bisectors (the thesis' memory workaround).
4. Intersect every pair of kept bisectors, across all paths.
5. The centre is the geometric median of the intersections (eq. 3.5), by Weiszfeld.

The LabVIEW original ran out of memory at 90 frames (~13,000 bisectors, ~84 million
intersections). Here the intersections are regenerated chunk by chunk on every Weiszfeld
pass (started from the median of a random sample) and never stored, so memory stays at a few
MB whatever the count: the full 90-frame set takes seconds. The method has no uncertainty of
its own; ``fit_thesis`` adds a delete-a-group jackknife over interleaved frame groups. The
default keeps at most 1000 bisectors (``keep_fraction=1.0`` keeps them all).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from alignd.errors import SolveError

from .common import SolveInputs
from .result import CentreResult

log = logging.getLogger(__name__)

__all__ = ["ThesisInfo", "bisectors", "filter_slopes", "fit_thesis", "geometric_median",
           "thesis_centre"]

CHUNK_PAIRS = 1 << 18          # intersections generated per chunk (a few MB of temporaries)
AUTO_MAX_BISECTORS = 1000      # auto subset: about 500,000 intersections


@dataclass(frozen=True)
class Bisectors:
    """Perpendicular bisectors as lines n . x = b (n a unit normal), with bookkeeping."""

    nx: np.ndarray
    ny: np.ndarray
    b: np.ndarray
    slope: np.ndarray
    path: np.ndarray
    mid_index: np.ndarray

    def __len__(self) -> int:
        return int(self.nx.size)

    def take(self, idx: np.ndarray) -> Bisectors:
        return Bisectors(self.nx[idx], self.ny[idx], self.b[idx], self.slope[idx],
                         self.path[idx], self.mid_index[idx])


@dataclass(frozen=True)
class ThesisInfo:
    n_bisectors: int
    n_filtered: int
    n_kept: int
    n_intersections: int
    weiszfeld_passes: int


def bisectors(P: np.ndarray, valid: np.ndarray) -> Bisectors:
    """All point-pair bisectors of every path (eqs. 3.2-3.4)."""
    parts = []
    for k in range(valid.shape[1]):
        idx = np.flatnonzero(valid[:, k])
        if idx.size < 2:
            continue
        i, j = np.triu_indices(idx.size, 1)
        pi, pj = P[idx[i], k], P[idx[j], k]
        d = pj - pi
        ln = np.hypot(d[:, 0], d[:, 1])
        ok = ln > 0
        d, ln, pi, pj = d[ok], ln[ok], pi[ok], pj[ok]
        n = d / ln[:, None]
        m = 0.5 * (pi + pj)
        with np.errstate(divide="ignore", invalid="ignore"):
            slope = -d[:, 0] / d[:, 1]
        parts.append((n[:, 0], n[:, 1], np.sum(n * m, axis=1), slope,
                      np.full(n.shape[0], k), 0.5 * (idx[i][ok] + idx[j][ok])))
    if not parts:
        raise SolveError("thesis: no feature has two detections: no bisectors")
    cols = [np.concatenate(c) for c in zip(*parts, strict=True)]
    return Bisectors(*cols)


def _robust_sd(x: np.ndarray) -> float:
    return 1.482602218505602 * float(np.median(np.abs(x - np.median(x)))) if x.size else 0.0


def filter_slopes(bis: Bisectors, t1: float = 4.0, t2: float = 3.0) -> np.ndarray:
    """The thesis' T1/T2 slope filter, per path; returns the mask of bisectors kept."""
    keep = np.zeros(len(bis), bool)
    for k in np.unique(bis.path):
        sel = np.flatnonzero(bis.path == k)
        s = bis.slope[sel]
        fin = np.isfinite(s)
        if np.count_nonzero(fin) < 4:
            keep[sel[fin]] = True
            continue
        med = float(np.median(s[fin]))
        T1 = t1 * max(_robust_sd(s[fin]), 1e-12)
        ok = fin & (np.abs(s - med) <= T1)
        x = bis.mid_index[sel]
        if np.count_nonzero(ok) >= 6:
            coef = np.polyfit(x[ok], s[ok], 2)
            res = s - np.polyval(coef, x)
            T2 = t2 * max(_robust_sd(res[ok]), 1e-12)
            ok &= np.abs(res) <= T2
        keep[sel[ok]] = True
    return keep


def _intersect(nx1: np.ndarray, ny1: np.ndarray, b1: np.ndarray, nx2: np.ndarray,
               ny2: np.ndarray, b2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intersections of lines n1 . x = b1 and n2 . x = b2 (broadcast), parallel ones dropped."""
    det = nx1 * ny2 - ny1 * nx2
    good = np.abs(det) > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        x = (b1 * ny2 - b2 * ny1) / det
        y = (nx1 * b2 - nx2 * b1) / det
    if good.all():
        return x.ravel(), y.ravel()
    return x[good], y[good]


def _intersections(bis: Bisectors, chunk: int = CHUNK_PAIRS) -> Iterator[tuple[np.ndarray,
                                                                               np.ndarray]]:
    """All pairwise intersections, chunk by chunk: a block of rows against the rows after
    it (a full rectangle), then the pairs within the block."""
    n = len(bis)
    nx, ny, b = bis.nx, bis.ny, bis.b
    i0 = 0
    while i0 < n - 1:
        rows = max(1, min(n - i0, chunk // max(n - i0, 1)))
        i1 = i0 + rows
        a, rest = slice(i0, i1), slice(i1, n)
        if i1 < n:
            yield _intersect(nx[a, None], ny[a, None], b[a, None],
                             nx[None, rest], ny[None, rest], b[None, rest])
        if rows > 1:
            i, j = np.triu_indices(rows, 1)
            i, j = i + i0, j + i0
            yield _intersect(nx[i], ny[i], b[i], nx[j], ny[j], b[j])
        i0 = i1


def _weiszfeld_pass(bis: Bisectors, x: np.ndarray, chunk: int = CHUNK_PAIRS) -> np.ndarray:
    """One Weiszfeld step over all pairwise intersections, generated chunk by chunk and
    never stored (memory ~ chunk, whatever the bisector count)."""
    n = len(bis)
    nx, ny = bis.nx, bis.ny
    bx = bis.b - nx * x[0] - ny * x[1]  # the lines with x as origin
    sw = sx = sy = 0.0

    def accumulate(det: np.ndarray, X: np.ndarray, Y: np.ndarray) -> None:
        nonlocal sw, sx, sy
        bad = np.abs(det) < 1e-9
        np.reciprocal(det, out=det, where=~bad)
        det[bad] = 0.0
        X *= det
        Y *= det
        d = np.multiply(X, X)
        d += Y * Y
        np.sqrt(d, out=d)
        np.maximum(d, 1e-9, out=d)
        np.reciprocal(d, out=d)
        d[bad] = 0.0
        sw += float(d.sum())
        sx += float(np.vdot(d, X))
        sy += float(np.vdot(d, Y))

    i0 = 0
    while i0 < n - 1:
        rows = max(1, min(n - i0, chunk // max(n - i0, 1)))
        i1 = i0 + rows
        a, r = slice(i0, i1), slice(i1, n)
        if i1 < n:
            det = np.multiply(nx[a, None], ny[None, r])
            det -= ny[a, None] * nx[None, r]
            X = np.multiply(bx[a, None], ny[None, r])
            X -= bx[None, r] * ny[a, None]
            Y = np.multiply(nx[a, None], bx[None, r])
            Y -= nx[None, r] * bx[a, None]
            accumulate(det, X, Y)
        if rows > 1:
            i, j = np.triu_indices(rows, 1)
            i, j = i + i0, j + i0
            accumulate(nx[i] * ny[j] - ny[i] * nx[j], bx[i] * ny[j] - bx[j] * ny[i],
                       nx[i] * bx[j] - nx[j] * bx[i])
        i0 = i1
    if sw == 0.0:
        raise SolveError("thesis: all bisectors are parallel (collinear points)")
    return np.array([x[0] + sx / sw, x[1] + sy / sw])


def _sample_intersections(bis: Bisectors, m: int,
                          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    n = len(bis)
    i = rng.integers(0, n, m)
    j = rng.integers(0, n, m)
    i, j = i[i != j], j[i != j]
    return _intersect(bis.nx[i], bis.ny[i], bis.b[i], bis.nx[j], bis.ny[j], bis.b[j])


def geometric_median(chunks: Callable[[], Iterator[tuple[np.ndarray, np.ndarray]]],
                     x0: np.ndarray, tol: float = 1e-4,
                     max_passes: int = 500) -> tuple[np.ndarray, int]:
    """Weiszfeld iteration over points delivered in chunks; returns (median, passes)."""
    x = np.asarray(x0, dtype=float).copy()
    for it in range(1, max_passes + 1):
        sw = swx = swy = 0.0
        for X, Y in chunks():
            d = np.hypot(X - x[0], Y - x[1])
            w = 1.0 / np.maximum(d, 1e-9)
            sw += float(w.sum())
            swx += float(w @ X)
            swy += float(w @ Y)
        if sw == 0.0:
            raise SolveError("thesis: no bisector intersections")
        new = np.array([swx / sw, swy / sw])
        step = float(np.hypot(*(new - x)))
        x = new
        if step < tol:
            return x, it
    return x, max_passes


def thesis_centre(inp: SolveInputs, *, keep_fraction: float | None = None, seed: int = 0,
                  t1: float = 4.0, t2: float = 3.0,
                  max_bisectors: int = AUTO_MAX_BISECTORS,
                  chunk: int = CHUNK_PAIRS, tol_px: float = 1e-3,
                  max_passes: int = 200) -> tuple[np.ndarray, ThesisInfo]:
    """The baseline's centre. ``keep_fraction`` None keeps at most ``max_bisectors``; 1.0
    keeps the full bisector set."""
    valid = inp.valid
    o = np.nanmean(inp.points[valid], axis=0)
    P = np.where(valid[..., None], inp.points - o, 0.0)
    _check_curved(P, valid)
    bis = bisectors(P, valid)
    n_all = len(bis)
    bis = bis.take(np.flatnonzero(filter_slopes(bis, t1, t2)))
    n_filt = len(bis)
    rng = np.random.default_rng(seed)
    if keep_fraction is None:
        keep_fraction = min(1.0, max_bisectors / max(n_filt, 1))
    if not 0.0 < keep_fraction <= 1.0:
        raise SolveError(f"thesis: keep_fraction must be in (0, 1], got {keep_fraction}")
    if keep_fraction < 1.0:
        n_keep = max(2, round(keep_fraction * n_filt))
        bis = bis.take(np.sort(rng.choice(n_filt, size=min(n_keep, n_filt), replace=False)))
    if len(bis) < 2:
        raise SolveError("thesis: fewer than 2 bisectors survive the slope filter")
    n_int = len(bis) * (len(bis) - 1) // 2
    # start from the geometric median of a random sample of intersections ...
    sx, sy = _sample_intersections(bis, 200_000, rng)
    if sx.size == 0:
        raise SolveError("thesis: all bisectors are parallel (collinear points)")
    x, _ = geometric_median(lambda: iter([(sx, sy)]), np.array([np.median(sx), np.median(sy)]),
                            tol=tol_px)
    # ... then Weiszfeld passes over all of them
    passes = 0
    for passes in range(1, max_passes + 1):  # noqa: B007
        new = _weiszfeld_pass(bis, x, chunk)
        step = float(np.hypot(*(new - x)))
        x = new
        if step < tol_px:
            break
    info = ThesisInfo(n_all, n_filt, len(bis), n_int, passes)
    log.debug("thesis: %s", info)
    return x + o, info


def _check_curved(P: np.ndarray, valid: np.ndarray) -> None:
    """Bisectors of a straight path are parallel: refuse data with no curved path."""
    extent = float(np.max(np.hypot(P[..., 0], P[..., 1])[valid])) if valid.any() else 0.0
    for k in range(valid.shape[1]):
        pk = P[valid[:, k], k]
        if pk.shape[0] < 3:
            continue
        sv = np.linalg.svd(pk - pk.mean(axis=0), compute_uv=False)
        if sv[1] > 1e-9 * max(extent, 1e-300):
            return
    raise SolveError("thesis: the points of every feature are collinear (or do not move)")


def fit_thesis(inp: SolveInputs, seed: int = 0, groups: int = 10,
               **kw: float | int | None) -> CentreResult:
    """Baseline centre with a jackknife covariance over ``groups`` interleaved frame groups."""
    c, info = thesis_centre(inp, seed=seed, **kw)  # type: ignore[arg-type]
    F = inp.n_frames
    groups = min(groups, F)
    reps = []
    for g in range(groups):
        keep = (np.arange(F) % groups) != g
        sub = SolveInputs(inp.angles_rad[keep], inp.points[keep], inp.valid[keep])
        try:
            cg, _ = thesis_centre(sub, seed=seed + 1 + g, **kw)  # type: ignore[arg-type]
        except SolveError:
            continue
        reps.append(cg)
    if len(reps) < 3:
        raise SolveError("thesis: too few frames for an uncertainty (jackknife failed)")
    R = np.asarray(reps)
    dev = R - R.mean(axis=0)
    cov = (len(R) - 1) / len(R) * dev.T @ dev
    dist = np.hypot(inp.points[..., 0] - c[0], inp.points[..., 1] - c[1])
    rad = np.nanmedian(dist, axis=0)
    res = (dist - rad[None, :])[inp.valid]
    return CentreResult(center_px=c, cov_px2=cov, method="thesis",
                        rms_residual_px=float(np.sqrt(np.mean(res**2))),
                        inliers=int(inp.valid.sum()), outliers=0, inlier_mask=inp.valid.copy(),
                        angles_deg=np.rad2deg(inp.angles_rad), n_frames=F,
                        extra={"info": info})
