"""A long, near-vertical straight edge fitted as a blurred step: every row at once.

The area method (:mod:`alignd.vision.edges`) needs its window's tails clear of the blur; on
a narrow pole and a defocused image (sigma 1.5 px) they are not, and its bias then follows
the edge's sub-pixel phase, which a near-vertical edge sweeps slowly along its length: that
turns into an angle error of hundredths of a degree. Here the edge is a model instead,

    P(x, y) = alpha_y + beta_y u + (gamma_y + delta_y u) F(u; s),   u = x - (a + b (y - y_m)),

with F the pixel-area integral of a Gaussian-blurred unit step of width s. alpha..delta
(levels, illumination slopes on either side; free per row, so a lighting gradient, vignetting
or a shadow along the edge is followed) enter linearly and are projected out row by row
(variable projection); only the line (a, b) and the blur s are fitted nonlinearly. The
estimate weights each pixel by how much it says about the edge's position (a matched
filter), so it is also less noisy than the area sum. Rows whose profile is not a step
(a crossing edge, a hard shadow, a speck) are rejected by their residual.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.special import ndtr

from alignd.vision.edges import Line

__all__ = ["Highlight", "ProfileFit", "Spread", "fit_vertical_edge", "line_basis", "solve_rows",
           "step_basis", "window_profile"]

_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
# one JPEG block row: the unit of the per-band error terms (side.py merges them further)
BAND_ROWS = 8


@dataclass(frozen=True)
class Highlight:
    """A bright or dark line along an edge, fitted with it: a polished rod's highlight
    beside its silhouette's edge. Left out of the model it pulled the edge's angle
    0.15 deg. Its offset from the edge (px, + toward +x), width (px) and median strength."""

    offset_px: float
    width_px: float
    strength: float  # DN px: its profile's integral across it


@dataclass(frozen=True)
class ProfileFit:
    """x = a + b (y - y_mid) with its covariance; the blur; the rows used."""

    a: float
    b: float
    y_mid: float
    cov_ab: np.ndarray  # of (a, b) as defined above (centred)
    blur_px: float
    rms_dn: float
    rows: np.ndarray  # the rows used
    contrast: float  # median right minus left level (DN)
    spread: Spread = "optics"
    # the bands of BAND_ROWS rows (row // BAND_ROWS) used and each band's share of the
    # angle's error (deg): terms whose sum of squares is a cluster-robust variance. Frames
    # of one view coded on the same block grid repeat part of their coding error; summing
    # these per band over the frames before squaring keeps that part from averaging away
    # (see :func:`alignd.vision.side.measure_tilt_frames`)
    bands: np.ndarray | None = None
    band_angle_deg: np.ndarray | None = None
    highlight: Highlight | None = None  # a line fitted along the edge, if any

    @property
    def angle_deg(self) -> float:
        """From the image vertical, positive when the top leans toward +x."""
        return math.degrees(math.atan(-self.b))

    @property
    def sigma_deg(self) -> float:
        return math.degrees(math.sqrt(max(float(self.cov_ab[1, 1]), 0.0)) / (1 + self.b ** 2))

    def line(self) -> Line:
        """As a :class:`Line` (x = a' + b y, un-centred) for the code that takes one."""
        a0 = self.a - self.b * self.y_mid
        T = np.array([[1.0, -self.y_mid], [0.0, 1.0]])
        nv = np.array([1.0, -self.b])
        norm = float(np.hypot(*nv))
        return Line(n=nv / norm, d=a0 / norm, rms_px=0.0, n_points=int(self.rows.size),
                    n_used=int(self.rows.size), cov_ab=T @ self.cov_ab @ T.T, vertical=True,
                    major_span=(float(self.rows.min()), float(self.rows.max())),
                    contrast=self.contrast)


Spread = Literal["optics", "disc", "pixel grid"]
_K = np.arange(-8, 9, dtype=np.float64)  # taps of a blur on the pixel grid (4 sigma at 2 px)


def step_basis(u: np.ndarray, s: float, spread: Spread = "optics"
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The step profile F (minus 1/2) at offset u, dF/du, dF/ds, and the per-row basis
    [1, u, F, u F] (N, W, 4).

    "optics": a Gaussian blur of width s before the pixels integrate (a lens); "disc": a
    uniform disc of radius s before they integrate (a lens out of focus: its edge ends
    abruptly a radius out, where a Gaussian's tails go on); "pixel grid": the
    pixel-integrated step blurred by a sampled Gaussian kernel afterwards (a filter in the
    camera's processing, or a renderer), whose shape depends on the sub-pixel phase.

    A lens's step is s times the difference of its blurred step's antiderivative A over
    the pixel's width: F = s (A(t+) - A(t-)) - 1/2 at t = (u +- 1/2) / s, so dF/du =
    A'(t+) - A'(t-) and dF/ds = (A - t A')(t+) - (A - t A')(t-).
    """
    if spread == "optics":
        tp, tm = (u + 0.5) / s, (u - 0.5) / s
        cp, cm = ndtr(tp), ndtr(tm)
        pp, pm = _INV_SQRT_2PI * np.exp(-0.5 * tp * tp), _INV_SQRT_2PI * np.exp(-0.5 * tm * tm)
        F = s * (tp * cp + pp - tm * cm - pm) - 0.5  # (A = t Phi(t) + phi(t))
        dFu, dFs = cp - cm, pp - pm
    elif spread == "disc":
        (ap, ep, bp), (am, em, bm) = _disc_step((u + 0.5) / s), _disc_step((u - 0.5) / s)
        F = s * (ap - am) - 0.5
        dFu, dFs = ep - em, bp - bm
    else:
        e = np.exp(-0.5 * (_K / s) ** 2)
        de = e * _K ** 2 / s ** 3
        g = e / e.sum()
        dg = (de - g * de.sum()) / e.sum()
        t = u[..., None] - _K + 0.5  # (N, W, K)
        ramp = np.clip(t, 0.0, 1.0)
        F = ramp @ g - 0.5
        dFu = ((t > 0.0) & (t < 1.0)).astype(np.float64) @ g
        dFs = ramp @ dg
    B = np.stack([np.ones_like(u), u, F, u * F], axis=2)
    return F, dFu, dFs, B


def _disc_step(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A disc-blurred unit step at ``t`` radii from the edge (the share of the disc beyond
    a chord there, E = 1/2 + (t sqrt(1 - t^2) + asin t) / pi), its antiderivative A and
    A - t E (:func:`step_basis`): A = t / 2 + (t asin t + sqrt(1 - t^2) - (1 - t^2)^(3/2)
    / 3) / pi within the disc, 0 before it and t beyond."""
    z = np.clip(t, -1.0, 1.0)
    root = np.sqrt(1.0 - z * z)
    asin = np.arcsin(z)
    E = 0.5 + (z * root + asin) / math.pi
    A = 0.5 * z + (z * asin + root - root ** 3 / 3.0) / math.pi + np.maximum(t - 1.0, 0.0)
    return A, E, A - t * E


def solve_rows(B: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Per-row least squares: coefficients (N, C, K) of Y (N, W, K) on B (N, W, C)
    (batched matrix products: einsum's generic loop was most of the side camera's time)."""
    Bt = B.transpose(0, 2, 1)
    return np.linalg.solve(Bt @ B + 1e-9 * np.eye(B.shape[2]), Bt @ Y)


class _OffTheWindows(Exception):
    """The edge fit left its windows: there is no step there to fit."""


def line_basis(u: np.ndarray, d: float | np.ndarray, w: float | np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A line along the edge at offset ``d`` from it, a Gaussian of width ``w`` integrated
    over each pixel: its profile G at offset u from the edge, dG/du and dG/dw
    (dG/dd = -dG/du)."""
    tp, tm = (u - d + 0.5) / w, (u - d - 0.5) / w
    pp, pm = _INV_SQRT_2PI * np.exp(-0.5 * tp * tp), _INV_SQRT_2PI * np.exp(-0.5 * tm * tm)
    return ndtr(tp) - ndtr(tm), (pp - pm) / w, -(tp * pp - tm * pm) / w


def _gauss_newton(P: np.ndarray, cols: np.ndarray, yc: np.ndarray, p: np.ndarray,
                  spread: Spread, iterations: int = 12
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Variable projection (Kaufman's Jacobian) for (a, b, s), and (d, w) of a line along
    the edge where ``p`` has them; returns p, residuals (N, W), the per-row coefficients
    (N, 4 or 5) and J^T J. Raises _OffTheWindows when the line leaves a row's window."""
    k = p.size
    JtJ = np.eye(k)
    r = np.zeros_like(P)
    c = np.zeros((P.shape[0], 4 if k == 3 else 5))
    half = cols.shape[1] / 2
    for it in range(iterations + 1):  # the last pass only evaluates J at the solution
        p, r, c, D = _jacobian_at(P, cols, yc, p, spread)
        J = D.reshape(-1, k)  # r = P - model: dr/dp = -D, the step solves D dp = r
        JtJ = J.T @ J
        if it == iterations:
            break
        step = np.linalg.solve(JtJ + 1e-12 * np.eye(k), J.T @ r.ravel())
        p = p + step
        p[2] = float(np.clip(p[2], 0.2, 5.0))
        if k == 5:  # the line stays inside the window, no sharper than a pixel's blur
            p[3] = float(np.clip(p[3], -half, half))
            p[4] = float(np.clip(p[4], 0.3, 3.0))
        if not np.all(np.abs(p[0] + p[1] * yc - cols.mean(axis=1)) <= half):
            raise _OffTheWindows  # (NaN fails the test too)
        if abs(step[0]) < 1e-5 and abs(step[1]) < 1e-8 and abs(step[2]) < 1e-4 and (
                k == 3 or abs(step[3]) < 1e-4):
            break
    return p, r, c, JtJ


def fit_vertical_edge(gray: np.ndarray, a0: float, b0: float, y_mid: float,
                      rows: np.ndarray, *, half_width: int = 7, blur0: float = 1.0,
                      x_limits: tuple[int, int] | None = None, min_rows: int = 20,
                      spread: Spread = "optics",
                      clip_levels: tuple[float, float] | None = (0.0, 255.0),
                      line: Highlight | bool | None = None) -> ProfileFit | None:
    """Fit the edge near x = a0 + b0 (y - y_mid) over ``rows`` (the start to about a pixel).

    ``line``: a line along the edge (:class:`Highlight`) is looked for where the plain step
    fits badly (None), never (False), or fitted from the one given, else the plain step (a
    later frame of the same view: the model stays the view's, since frames that took it
    and frames that did not scattered a pre-check's tilt).

    Windows of 2 * half_width + 1 px, fixed by the start line, stay inside ``x_limits``
    (x0, x1 exclusive; default the image). ``spread``: how the blur arises (see
    :func:`step_basis`). ``clip_levels``: the sensor's black and full-scale levels in ``gray``'s
    units (:func:`alignd.vision.edges.as_gray` scales every bit depth to 0-255): rows whose
    step comes within 3 noise sigma of either are left out, since clipping flattens one side
    of the profile and the noise no longer averages out there (a saturated sample under a
    vertical light gradient leaned its edge by 0.01 deg). None when too few rows remain.

    The standard error treats each band of 8 image rows as one unit (a cluster-robust
    sandwich): JPEG/MJPEG codes 8 x 8 blocks, so the rows of a block share their coding
    error and are not independent samples of the edge. None, too, when the fit runs out of
    its windows (a profile that is no step there: a shiny pole's highlight beside its
    edge drove the line thousands of pixels off, until the per-row solve was singular).
    """
    def fitted(start: _LineStart | None) -> ProfileFit | None:
        try:
            return _fit_vertical_edge(gray, a0, b0, y_mid, rows, half_width, blur0, x_limits,
                                      min_rows, spread, clip_levels, start)
        except _OffTheWindows:
            return None

    if isinstance(line, Highlight):
        kept = fitted(_LineStart(0.0, line.offset_px, line.width_px, blur0))
        if kept is not None and kept.highlight is not None:
            return kept
    plain = fitted(None)
    if line is False or isinstance(line, Highlight):
        return plain
    if plain is not None and (
            plain.rms_dn <= LINE_TRIGGER * _row_noise(gray, a0, b0, y_mid, rows, half_width)):
        return plain
    mean = window_profile(gray, a0, b0, y_mid, rows, half_width, x_limits)
    if mean is None:
        return plain
    prof, frac = mean
    rise = float(prof[-1] - prof[0])  # how the window's mean profile rises end to end
    if plain is not None and _bump(gray, plain, half_width) <= LINE_BUMP * abs(rise):
        return plain
    best = plain
    for start in _line_starts(prof, frac, half_width):
        f = fitted(start)
        # the step rises or falls as the window does from end to end: a step the other way
        # with a steep slope beside it fitted a narrow rod's edge and highlight as well
        if f is None or f.contrast * rise <= 0 or f.highlight is None or (
                abs(f.highlight.offset_px) < LINE_MIN_OFFSET_PX):
            continue
        if best is None or f.rms_dn < best.rms_dn:
            best = f
    if best is None or best.highlight is None or (
            plain is not None and best.rms_dn > LINE_GAIN * plain.rms_dn):
        return plain
    return best


# a line along the edge (a highlight on a polished rod) is looked for where the plain
# step's residual exceeds this many times the frame's noise beside the edge, and kept where
# it brings the residual under LINE_GAIN of the plain step's
LINE_TRIGGER = 2.0
LINE_GAIN = 0.5
# and where the plain step's mean residual, beside the edge, peaks over this share of the
# step across the window (a blur the model draws differently leaves its residual at the
# edge itself; the plain step's own contrast takes in part of the line)
LINE_BUMP = 0.05
# nor nearer the edge than this (px): there it reshapes the edge's blur instead (a line
# 0.6 px from a sample's edge moved the edge 1 px)
LINE_MIN_OFFSET_PX = 1.5


@dataclass(frozen=True)
class _LineStart:
    """Where a fit of the edge with a line along it starts: the edge's shift from the
    start line (px), the line's offset from the edge and width, the blur (px)."""

    shift: float
    offset: float
    width: float
    blur: float


def window_profile(gray: np.ndarray, a0: float, b0: float, y_mid: float, rows: np.ndarray,
                   half_width: int, x_limits: tuple[int, int] | None = None
                   ) -> tuple[np.ndarray, float] | None:
    """The mean over ``rows`` of the windows a fit of the edge near x = a0 + b0 (y - y_mid)
    reads, and the line's mean offset from the windows' centre pixels (px); None with
    fewer than 8 rows inside the image (``x_limits``)."""
    rows, start = _windows(gray, a0, b0, y_mid, rows, half_width, x_limits)
    if rows.size < 8:
        return None
    prof = gray[rows[:, None], start[:, None] + np.arange(2 * half_width + 1)].astype(
        np.float64).mean(axis=0)
    return prof, float(np.mean(a0 + b0 * (rows - y_mid) - (start + half_width)))


def _windows(gray: np.ndarray, a0: float, b0: float, y_mid: float, rows: np.ndarray,
             half_width: int, x_limits: tuple[int, int] | None
             ) -> tuple[np.ndarray, np.ndarray]:
    """The rows (inside the image) whose window of 2 half_width + 1 px round the line
    x = a0 + b0 (y - y_mid) lies inside ``x_limits`` (default the image), and each
    window's first column."""
    h, w = gray.shape
    lo, hi = x_limits if x_limits is not None else (0, w)
    rows = np.asarray(rows, int)
    rows = rows[(rows >= 0) & (rows < h)]
    start = np.round(a0 + b0 * (rows - y_mid)).astype(int) - half_width
    ok = (start >= lo) & (start + 2 * half_width + 1 <= hi)
    return rows[ok], start[ok]


def _line_starts(prof: np.ndarray, frac: float, half_width: int, keep: int = 3
                 ) -> list[_LineStart]:
    """The ``keep`` best starts, with edges a pixel apart or more, for a step with a line
    beside it, on a grid over the windows' mean profile ``prof`` (:func:`window_profile`,
    the start line ``frac`` px off the windows' centres). The fit from a fixed start near
    the line's flank settled on the flank (a step the wrong way with a dark line beside
    it); the grid sees every arrangement of the step and the line at once."""
    m = prof.size
    k = np.arange(m) - half_width - frac
    grid = [(t, d, wd, sb)
            for t in np.arange(-half_width + 1.5, half_width - 1.5 + 1e-9, 0.5)
            for d in np.arange(-half_width + 0.5, half_width - 0.5 + 1e-9, 0.5)
            if abs(d) >= 1.0 and abs(t + d) <= half_width
            for wd in (0.7, 1.3, 2.2) for sb in (0.7, 1.4)]
    if not grid:
        return []
    g = np.array(grid)
    u = k[None, :] - g[:, 0:1]  # (G, m): offset from the step
    rss = np.empty(len(grid))
    for sb in (0.7, 1.4):
        sel = g[:, 3] == sb
        G = line_basis(u[sel], g[sel, 1:2], g[sel, 2:3])[0]
        B = np.concatenate([step_basis(u[sel], sb)[3], G[..., None]], axis=2)
        coef = solve_rows(B, np.broadcast_to(prof, (B.shape[0], m))[..., None])
        rss[sel] = np.sum(((B @ coef)[..., 0] - prof) ** 2, axis=1)
    out: list[_LineStart] = []
    for j in np.argsort(rss):
        t, d, wd, sb = grid[int(j)]
        if all(abs(t - o.shift) >= 1.0 for o in out):
            out.append(_LineStart(float(t), float(d), float(wd), float(sb)))
        if len(out) == keep:
            break
    return out


def _bump(gray: np.ndarray, fit: ProfileFit, half_width: int) -> float:
    """The largest mean residual (DN, absolute) of ``fit`` over its rows, in half-pixel
    bins of the offset from the edge LINE_MIN_OFFSET_PX or more away: what a line beside
    the edge leaves."""
    yc = (fit.rows - fit.y_mid).astype(np.float64)
    centre = fit.a + fit.b * yc
    cols = np.round(centre).astype(int)[:, None] + np.arange(-half_width, half_width + 1)
    cols = np.clip(cols, 0, gray.shape[1] - 1)
    P = gray[fit.rows[:, None], cols].astype(np.float64)
    u = cols - centre[:, None]
    B = step_basis(u, fit.blur_px, fit.spread)[3]
    r = P - (B @ solve_rows(B, P[..., None]))[..., 0]
    side = np.abs(u) >= LINE_MIN_OFFSET_PX
    if not side.any():
        return 0.0
    k = np.round(u[side] * 2).astype(int)
    k -= k.min()
    n = np.bincount(k)
    mean = np.bincount(k, r[side]) / np.maximum(n, 1)
    return float(np.max(np.abs(mean[n >= 8]), initial=0.0))


def _row_noise(gray: np.ndarray, a0: float, b0: float, y_mid: float, rows: np.ndarray,
               half_width: int) -> float:
    """The frame's noise in the edge's windows (DN), from differences between adjacent
    rows: a near-vertical edge barely moves from one row to the next, the noise does."""
    h, w = gray.shape
    rows = np.asarray(rows, int)
    rows = rows[(rows >= 0) & (rows < h - 1)]
    x = np.clip(np.round(a0 + b0 * (rows - y_mid)).astype(int), half_width, w - 1 - half_width)
    cols = x[:, None] + np.arange(-half_width, half_width + 1)[None, :]
    d = gray[rows[:, None] + 1, cols].astype(np.float64) - gray[rows[:, None], cols]
    if d.size == 0:
        return 0.0
    # the mean absolute deviation, not the median's: integer levels make the median's
    # a whole number of DN (1 DN read 1.05 for 1.5 DN of noise)
    dev = np.abs(d - np.median(d))
    dev = dev[dev <= 4.0 * max(float(np.mean(dev)), 0.5)]  # not the rows an edge crosses
    return float(np.mean(dev)) * math.sqrt(math.pi / 2) / math.sqrt(2.0)


def _basis(u: np.ndarray, p: np.ndarray, spread: Spread) -> np.ndarray:
    """The per-row basis at offset u for the nonlinear parameters ``p`` (a, b, s[, d, w])."""
    B = step_basis(u, p[2], spread)[3]
    if p.size == 5:
        B = np.concatenate([B, line_basis(u, p[3], p[4])[0][..., None]], axis=2)
    return B


def _fit_vertical_edge(gray: np.ndarray, a0: float, b0: float, y_mid: float,
                       rows: np.ndarray, half_width: int, blur0: float,
                       x_limits: tuple[int, int] | None, min_rows: int, spread: Spread,
                       clip_levels: tuple[float, float] | None,
                       line_start: _LineStart | None = None) -> ProfileFit | None:
    rows, start = _windows(gray, a0, b0, y_mid, rows, half_width, x_limits)
    m = 2 * half_width + 1
    if rows.size < min_rows:
        return None
    cols = start[:, None] + np.arange(m)[None, :]
    P = gray[rows[:, None], cols].astype(np.float64)
    yc = (rows - y_mid).astype(np.float64)
    use = np.ones(rows.size, bool)
    if clip_levels is not None:  # start from the rows without a clipped pixel
        unclipped = ((clip_levels[0] + 0.5 < P) & (clip_levels[1] - 0.5 > P)).all(axis=1)
        if unclipped.sum() >= min_rows:
            use = unclipped
    ls = line_start
    x = np.array([a0, b0, blur0] if ls is None else
                 [a0 + ls.shift, b0, ls.blur, ls.offset, ls.width])
    r_all = np.zeros_like(P)
    coef = np.zeros((rows.size, 4))
    for _ in range(4):
        x, _r, _c, _JtJ = _gauss_newton(P[use], cols[use], yc[use], x, spread)
        B = _basis(cols - (x[0] + x[1] * yc)[:, None], x, spread)
        coef = solve_rows(B, P[..., None])[..., 0]
        model = (B @ coef[..., None])[..., 0]
        r_all = P - model
        res_rows = np.sqrt(np.mean(r_all ** 2, axis=1))
        med = float(np.median(res_rows[use]))
        mad = float(np.median(np.abs(res_rows[use] - med))) * 1.4826
        gam = coef[:, 2]
        gmed = float(np.median(gam[use]))
        new = (res_rows <= med + 4.0 * mad + 1e-9) & (np.sign(gam) == np.sign(gmed)) & (
            np.abs(gam) >= 0.5 * abs(gmed))
        if clip_levels is not None:  # the fitted (noise-free) profile, not the noisy pixels
            margin = 0.5 + 3.0 * med
            new &= (model.min(axis=1) > clip_levels[0] + margin) & (
                model.max(axis=1) < clip_levels[1] - margin)
        if new.sum() < min_rows:
            return None
        if np.array_equal(new, use):
            break
        use = new
    else:
        x, _r, _c, _JtJ = _gauss_newton(P[use], cols[use], yc[use], x, spread)
    x, r, _c, J = _jacobian_at(P[use], cols[use], yc[use], x, spread)
    n_use = int(use.sum())
    dof = max(n_use * m - x.size - _c.shape[1] * n_use, 1)
    s2 = float(np.sum(r ** 2)) / dof
    cov = _cluster_cov(J, r, rows[use] // 8, n_use * m, dof)[:2, :2]
    bands, infl = _band_influence(J, r, rows[use] // BAND_ROWS, n_use * m, dof)
    band_deg = -np.degrees(infl[:, 1]) / (1 + x[1] ** 2)  # angle = atan(-b)
    return ProfileFit(a=float(x[0]), b=float(x[1]), y_mid=y_mid, cov_ab=cov,
                      blur_px=float(x[2]), rms_dn=math.sqrt(s2), rows=rows[use],
                      contrast=float(np.median(coef[use, 2])), spread=spread,
                      bands=bands, band_angle_deg=band_deg,
                      highlight=None if x.size == 3 else Highlight(
                          float(x[3]), float(x[4]), float(np.median(coef[use, 4]))))


def _band_influence(D: np.ndarray, r: np.ndarray, cluster: np.ndarray, n_obs: int,
                    dof: int) -> tuple[np.ndarray, np.ndarray]:
    """Each cluster's term (J^T J)^-1 s_g sqrt(n / dof) of the parameters (a, b, s): the
    sandwich of :func:`_cluster_cov` is the sum of their outer products."""
    k = D.shape[2]
    J = D.reshape(-1, k)
    JtJi = np.linalg.inv(J.T @ J + 1e-12 * np.eye(k))
    scores = np.einsum("nwk,nw->nk", D, r)
    ids, inv = np.unique(cluster, return_inverse=True)
    g = np.zeros((ids.size, k))
    np.add.at(g, inv, scores)
    return ids, g @ JtJi * math.sqrt(n_obs / dof)


def _jacobian_at(P: np.ndarray, cols: np.ndarray, yc: np.ndarray, p: np.ndarray,
                 spread: Spread) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residuals (N, W), the per-row coefficients (N, 4 or 5) and the projected Jacobian
    (N, W, 3 or 5) of the model B c with respect to a, b, s (and d, w of a line along the
    edge) (c held) at ``p`` (no step taken)."""
    u = cols - (p[0] + p[1] * yc)[:, None]
    F, dFu, dFs, B = step_basis(u, p[2], spread)
    if p.size == 5:
        G, dGu, dGw = line_basis(u, p[3], p[4])
        B = np.concatenate([B, G[..., None]], axis=2)
    c = solve_rows(B, P[..., None])[..., 0]
    r = P - (B @ c[..., None])[..., 0]
    da = -(c[:, 1:2] + c[:, 2:3] * dFu + c[:, 3:4] * (F + u * dFu))
    ds = (c[:, 2:3] + c[:, 3:4] * u) * dFs
    if p.size == 5:
        da = da - c[:, 4:5] * dGu
        D = np.stack([da, da * yc[:, None], ds, -c[:, 4:5] * dGu, c[:, 4:5] * dGw], axis=2)
    else:
        D = np.stack([da, da * yc[:, None], ds], axis=2)
    D = D - B @ solve_rows(B, D)
    return p, r, c, D


def _cluster_cov(D: np.ndarray, r: np.ndarray, cluster: np.ndarray, n_obs: int,
                 dof: int) -> np.ndarray:
    """Covariance of (a, b, s): the sandwich (J^T J)^-1 (sum_g s_g s_g^T) (J^T J)^-1 with
    s_g the score J^T r of each cluster g of rows, scaled by n / dof; never below the
    ordinary (independent pixels) covariance."""
    k = D.shape[2]
    J = D.reshape(-1, k)
    JtJi = np.linalg.inv(J.T @ J + 1e-12 * np.eye(k))
    s2 = float(np.sum(r ** 2)) / dof
    plain = s2 * JtJi
    scores = np.einsum("nwk,nw->nk", D, r)  # per row
    _, inv = np.unique(cluster, return_inverse=True)
    g = np.zeros((int(inv.max()) + 1, k))
    np.add.at(g, inv, scores)
    meat = g.T @ g * (n_obs / dof)
    sand = JtJi @ meat @ JtJi
    return sand if sand[1, 1] > plain[1, 1] else plain
