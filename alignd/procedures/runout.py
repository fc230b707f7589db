"""Turntable error motion (runout): how far the rotation axis wanders as the table turns.

A real bearing does not turn about one fixed line: its axis moves by a few um, periodically
with the angle (the simulated one by harmonics 2 and 3). The part of that motion a rigid
rotation cannot absorb biases every centre fit by up to its amplitude, so commissioning
measures it once over a wide sweep and later sweeps subtract it.

The model, for a point carried by the turntable (the holder's centre) seen at angle ``a``::

    z(a) = c + R(s a) p + w(a)

with ``c`` the mean axis, ``p`` the point's arm, ``s`` = +1 or -1 the turning sense in the
image, and ``w`` the error motion, written as a Fourier series of harmonics 2..K (harmonics
0 and 1 are the axis and the arm: no measurement on one point separates them from ``w``).
All terms are linear in the unknowns, so one least-squares solve gives everything. Over most
of a turn (``WELL_SEPARATED_DEG``) the harmonics stay nearly orthogonal to the rigid terms
and the fitted series is the error motion; on a short sweep they are not, and the map is
what is left after the best rigid fit over the swept range (the part that would bias a
centre fit on that range).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from alignd.errors import SolveError

DEFAULT_HARMONICS = (2, 3, 4, 5)
# over at least this span the harmonics separate from the rigid terms (nearly orthogonal):
# the fitted series is the error motion itself, harmonics 0 and 1 excluded
WELL_SEPARATED_DEG = 270.0


def _rigid_columns(a_rad: np.ndarray, sign: int) -> np.ndarray:
    """Design matrix (2n, 4) of the rigid part: axis (cx, cy) and arm (px, py)."""
    n = len(a_rad)
    c, s = np.cos(sign * a_rad), np.sin(sign * a_rad)
    A = np.zeros((2 * n, 4))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[0::2, 2], A[0::2, 3] = c, -s  # R(a) p, x row
    A[1::2, 2], A[1::2, 3] = s, c  # y row
    return A


def _harmonic_columns(a_rad: np.ndarray, harmonics: tuple[int, ...]) -> np.ndarray:
    """Design matrix (2n, 4 K): cos and sin of each harmonic, separately in x and in y."""
    n = len(a_rad)
    cols = []
    for k in harmonics:
        ck, sk = np.cos(k * a_rad), np.sin(k * a_rad)
        for v in (ck, sk):
            cx = np.zeros(2 * n)
            cy = np.zeros(2 * n)
            cx[0::2] = v
            cy[1::2] = v
            cols += [cx, cy]
    return np.column_stack(cols) if cols else np.zeros((2 * n, 0))


@dataclass(frozen=True)
class RunoutMap:
    """Turntable error motion: the axis' displacement from the mean axis, per angle, in the image
    plane of the top camera, mm (x right, y down in image axes scaled by pixel size)."""

    angles_deg: np.ndarray  # sorted, the measured angles
    offset_mm: np.ndarray  # shape (n, 2): displacement of the axis at each angle
    residual_um: float  # RMS of what the model does not explain (1 sigma)

    def __post_init__(self) -> None:
        a = np.asarray(self.angles_deg, float)
        o = np.asarray(self.offset_mm, float)
        if a.ndim != 1 or o.shape != (len(a), 2) or len(a) < 2:
            raise ValueError(f"a runout map needs n >= 2 angles and (n, 2) offsets, got "
                             f"{a.shape} and {o.shape}")
        if not np.all(np.diff(a) > 0):
            raise ValueError("runout map angles must be strictly increasing")
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(o))):
            raise ValueError("runout map holds non-finite values")
        object.__setattr__(self, "angles_deg", a)
        object.__setattr__(self, "offset_mm", o)

    @property
    def full_turn(self) -> bool:
        """Whether the map covers a whole turn (then it wraps round, else it is clamped)."""
        step = float(np.median(np.diff(self.angles_deg)))
        return float(self.angles_deg[-1] - self.angles_deg[0]) + 1.5 * step >= 360.0

    @property
    def amplitude_um(self) -> float:
        """The largest displacement in the map (um)."""
        return float(np.hypot(self.offset_mm[:, 0], self.offset_mm[:, 1]).max() * 1000.0)

    def at(self, angle_deg: float | np.ndarray) -> np.ndarray:
        """Displacement (mm) at the given angle(s), linearly interpolated, shape (..., 2).

        A full-turn map wraps round; a partial one holds its end values outside its range.
        """
        q = np.asarray(angle_deg, float)
        a = self.angles_deg
        if self.full_turn:
            a0 = float(a[0])
            q = a0 + np.mod(q - a0, 360.0)
            a = np.concatenate([a, [a0 + 360.0]])
            o = np.vstack([self.offset_mm, self.offset_mm[:1]])
        else:
            o = self.offset_mm
        return np.stack([np.interp(q, a, o[:, 0]), np.interp(q, a, o[:, 1])], axis=-1)

    def correct_px(self, angles_deg: np.ndarray, points_px: np.ndarray,
                   pixel_size_mm: float) -> np.ndarray:
        """Image points with the error motion taken out: ``points - at(angle) / pixel``.

        ``points_px`` is (n, 2) or (n, m, 2) for n frames at ``angles_deg`` (NaN stays NaN)."""
        p = np.asarray(points_px, float)
        d = self.at(np.asarray(angles_deg, float)) / pixel_size_mm
        if p.ndim == 3:
            d = d[:, None, :]
        return p - d

    def to_json(self) -> dict[str, object]:
        return {"version": 1, "angles_deg": self.angles_deg.tolist(),
                "offset_um": (self.offset_mm * 1000.0).tolist(),
                "residual_um": self.residual_um, "amplitude_um": self.amplitude_um}

    @classmethod
    def from_json(cls, d: dict[str, object]) -> RunoutMap:
        """The inverse of ``to_json``; a malformed record raises ``ValueError`` naming it."""
        try:
            angles = np.asarray(d["angles_deg"], float)
            off = np.asarray(d["offset_um"], float) / 1000.0
            res = float(d["residual_um"])  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"malformed runout map: {exc}") from None
        return cls(angles, off.reshape(-1, 2) if off.size else off, res)


def _solve(R: np.ndarray, ar: np.ndarray, hs: tuple[int, ...], y: np.ndarray
           ) -> tuple[np.ndarray, float, np.ndarray]:
    """Least squares of the rigid terms and the harmonics ``hs``: solution, residual (1
    sigma per coordinate), harmonic design matrix."""
    H = _harmonic_columns(ar, hs)
    A = np.hstack([R, H])
    sol, *_ = np.linalg.lstsq(A, y, rcond=1e-10)
    resid = y - A @ sol
    dof = max(len(y) - np.linalg.matrix_rank(A), 1)
    return sol, math.sqrt(float(resid @ resid) / dof), H


def fit_runout(angles_deg: np.ndarray, centres_px: np.ndarray, pixel_size_mm: float, *,
               sign: int = 1, harmonics: tuple[int, ...] = DEFAULT_HARMONICS,
               min_chi2: float = 20.0) -> RunoutMap:
    """The error-motion map from a wide sweep of one tracked point (the holder's centre).

    ``angles_deg`` are the turntable's read-back angles, ``centres_px`` (n, 2) the point in
    the top image (NaN rows are skipped), ``pixel_size_mm`` the image scale at the point's
    plane, ``sign`` the turning sense in the image (+1: the design notes' convention).
    Harmonics the sweep cannot resolve (more unknowns than half the points) are dropped;
    over a wide sweep so are those the data do not show (chi-square of the harmonic's four
    coefficients below ``min_chi2``; 20 is p = 5e-4 for pure noise).
    """
    a = np.asarray(angles_deg, float)
    z = np.asarray(centres_px, float)
    if z.shape != (len(a), 2):
        raise SolveError(f"fit_runout: expected (n, 2) centres for {len(a)} angles, got "
                         f"{z.shape}")
    if sign not in (1, -1):
        raise SolveError(f"fit_runout: sign must be +1 or -1, got {sign}")
    ok = np.all(np.isfinite(z), axis=1) & np.isfinite(a)
    a, z = a[ok], z[ok] * pixel_size_mm
    order = np.argsort(a)
    a, z = a[order], z[order]
    keep = np.concatenate([[True], np.diff(a) > 1e-9])  # one sample per angle
    a, z = a[keep], z[keep]
    n = len(a)
    if n < 8:
        raise SolveError(f"fit_runout: {n} usable frames; a runout map needs at least 8")
    span = float(a[-1] - a[0])
    if span < 30.0:
        raise SolveError(f"fit_runout: the sweep spans {span:.1f} deg; a runout map needs a "
                         "wide sweep (commission.sweep_deg, ideally a full turn)")
    hs = tuple(k for k in harmonics if k >= 2)
    while hs and 4 + 4 * len(hs) > n:  # 2n equations; keep the fit over-determined x2
        hs = hs[:-1]
    ar = np.radians(a)
    R = _rigid_columns(ar, sign)
    y = z.reshape(-1)
    sol, residual_mm, H = _solve(R, ar, hs, y)
    if span >= WELL_SEPARATED_DEG and hs:
        # keep the harmonics the data show (chi-square of their 4 coefficients): a noise
        # harmonic would be subtracted from every later sweep as if it were the bearing's
        A = np.hstack([R, H])
        cov = residual_mm ** 2 * np.linalg.pinv(A.T @ A)
        kept = []
        for i, k in enumerate(hs):
            sl = slice(4 + 4 * i, 8 + 4 * i)
            c = sol[sl]
            chi2 = float(c @ np.linalg.pinv(cov[sl, sl]) @ c)
            if chi2 > min_chi2:
                kept.append(k)
        if tuple(kept) != hs:
            hs = tuple(kept)
            sol, residual_mm, H = _solve(R, ar, hs, y)
    w = H @ sol[4:] if H.shape[1] else np.zeros_like(y)
    if span < WELL_SEPARATED_DEG:
        # a short sweep cannot tell the harmonics from the axis and the arm: the map is
        # what a rigid fit over this range leaves (what would bias a centre fit on it)
        coef, *_ = np.linalg.lstsq(R, w, rcond=None)
        w = w - R @ coef
    return RunoutMap(a, w.reshape(-1, 2), residual_mm * 1000.0)
