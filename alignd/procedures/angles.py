"""The turntable's angle as the images see it, against what the controller reads back.

The solver assumes the design notes' convention: turning by +a turns the image by R(a).
A turntable wired the other way round, a mirrored camera, or a wrong gear ratio in the
stage's scale break that silently (the centre comes out wrong, the loop "does not converge").
The holder's own edges show how far the image turned: the slope of the image angle against
the read-back angle is +1 on a rig that matches the convention, -1 on a reversed one, and its
distance from +-1 is the angle-scale error. Every sweep checks it; commissioning measures it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from alignd.errors import ConfigError
from alignd.procedures.holder_geometry import turned


@dataclass(frozen=True)
class AngleMap:
    """How read-back angles become image angles:
    ``image = sign * (scale * readback + error(readback))``, where ``error`` is the encoder's
    periodic error, a sum of harmonics (h, cos and sin amplitudes in degrees) measured by
    commissioning (none from the config)."""

    sign: int = 1
    scale: float = 1.0
    source: str = "config"  # "config" or "commission <run id>"
    error: tuple[tuple[int, float, float], ...] = ()

    def error_deg(self, readback_deg: np.ndarray | list[float]) -> np.ndarray:
        a = np.radians(np.asarray(readback_deg, float))
        out = np.zeros_like(a)
        for h, c, d in self.error:
            out += c * np.cos(h * a) + d * np.sin(h * a)
        return out

    def image_angles(self, readback_deg: np.ndarray | list[float]) -> np.ndarray:
        rb = np.asarray(readback_deg, float)
        return self.sign * (self.scale * rb + self.error_deg(rb))


@dataclass(frozen=True)
class AngleErrorFit:
    """Image angle against read-back over a wide sweep: scale and periodic error."""

    scale: float
    scale_sigma: float
    error: tuple[tuple[int, float, float], ...]  # significant harmonics only
    peak_deg: float  # largest periodic error over the swept angles
    sigma_deg: float  # per-frame residual


def fit_angle_error(readback_deg: np.ndarray, image_deg: np.ndarray, sign: int,
                    harmonics: tuple[int, ...] = (2, 3, 4), min_snr: float = 3.0
                    ) -> AngleErrorFit:
    """``sign * image = b + scale * a + sum_h (c_h cos ha + d_h sin ha)`` by least squares;
    a harmonic is kept when its amplitude exceeds ``min_snr`` times its uncertainty (an
    insignificant one would add its noise to every later sweep). The first harmonic is not
    fitted: on a sweep short of a full turn it trades off against the scale, and a tilted
    camera's perspective turns the holder's edges by a first harmonic of its own."""
    a = np.asarray(readback_deg, float)
    y = sign * np.asarray(image_deg, float)
    ok = np.isfinite(a) & np.isfinite(y)
    a, y = a[ok], y[ok]
    ar = np.radians(a)
    cols = [np.ones_like(a), a - a.mean()]
    for h in harmonics:
        cols += [np.cos(h * ar), np.sin(h * ar)]
    A = np.column_stack(cols)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    res = y - A @ coef
    dof = max(len(y) - A.shape[1], 1)
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.pinv(A.T @ A)
    kept = []
    for i, h in enumerate(harmonics):
        c, d = float(coef[2 + 2 * i]), float(coef[3 + 2 * i])
        sig = math.sqrt(max(cov[2 + 2 * i, 2 + 2 * i] + cov[3 + 2 * i, 3 + 2 * i], 0.0) / 2)
        if math.hypot(c, d) > min_snr * max(sig, 1e-12):
            kept.append((h, c, d))
    amap = AngleMap(1, 1.0, "fit", tuple(kept))
    grid = np.linspace(a.min(), a.max(), 721)
    peak = float(np.abs(amap.error_deg(grid)).max()) if kept else 0.0
    return AngleErrorFit(float(coef[1]), math.sqrt(max(cov[1, 1], 0.0)), tuple(kept), peak,
                         math.sqrt(s2))


@dataclass(frozen=True)
class AngleSlope:
    """Fitted d(image angle)/d(read-back angle) with its 1-sigma uncertainty."""

    slope: float
    sigma: float
    n: int
    rms_deg: float

    @property
    def sign(self) -> int:
        return 1 if self.slope > 0 else -1

    @property
    def scale(self) -> float:
        return abs(self.slope)


def holder_image_angles(points: np.ndarray) -> np.ndarray:
    """Direction (deg) of the holder's edges in each frame, unwrapped along the frames.

    ``points`` (n, 4, 2): corners in any cyclic order. The direction of corner 0 -> 1 is
    taken modulo 90 deg (a tracker may start its corner order at another corner when the
    holder turns far), then unwrapped: consecutive frames must differ by less than 45 deg.
    NaN where a frame was not tracked.
    """
    p = np.asarray(points, float)
    u = ((p[:, 1] - p[:, 0]) + (p[:, 2] - p[:, 3])) / 2
    raw = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
    out = np.full(len(p), np.nan)
    prev = None
    for i, a in enumerate(raw):
        if not np.isfinite(a):
            continue
        if prev is None:
            out[i] = a
        else:
            out[i] = a + 90.0 * round((prev - a) / 90.0)
        prev = out[i]
    return out


def nearest_order(corners: np.ndarray, prev: np.ndarray) -> np.ndarray:
    """``corners`` (4, 2, in cyclic order) rolled to the cyclic order nearest ``prev``."""
    c = np.asarray(corners, float)
    costs = [float(np.linalg.norm(np.roll(c, -k, axis=0) - prev, axis=1).sum())
             for k in range(4)]
    return np.roll(c, -int(np.argmin(costs)), axis=0)


# Within this angle (deg) of turning its diagonal level in the image (a corner straight
# left of the centre), where the image's corner order changes, a holder's order comes from
# holder.size_mm: what its noise would otherwise decide, frame by frame
NEAR_DIAGONAL_DEG = 5.0
# sides within this fraction of each other: a square holder, whose sides cannot tell u from v
SQUARE_WITHIN = 0.05


@dataclass(frozen=True)
class ReferenceOrder:
    """The reference frame's corners in the holder frame's order; ``swapped``: the image's
    order has u and v the other way round from holder.size_mm, clear of the diagonal (the
    config's lengths are in the other order: docs/configure.md)."""

    corners: np.ndarray
    swapped: bool
    u_px: float  # the length of the image's u side (corner 0 -> 1) and v side, px
    v_px: float
    # swapped: the config's frame is the image's turned by this many corners (1 or 3), its u
    # pointing right (as it did before the holder turned past its diagonal)
    turn: int = 0
    # a square holder near its diagonal: no numbering can be told from the noise's
    ambiguous: bool = False

    def image_target_mm(self, target_mm: tuple[float, float]) -> tuple[float, float]:
        """``target_mm`` of the config's frame in the image's (``swapped``: the holder.
        target_mm that names the same point with holder.size_mm in the image's order)."""
        return turned(target_mm, self.turn)


def reference_order(corners: np.ndarray, size_mm: tuple[float, float]) -> ReferenceOrder:
    """The corners (image order: corner 0 top-left, clockwise) of the frame that defines
    the holder frame (turntable 0) in the config's order.

    The image's order is the holder frame (docs/configure.md) unless the holder lies within
    NEAR_DIAGONAL_DEG of a corner straight left of its centre: there the order flips
    between two frames with noise alone (a 40 x 25 mm holder at 32 deg in the image), the
    target point then turning a quarter round the holder. Its order is then the one whose
    u side has the length holder.size_mm gives u, of the two its u pointing right.
    """
    c = np.asarray(corners, float)
    d = c - c.mean(axis=0)
    ang = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    near = float(min(ang.min() + 180.0, 180.0 - ang.max())) < NEAR_DIAGONAL_DEG

    def sides(p: np.ndarray) -> tuple[float, float]:
        u = ((p[1] - p[0]) + (p[2] - p[3])) / 2
        v = ((p[3] - p[0]) + (p[2] - p[1])) / 2
        return float(np.hypot(*u)), float(np.hypot(*v))

    su, sv = size_mm
    a, b = sides(c)
    square = abs(su - sv) <= SQUARE_WITHIN * max(su, sv)
    if square or (a >= b) == (su >= sv):
        return ReferenceOrder(c, False, a, b, ambiguous=square and near)
    # one corner on: u along the other pair of sides, the one of its two senses pointing
    # right (the image's own order just before the holder turned past its diagonal)
    k = max((1, 3), key=lambda k: float(((c[(k + 1) % 4] - c[k]) + (c[(k + 2) % 4]
                                                                    - c[(k + 3) % 4]))[0]))
    if not near:
        return ReferenceOrder(c, True, a, b, k)
    best = np.roll(c, -k, axis=0)
    return ReferenceOrder(best, False, *sides(best))


def holder_frame_order(points: np.ndarray, readback_deg: np.ndarray | list[float],
                       size_mm: tuple[float, float]) -> tuple[np.ndarray, ReferenceOrder | None]:
    """Every frame's corners in the holder frame's order: the tracked frame nearest
    turntable 0 by :func:`reference_order`, the others followed from it frame by frame
    (:func:`consistent_order`); and that frame's ReferenceOrder (None: nothing tracked)."""
    p = np.asarray(points, float)
    ok = np.flatnonzero(np.all(np.isfinite(p), axis=(1, 2)))
    if len(ok) == 0:
        return p, None
    ref = int(ok[np.argmin(np.abs(np.asarray(readback_deg, float)[ok]))])
    r = reference_order(p[ref], size_mm)
    p = p.copy()
    p[ref] = r.corners
    return consistent_order(p, ref), r


def consistent_order(points: np.ndarray, ref: int) -> np.ndarray:
    """The corners of every frame in the cyclic order of frame ``ref``, followed frame by
    frame outwards from it (a tracker restarts its order when the holder turns far; the
    holder frame of the config is the order at turntable 0). Steps between frames must
    move a corner less than half the holder's shorter side."""
    p = np.asarray(points, float).copy()
    n = len(p)
    for direction in (1, -1):
        prev = p[ref]
        i = ref + direction
        while 0 <= i < n:
            if np.all(np.isfinite(p[i])) and np.all(np.isfinite(prev)):
                p[i] = nearest_order(p[i], prev)
                prev = p[i]
            i += direction
    return p


def fit_slope(angles_deg: np.ndarray, image_deg: np.ndarray) -> AngleSlope:
    """Straight-line fit of the image angle against the (read-back) angle."""
    a = np.asarray(angles_deg, float)
    y = np.asarray(image_deg, float)
    ok = np.isfinite(a) & np.isfinite(y)
    a, y = a[ok], y[ok]
    n = len(a)
    if n < 3 or float(np.ptp(a)) <= 0:
        return AngleSlope(float("nan"), float("inf"), n, float("nan"))
    X = np.column_stack([np.ones(n), a - a.mean()])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    res = y - X @ coef
    s2 = float(res @ res) / max(n - 2, 1)
    # floor: the tracker's angle noise is never below ~1e-4 deg
    sigma = math.sqrt(max(s2, 1e-8) / float(((a - a.mean()) ** 2).sum()))
    return AngleSlope(float(coef[1]), sigma, n, math.sqrt(float(res @ res) / n))


# a sweep's slope may differ from the expected +1 by this much before the run stops
# (the encoder's periodic error and the tracker's noise stay far below it over +-10 deg)
SLOPE_TOLERANCE = 0.01


def check_sweep_angles(readback_deg: list[float], points: np.ndarray, amap: AngleMap,
                       kind: str) -> AngleSlope:
    """Stop (``ConfigError``) when the images turned otherwise than the angles say.

    With ``amap`` applied, the holder's image angle must follow the angle with slope +1.
    A slope near -1 is a reversed turntable (or a mirrored camera); one off by more than
    ``SLOPE_TOLERANCE`` (and 5 sigma) a wrong angle scale. Both name the fix.
    """
    fit = fit_slope(amap.image_angles(readback_deg), holder_image_angles(points))
    if not math.isfinite(fit.slope):
        return fit
    bound = SLOPE_TOLERANCE + 5 * fit.sigma
    if abs(fit.slope - 1.0) <= bound:
        return fit
    where = (f"the {kind} sweep turned the image by {fit.slope:+.4f} ± {fit.sigma:.4f} deg "
             f"per degree of the turntable's read-back (expected +1, using the {amap.source}"
             f" direction {amap.sign:+d} and scale {amap.scale:.5g})")
    if abs(fit.slope + 1.0) <= bound:
        raise ConfigError(
            f"turntable reversed: {where}. The turntable turns the other way round in the "
            "image (or the top camera is mirrored). Fix: run `alignctl commission` (it "
            "measures and records the direction), or set procedure.turntable_direction: "
            f"{-amap.sign:+d} in the config; no stage was moved on this sweep's data")
    raise ConfigError(
        f"turntable angle scale wrong: {where}. The controller's degrees are not the "
        f"table's (a scale error of {(fit.scale - 1) * 100:+.2f} %: wrong stage model or "
        "gear ratio). Fix: correct the turntable axis' `stage` in the config, or run "
        "`alignctl commission` to measure and record the scale; no stage was moved on "
        "this sweep's data")
