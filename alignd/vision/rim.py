"""Turntable rim: ellipse fit, perceived eccentricity, camera zenith, plane rectification.

Geometry (the thesis' eq. 3.7, whose text lost its equations, re-derived for a pinhole):
a circle of radius R lies in the turntable plane; the camera sits at height h above the
plane, its optical axis meets the plane at the circle's centre and makes the zenith angle
theta with the plane normal, so the camera is at distance D = h / cos(theta) from the centre.
In normalised image coordinates (u across the tilt, v along it, v toward the far side) a
plane point (x, y) images at u = x / (D + y sin), v = y cos / (D + y sin), and the circle
x^2 + y^2 = R^2 becomes, with rho = R / D,

    cos^2 u^2 + (1 - rho^2 sin^2) v^2 + 2 rho^2 sin cos v - rho^2 cos^2 = 0,

an ellipse with semi-axes rho / sqrt(1 - rho^2 sin^2) (across the tilt) and
rho cos / (1 - rho^2 sin^2) (along it). Hence

    b / a = cos(theta) / sqrt(1 - rho^2 sin^2(theta)),
    e^2 = sin^2(theta) (1 - rho^2) / (1 - rho^2 sin^2(theta)),     rho = R cos(theta) / h,

which is e = sin(theta) for a distant camera (rho -> 0). With S = sin^2(theta) and
q = R^2 / h^2 the inverse is the root of q (1 - e^2) S^2 + (1 - q + e^2 q) S - e^2 = 0.
The ellipse's centre is *not* the image of the circle's centre: it is shifted toward the
near side by rho^2 sin cos / (1 - rho^2 sin^2) (normalised units).

When the focal length is known the ellipse alone gives theta and D (no h needed), and with
them the homography that rectifies image points onto the turntable plane
(:class:`PlaneRectifier`), which removes the ellipse bias from the bisector method.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import erfc

from alignd.errors import VisionError
from alignd.vision.edges import (
    EdgePoints,
    area_crossings,
    as_gray,
    check_usable,
    despeckle,
)
from alignd.vision.lens import Lens

log = logging.getLogger(__name__)

__all__ = ["PlaneRectifier", "RimFit", "camera_zenith_from_eccentricity",
           "eccentricity_from_zenith", "fit_ellipse", "fit_rim", "fit_rim_frames",
           "zenith_from_ellipse"]


# ---- eq. 3.7 and its inverse -----------------------------------------------------------
def eccentricity_from_zenith(zenith_deg: float, radius_mm: float, height_mm: float) -> float:
    """Perceived eccentricity of a circle of radius R seen from height h at zenith theta."""
    th = math.radians(zenith_deg)
    s2 = math.sin(th) ** 2
    rho2 = (radius_mm * math.cos(th) / height_mm) ** 2
    if rho2 >= 1.0:
        raise ValueError("camera inside the cone of the circle (R cos(theta) >= h)")
    return math.sqrt(s2 * (1 - rho2) / (1 - rho2 * s2))


def camera_zenith_from_eccentricity(e: float, radius_mm: float, height_mm: float) -> float:
    """Camera zenith angle (deg) from the rim's perceived eccentricity, R and h (eq. 3.7)."""
    if not 0.0 <= e < 1.0:
        raise ValueError(f"eccentricity must be in [0, 1), got {e}")
    q = (radius_mm / height_mm) ** 2
    e2 = e * e
    bq = 1 - q + e2 * q
    disc = bq * bq + 4 * q * (1 - e2) * e2
    S = 2 * e2 / (bq + math.sqrt(disc))  # stable form of the positive root
    return math.degrees(math.asin(math.sqrt(min(max(S, 0.0), 1.0))))


def zenith_from_ellipse(a_px: float, b_px: float, focal_px: float) -> tuple[float, float]:
    """Zenith (deg) and rho = R / D from the ellipse's semi-axes and the focal length."""
    an2 = (a_px / focal_px) ** 2
    bn2 = (b_px / focal_px) ** 2
    disc = max((an2 + 1) ** 2 - 4 * bn2, 0.0)
    c2 = ((an2 + 1) - math.sqrt(disc)) / (2 * an2)
    c2 = min(max(c2, 0.0), 1.0)
    s2 = 1.0 - c2
    rho = 1.0 / math.sqrt(s2 + 1.0 / an2)
    return math.degrees(math.acos(math.sqrt(c2))), rho


# ---- ellipse fitting -------------------------------------------------------------------
def fit_ellipse(xy: np.ndarray) -> np.ndarray:
    """Direct least-squares ellipse (Fitzgibbon; Halir & Flusser's stable form).

    Returns conic coefficients (A, B, C, D, E, F) of A x^2 + B xy + C y^2 + D x + E y + F = 0
    in the input's coordinates; data are centred and scaled internally for conditioning.
    """
    xy = np.asarray(xy, float)
    if xy.shape[0] < 6:
        raise VisionError(f"ellipse fit needs at least 6 points, got {xy.shape[0]}")
    m = xy.mean(axis=0)
    sc = float(np.sqrt(((xy - m) ** 2).sum(axis=1).mean())) or 1.0
    x = (xy[:, 0] - m[0]) / sc
    y = (xy[:, 1] - m[1]) / sc
    D1 = np.column_stack([x * x, x * y, y * y])
    D2 = np.column_stack([x, y, np.ones_like(x)])
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    T = -np.linalg.solve(S3, S2.T)
    M = S1 + S2 @ T
    M = np.array([M[2] / 2, -M[1], M[0] / 2])
    _w, v = np.linalg.eig(M)
    v = np.real(v)
    cond = 4 * v[0] * v[2] - v[1] ** 2
    idx = np.flatnonzero(cond > 0)
    if idx.size == 0:
        raise VisionError("points do not lie on an ellipse")
    a1 = v[:, idx[0]]
    a2 = T @ a1
    A, B, C, D, E, F = np.concatenate([a1, a2])
    # undo scaling: x = (X - mx)/sc
    s2 = sc * sc
    A2, B2, C2 = A / s2, B / s2, C / s2
    D2_, E2 = D / sc, E / sc
    mx, my = m
    return np.array([
        A2, B2, C2,
        -2 * A2 * mx - B2 * my + D2_,
        -2 * C2 * my - B2 * mx + E2,
        A2 * mx * mx + B2 * mx * my + C2 * my * my - D2_ * mx - E2 * my + F,
    ])


def _conic_params(k: np.ndarray) -> tuple[np.ndarray, tuple[float, float], float]:
    A, B, C, D, E, F = k
    M = np.array([[A, B / 2], [B / 2, C]])
    ctr = np.linalg.solve(M, -np.array([D, E]) / 2)
    val = -(A * ctr[0] ** 2 + B * ctr[0] * ctr[1] + C * ctr[1] ** 2 + D * ctr[0] + E * ctr[1]
            + F)
    w, v = np.linalg.eigh(M / val)
    if np.any(w <= 0):
        raise VisionError("fitted conic is not an ellipse")
    axes = 1.0 / np.sqrt(w)  # ascending eigenvalues -> a, b
    ang = math.degrees(math.atan2(v[1, 0], v[0, 0]))
    ang = (ang + 90.0) % 180.0 - 90.0
    return ctr, (float(axes[0]), float(axes[1])), ang


def _sampson(k: np.ndarray, xy: np.ndarray) -> np.ndarray:
    A, B, C, D, E, F = k
    x, y = xy[:, 0], xy[:, 1]
    f = A * x * x + B * x * y + C * y * y + D * x + E * y + F
    gx = 2 * A * x + B * y + D
    gy = B * x + 2 * C * y + E
    return f / np.maximum(np.hypot(gx, gy), 1e-12)


@dataclass(frozen=True)
class RimFit:
    """The rim ellipse and what it says about the top camera."""

    center_px: np.ndarray
    axes_px: tuple[float, float]  # semi-axes a >= b
    angle_deg: float  # major axis direction (x toward y)
    eccentricity: float
    camera_zenith_deg: float  # eq. 3.7 from e, R, h (NaN if R or h unknown)
    rms_px: float
    n_points: int
    conic: np.ndarray  # (A, B, C, D, E, F)
    eccentricity_std: float = math.nan  # standard uncertainty of e (from the fit)

    def to_json(self) -> dict[str, object]:
        zen = self.camera_zenith_deg
        return {"ellipse": {"center_px": [float(v) for v in self.center_px],
                            "axes_px": [float(v) for v in self.axes_px],
                            "angle_deg": self.angle_deg},
                "eccentricity": self.eccentricity,
                "eccentricity_std": (self.eccentricity_std
                                     if math.isfinite(self.eccentricity_std) else None),
                "camera_zenith_deg": zen if math.isfinite(zen) else None,
                "rms_px": self.rms_px, "n_points": self.n_points}


MIN_SUPPORT = 0.65  # the rim: 0.9 and more; contours that strayed: up to 0.55
MAX_TRIES = 4  # coarse candidates refined at most, the first whose fit passes is taken


def _coarse_ellipses(gray: np.ndarray, min_contrast: float) -> list[np.ndarray]:
    """The rim at 1/4 scale, as full-res conics to refine in turn: elliptical outlines
    (:func:`_contours`), each checked against the image (:func:`_edge_support`); the best
    supported first, the outermost of those about as well supported (a rim ring's outer
    edge, not its inner one), then the other outlines and the circles voted by the
    image's gradients (:func:`_hough_candidates`; where a shadow and a cable break every
    outline open), best supported first, each with a support of ``MIN_SUPPORT`` or more.
    Later ones are only refined when the earlier ones' fits are refused (a holder smeared
    over the rim in a turned frames' mean can let a cable's loop outscore every outline
    of the disc)."""
    h, w = gray.shape
    f = 4
    small = cv2.resize(gray, (w // f, h // f), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), 1.0)
    lo, hi = np.percentile(small, [0.5, 99.5])
    if hi - lo < min_contrast:
        raise VisionError("rim image: too little contrast for a rim")
    u8 = np.clip((small - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    sh, sw = u8.shape
    cands: list[tuple[float, np.ndarray, np.ndarray]] = []  # (points, params, full-res pts)
    conics: list[np.ndarray] = []  # the candidates' conics at 1/4 scale
    for cnt in _contours(u8):
        if cnt.shape[0] < 40:
            continue
        pts = cnt[:, 0, :].astype(float)
        inner = ((pts[:, 0] > 1) & (pts[:, 0] < sw - 2) & (pts[:, 1] > 1)
                 & (pts[:, 1] < sh - 2))
        if inner.mean() < 0.6 or inner.sum() < 40:
            continue
        pts = pts[inner]
        if any(np.mean(np.abs(_sampson(kc, pts)) < 1.0) > 0.9 for kc in conics):
            continue  # the same ellipse at another level: no need to fit it
        for k, keep in _robust_ellipses(pts, min_cover=0.3):
            try:
                ctr, (a, b), ang = _conic_params(k)
            except (VisionError, np.linalg.LinAlgError):
                continue
            if b < 0.1 * min(sh, sw) or a > 2 * max(sh, sw):
                continue
            par = np.array([ctr[0], ctr[1], a, b])
            if any(np.max(np.abs(c[1][:4] - par)) < 1.0 for c in cands):
                continue  # the same ellipse at another threshold
            full = (pts[keep] + 0.5) * f - 0.5
            cands.append((float(keep.sum()), np.array([*par, ang]), full))
            conics.append(k)
    cands.sort(key=lambda c: -c[0])
    scored = []
    for _n, _par, full in cands[:24]:
        try:  # each candidate moved onto the nearest strong step first (an arc's
            # ellipse may be a few px off elsewhere)
            k = _outer_crossings(gray, fit_ellipse(full), min_contrast)
            scored.append((_edge_support(gray, k, min_contrast), k))
        except (VisionError, np.linalg.LinAlgError):
            continue
    out: list[np.ndarray] = []
    top = max((sc for sc, _ in scored), default=0.0)
    if top >= MIN_SUPPORT:
        near = [(k, _conic_params(k)[1][0]) for sc, k in scored if sc >= top - 0.05]
        out.append(max(near, key=lambda t: t[1])[0])
    hough = _hough_candidates(gray, u8, f, min_contrast)
    out += [k for sc, k in sorted([*scored, *hough], key=lambda t: -t[0])
            if sc >= MIN_SUPPORT and not any(k is q for q in out)]
    if out and top < MIN_SUPPORT:
        log.info("rim image: no outline followed the rim (best support %.2f); a circle "
                 "voted by the gradients did", top)
    if not out:
        top = max(top, max((sc for sc, _ in hough), default=0.0))
        raise VisionError("rim image: no elliptical rim found" + (
            f" (the best candidate's edge runs along only {100 * top:.0f} % of it)"
            if scored or hough else ""))
    return _distinct(out)[:MAX_TRIES]


def _distinct(ks: list[np.ndarray], tol_px: float = 1.0) -> list[np.ndarray]:
    """The conics in order, without those within ``tol_px`` (centre, axes) of an earlier
    one: refining the same ellipse twice gives the same answer."""
    out: list[tuple[np.ndarray, np.ndarray]] = []
    for k in ks:
        try:
            ctr, (a, b), _ang = _conic_params(k)
        except (VisionError, np.linalg.LinAlgError):
            continue
        par = np.array([ctr[0], ctr[1], a, b])
        if np.all(np.isfinite(par)) and not any(np.max(np.abs(q - par)) < tol_px
                                                for _, q in out):
            out.append((k, par))
    return [k for k, _ in out]


def _hough_candidates(gray: np.ndarray, u8: np.ndarray, f: int, min_contrast: float,
                      n: int = 8) -> list[tuple[float, np.ndarray]]:
    """Circles voted by the 1/4-scale image's gradients (``cv2.HoughCircles``), each moved
    onto the nearest strong step (:func:`_outer_crossings`, which lets it become the
    ellipse) and scored by its edge support. A vote needs no closed outline: a disc
    crossed by a cable and a shadow's edge, as dark as the floor on one side, still
    gathers its gradients round its centre (the corpus' "dark disc" scene #26 of seed
    2024: no outline near the rim, support 0.96 at the circle's ellipse). The rim's e is
    at most about 0.3 in practice, a - b within the crossings' 14 px reach of a circle."""
    sh, sw = u8.shape
    circ = cv2.HoughCircles(u8, cv2.HOUGH_GRADIENT, dp=1, minDist=5, param1=60, param2=20,
                            minRadius=int(0.1 * min(sh, sw)), maxRadius=int(max(sh, sw)))
    out: list[tuple[float, np.ndarray]] = []
    if circ is None:
        return out
    for cx, cy, r in circ[0][:n]:
        cx, cy, r = (cx + 0.5) * f - 0.5, (cy + 0.5) * f - 0.5, r * f
        k0 = np.array([1.0, 0.0, 1.0, -2 * cx, -2 * cy, cx * cx + cy * cy - r * r])
        try:
            k = _outer_crossings(gray, k0, min_contrast)
        except (VisionError, np.linalg.LinAlgError):
            continue
        out.append((_edge_support(gray, k, min_contrast), k))
    return sorted(out, key=lambda t: -t[0])


def _contours(u8: np.ndarray) -> Iterator[np.ndarray]:
    """Outlines that may hold the rim: the contours at a ladder of levels of either
    polarity, with and without thin structures (cables) opened and closed away, then the
    chains of edge pixels (Canny), which still follow the rim where a shadow or a floor
    as bright as the disc breaks every level's region open."""
    ker = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    for thr in range(32, 240, 32):
        for mask in (u8 < thr, u8 > thr):
            m8 = mask.astype(np.uint8)
            m_oc = cv2.morphologyEx(cv2.morphologyEx(m8, cv2.MORPH_OPEN, ker),
                                    cv2.MORPH_CLOSE, ker)
            for m in (m8, m_oc):
                yield from cv2.findContours(m, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[0]
    edges = cv2.Canny(u8, 25, 60, L2gradient=True)
    yield from cv2.findContours(edges, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)[0]


def _edge_support(gray: np.ndarray, k: np.ndarray, min_contrast: float, n: int = 240
                  ) -> float:
    """Fraction of the ellipse k along which the image steps, with one polarity and a
    like contrast, between 5-8 px inside and 5-8 px outside (a rim does nearly all
    round; a cable loop or a contour that strays onto a holder or a shadow does not)."""
    try:
        ctr, (a, b), ang = _conic_params(k)
    except (VisionError, np.linalg.LinAlgError):
        return 0.0
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    t = math.radians(ang)
    c, s = math.cos(t), math.sin(t)
    u, v = a * np.cos(phi), b * np.sin(phi)
    px, py = ctr[0] + c * u - s * v, ctr[1] + s * u + c * v
    nx, ny = c * u / a ** 2 - s * v / b ** 2, s * u / a ** 2 + c * v / b ** 2
    nn = np.hypot(nx, ny)
    nx, ny = nx / nn, ny / nn
    off = np.array([-8.0, -6.5, -5.0, 5.0, 6.5, 8.0], np.float32)
    mx = (px[:, None] + off[None] * nx[:, None]).astype(np.float32)
    my = (py[:, None] + off[None] * ny[:, None]).astype(np.float32)
    prof = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=float("nan"))
    step = prof[:, 3:].mean(axis=1) - prof[:, :3].mean(axis=1)
    fin = np.isfinite(step)
    if fin.sum() < n // 2:
        return 0.0
    sign = 1.0 if np.median(step[fin]) > 0 else -1.0
    st = np.where(fin, sign * step, 0.0)
    med = float(np.median(st[st > 0])) if np.any(st > 0) else 0.0
    good = (st >= max(min_contrast, 0.3 * med)) & (st <= 3.0 * med)
    return float(good.mean())


def _refit(pts: np.ndarray, keep: np.ndarray, tol: float
           ) -> tuple[np.ndarray, np.ndarray] | None:
    """Iteratively reweighted ellipse: refit on the points within 3 robust sigma (>= tol)."""
    k = None
    for _ in range(5):
        if keep.sum() < 40:
            return None
        try:
            k = fit_ellipse(pts[keep])
            _conic_params(k)
        except (VisionError, np.linalg.LinAlgError):
            return None
        r = np.abs(_sampson(k, pts))
        sig = float(np.median(r[keep])) * 1.4826
        new = r < max(3 * sig, tol)
        if np.array_equal(new, keep):
            break
        keep = new
    return (k, keep) if k is not None and keep.sum() >= 40 else None


def _coverage(k: np.ndarray, pts: np.ndarray) -> float:
    """Fraction of 36 angular sectors around the ellipse centre holding points."""
    try:
        ctr, _, _ = _conic_params(k)
    except (VisionError, np.linalg.LinAlgError):
        return 0.0
    ang = np.arctan2(pts[:, 1] - ctr[1], pts[:, 0] - ctr[0])
    return float(np.unique(((ang + np.pi) / (2 * np.pi) * 36).astype(int) % 36).size / 36)


def _robust_ellipses(pts: np.ndarray, tol: float = 1.0, min_cover: float = 0.5
                     ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Ellipses through much of ``pts`` (a contour), most inliers first: a fit to all of
    them, or, when something merged with the rim (a holder, a cable, a shadow's edge),
    fits to each of eight arcs, refitted on their inliers; each must cover ``min_cover``
    of its ellipse within 1 px rms. All are kept, not only the one with most inliers:
    an ellipse hugging a cable and a small cap can have more than the rim's own arc,
    and the image (edge support) decides between them."""
    n = len(pts)
    trials = [np.ones(n, bool)]
    if n >= 160:
        arc = n // 4
        for s0 in range(0, n, max(n // 8, 1)):
            m = np.zeros(n, bool)
            m[(s0 + np.arange(arc)) % n] = True
            trials.append(m)
    fits: list[tuple[np.ndarray, np.ndarray]] = []
    for keep in trials:
        fit = _refit(pts, keep, tol)
        if fit is None:
            continue
        k, kp = fit
        if _coverage(k, pts[kp]) < min_cover:
            continue
        if float(np.sqrt(np.mean(_sampson(k, pts[kp]) ** 2))) > 1.0:
            continue
        fits.append((k, kp))
        if kp.mean() > 0.9:
            break
    return sorted(fits, key=lambda f: -int(f[1].sum()))


def _outer_crossings(gray: np.ndarray, k: np.ndarray, min_contrast: float,
                     reach_px: float = 14.0, n: int = 360) -> np.ndarray:
    """Refine a rough conic to ~0.3 px: along normals, from the background inward, the
    first crossing of half the first strong step (the turntable's outer boundary, not the
    inner edge of a rim ring)."""
    ctr, (a, b), ang = _conic_params(k)
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rot = math.radians(ang)
    cr, sr = math.cos(rot), math.sin(rot)
    ex, ey = a * np.cos(phi), b * np.sin(phi)
    px = ctr[0] + cr * ex - sr * ey
    py = ctr[1] + sr * ex + cr * ey
    nx, ny = cr * ex / a ** 2 - sr * ey / b ** 2, sr * ex / a ** 2 + cr * ey / b ** 2
    nn = np.hypot(nx, ny)
    nx, ny = nx / nn, ny / nn
    s = np.arange(reach_px, -reach_px - 0.5, -0.5)  # outside -> inside
    mx = (px[:, None] + s[None] * nx[:, None]).astype(np.float32)
    my = (py[:, None] + s[None] * ny[:, None]).astype(np.float32)
    prof = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=float("nan"))
    xy = _first_half_crossings(prof, s, px, py, nx, ny, min_contrast)
    if len(xy) < 20:
        raise VisionError("rim image: the rim's outer edge could not be traced")
    k2 = fit_ellipse(xy)
    for _ in range(3):
        r = _sampson(k2, xy)
        keep = np.abs(r) < max(4 * 1.4826 * float(np.median(np.abs(r))), 0.3)
        if keep.all() or keep.sum() < 20:
            break
        xy = xy[keep]
        k2 = fit_ellipse(xy)
    return k2


def _first_half_crossings(prof: np.ndarray, s: np.ndarray, px: np.ndarray, py: np.ndarray,
                          nx: np.ndarray, ny: np.ndarray, min_contrast: float) -> np.ndarray:
    """For each profile (a row, sampled at offsets ``s`` from the background inward): the
    background is the median of its first 6 samples, the first strong step is the first
    sample off it by more than ``min_contrast`` and 35 % of the row's largest step, the
    step's level the median of 6 samples from there; returns the points where the row
    first crosses half that step (linear interpolation), rows without one left out."""
    fin = np.all(np.isfinite(prof), axis=1)
    prof, px, py, nx, ny = prof[fin], px[fin], py[fin], nx[fin], ny[fin]
    m = prof.shape[1]
    bg = np.median(prof[:, :6], axis=1)
    d = np.abs(prof - bg[:, None])
    dmax = d.max(axis=1) if m else np.zeros(len(prof))
    strong = d > np.maximum(min_contrast, 0.35 * dmax)[:, None]
    has = strong.any(axis=1) & (dmax >= min_contrast)
    j = np.argmax(strong, axis=1)
    win = j[:, None] + np.arange(6)[None]
    lvl = np.nanmedian(np.where(win < m, np.take_along_axis(prof, np.minimum(win, m - 1),
                                                            axis=1), np.nan), axis=1)
    half = np.abs(lvl - bg) / 2
    ge = (d >= half[:, None]) & (np.arange(m)[None] <= j[:, None])
    j1 = np.argmax(ge, axis=1)
    has &= ge.any(axis=1) & (j1 > 0)
    r = np.flatnonzero(has)
    j1 = j1[r]
    d0, d1 = d[r, j1 - 1], d[r, j1]
    f = (half[r] - d0) / np.maximum(d1 - d0, 1e-9)
    t = s[j1 - 1] + f * (s[j1] - s[j1 - 1])
    return np.column_stack([px[r] + t * nx[r], py[r] + t * ny[r]])


def _rim_points(gray: np.ndarray, k: np.ndarray, half_width: int, min_contrast: float,
                tails: int) -> EdgePoints:
    """Area-method crossings of the conic k, columns where it is flat, rows where steep."""
    A, B, C, D, E, F = k
    h, w = gray.shape
    chunks_xy, chunks_c = [], []
    for vertical in (False, True):
        if not vertical:  # columns x: C y^2 + (B x + E) y + (A x^2 + D x + F) = 0
            t = np.arange(w, dtype=float)
            qa, qb, qc = C, B * t + E, A * t * t + D * t + F
        else:  # rows y: A x^2 + (B y + D) x + (C y^2 + E y + F) = 0
            t = np.arange(h, dtype=float)
            qa, qb, qc = A, B * t + D, C * t * t + E * t + F
        disc = qb * qb - 4 * qa * qc
        ok = disc > 0
        for sign in (-1.0, 1.0):
            root = np.full_like(t, np.nan)
            root[ok] = (-qb[ok] + sign * np.sqrt(disc[ok])) / (2 * qa)
            if not vertical:
                x, y = t, root
            else:
                x, y = root, t
            gx = 2 * A * x + B * y + D
            gy = B * x + 2 * C * y + E
            use = np.isfinite(root)
            use &= (np.abs(gy) >= np.abs(gx)) if not vertical else (np.abs(gx) > np.abs(gy))
            # at least 45 deg from the profile direction: keep a margin from the switch
            idx = np.flatnonzero(use)
            if idx.size < 3:
                continue
            # split into contiguous runs so that the along-edge smoothing stays on one arc
            runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
            for run in runs:
                if run.size < 3:
                    continue
                pts = area_crossings(gray, t[run], root[run], vertical, half_width=half_width,
                                     tails=tails, min_contrast=min_contrast)
                if pts.xy.shape[0]:
                    chunks_xy.append(pts.xy)
                    chunks_c.append(pts.contrast)
    if not chunks_xy:
        return EdgePoints(np.empty((0, 2)), np.empty(0), False)
    return EdgePoints(np.concatenate(chunks_xy), np.concatenate(chunks_c), False)


# ---- sub-pixel refinement: edge profiles along the ellipse, then a geometric fit ----------
Ellipse = np.ndarray  # (cx, cy, a, b, theta_rad)


def _params_from_conic(k: np.ndarray) -> Ellipse:
    ctr, (a, b), ang = _conic_params(k)
    return np.array([ctr[0], ctr[1], a, b, math.radians(ang)])


def _conic_from_params(p: Ellipse) -> np.ndarray:
    cx, cy, a, b, t = (float(v) for v in p)
    c, s = math.cos(t), math.sin(t)
    M = np.array([[c, -s], [s, c]]) @ np.diag([1 / a ** 2, 1 / b ** 2]) @ np.array(
        [[c, s], [-s, c]])
    ctr = np.array([cx, cy])
    A, B, C = M[0, 0], 2 * M[0, 1], M[1, 1]
    D, E = -2 * (M @ ctr)
    F = float(ctr @ M @ ctr) - 1.0
    k = np.array([A, B, C, D, E, F])
    return k / np.abs(k).max()


def _ellipse_frame(p: Ellipse, x: np.ndarray, y: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance (px, + outside) of points to the ellipse p, to first order in the
    normalised radius (exact for a circle), with the points' parametric angle."""
    cx, cy, a, b, t = p
    c, s = math.cos(t), math.sin(t)
    dx, dy = x - cx, y - cy
    u = c * dx + s * dy
    v = -s * dx + c * dy
    un, vn = u / a, v / b
    rho = np.sqrt(un * un + vn * vn)
    g = np.sqrt((un / a) ** 2 + (vn / b) ** 2) / np.maximum(rho, 1e-12)
    return (rho - 1.0) / np.maximum(g, 1e-12), np.arctan2(vn, un), rho


def _distance_jacobian(p: Ellipse, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """d(distance)/d(cx, cy, a, b, theta) at the points, by central differences."""
    steps = (1e-3, 1e-3, 1e-3, 1e-3, 1e-6)
    cols = []
    for i, h in enumerate(steps):
        dp = np.zeros(5)
        dp[i] = h
        cols.append((_ellipse_frame(p + dp, x, y)[0] - _ellipse_frame(p - dp, x, y)[0])
                    / (2 * h))
    return np.column_stack(cols)


@dataclass(frozen=True)
class _Profiles:
    """One fitted edge profile per arc segment of the ellipse."""

    xy: np.ndarray  # (K, 2) edge points
    sigma: np.ndarray  # (K,) standard error of the point along the normal (px)
    contrast: np.ndarray  # (K,) outside minus inside level (DN)
    width: np.ndarray  # (K,) edge width s (px, the Gaussian's sigma incl. the pixel)
    rms: np.ndarray  # (K,) residual rms (DN)
    phi: np.ndarray  # (K,) parametric angle of the segment
    ok: np.ndarray  # (K,) bool


def _edge_profiles(gray: np.ndarray, p: Ellipse, half_band: float, seg_px: float = 12.0,
                   iterations: int = 10) -> _Profiles:
    """Fit I = b0 + b1 d + c0 Phi(t) + b2 s (t Phi(t) + phi(t)), t = (d - delta) / s, to
    the pixels within ``half_band`` px of the ellipse, segment by segment (arcs of
    ~seg_px): delta is the edge's offset along the normal, d the pixel's signed distance
    to the ellipse (exact pixel positions, no interpolation), s the edge's width. The
    levels and the slopes absorb lighting gradients, vignetting, shading and either
    polarity: b1 is the slope inside, b1 + b2 outside, the last term being the blur of
    b2 max(d - delta, 0), a kink at the edge blurred as the edge is. The floor and the
    disc slope differently under any light (their levels differ) and a textured floor
    slopes on its own: one slope for both sides moved each arc's edge by ~0.1 px per
    DN/px of the difference, times the contrast's inverse, in a pattern that varies round
    the rim (e off by 0.003-0.009 in the corpus' worst frames). The second slope costs
    precision, the less the wider the band (+-8 px and more: delta's standard error
    x1.33 against one slope at +-5 px; e's median standard error in the corpus +17 %)."""
    h, w = gray.shape
    cx, cy, a, b, _t = p
    if not (np.all(np.isfinite(p)) and min(a, b) > 5.0):
        raise VisionError("rim image: the ellipse fit diverged")
    r = max(a, b) + half_band + 2
    x0, x1 = max(int(cx - r), 0), min(int(cx + r) + 2, w)
    y0, y1 = max(int(cy - r), 0), min(int(cy + r) + 2, h)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    xf, yf = xx.ravel().astype(float), yy.ravel().astype(float)
    d, phi, _ = _ellipse_frame(p, xf, yf)
    sel = np.abs(d) <= half_band
    d, phi = d[sel], phi[sel]
    val = gray[yy.ravel()[sel], xx.ravel()[sel]].astype(float)
    perim = math.pi * (3 * (a + b) - math.sqrt((3 * a + b) * (a + 3 * b)))
    K = max(int(perim / seg_px), 24)
    seg = (((phi + math.pi) / (2 * math.pi)) * K).astype(int) % K
    order = np.argsort(seg, kind="stable")
    d, val, seg = d[order], val[order], seg[order]
    counts = np.bincount(seg, minlength=K)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    present = counts > 0
    # a segment needs pixels on both sides of the edge, as many as a full arc holds
    expect = float(np.median(counts[present])) if present.any() else 0.0
    n_in = np.bincount(seg, weights=(d < -1.0).astype(float), minlength=K)
    n_out = np.bincount(seg, weights=(d > 1.0).astype(float), minlength=K)
    usable = (counts >= max(0.7 * expect, 20)) & (n_in >= 0.3 * counts) & (
        n_out >= 0.3 * counts)
    # a clipped (saturated or black) side flattens the step asymmetrically: an arc with
    # clipped pixels within 4 px of the edge is left out; farther out (a saturated disc in
    # the wide band) they only lose their weight
    clip = (val >= 254.5) | (val <= 0.5)
    near = np.abs(d) <= 4.0
    usable &= np.bincount(seg, weights=(clip & near).astype(float), minlength=K) <= 0.02 * (
        np.bincount(seg, weights=near.astype(float), minlength=K))
    ids = np.flatnonzero(present)
    st = starts[ids]

    def segsum(v: np.ndarray) -> np.ndarray:  # sums over each present segment
        return np.add.reduceat(v, st, axis=0)

    nf = 6
    # start: each side's mean level, flat, no offset, s = 1 px
    P = np.zeros((K, nf))
    P[:, 0] = np.bincount(seg, weights=np.where(d < -1.0, val, 0.0), minlength=K) / np.maximum(
        n_in, 1)
    P[:, 2] = np.bincount(seg, weights=np.where(d > 1.0, val, 0.0), minlength=K) / np.maximum(
        n_out, 1) - P[:, 0]
    P[:, 4] = 1.0
    free = (~clip).astype(float)
    wts = free
    lam = 1e-3
    res = np.zeros_like(d)

    def model(P: np.ndarray) -> tuple[np.ndarray, ...]:
        b0, b1, c0, dl, s = (P[seg, i] for i in range(5))
        b2 = P[seg, 5]
        t = (d - dl) / s
        F = 0.5 * _erfc(-t / math.sqrt(2))
        f = np.exp(-0.5 * t * t) / math.sqrt(2 * math.pi)
        kink = s * (t * F + f)
        return val - (b0 + b1 * d + c0 * F + b2 * kink), t, F, f, c0, s, b2, kink

    JtJ = np.zeros((ids.size, nf, nf))
    for it in range(iterations):
        res, t, F, f, c0, s, b2, kink = model(P)
        if it >= 3:  # Tukey's biweight on the segment's robust scale: specks, cable edges
            sc = _seg_scale(res, seg, K) * 4.685
            u = res / sc[seg]
            wts = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0) * free
        J = np.column_stack([np.ones_like(d), d, F, -c0 * f / s - b2 * F,
                             -c0 * f * t / s + b2 * f, kink])
        Jw = J * wts[:, None]
        JtJ = segsum(Jw[:, :, None] * J[:, None, :])
        Jtr = segsum(Jw * res[:, None])
        diag = np.einsum("kii->ki", JtJ)
        A = JtJ + lam * diag[:, :, None] * np.eye(nf)[None] + 1e-9 * np.eye(nf)[None]
        try:
            step = np.linalg.solve(A, Jtr[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            break
        step[:, 3] = np.clip(step[:, 3], -1.0, 1.0)
        P[ids] += step
        P[ids, 4] = np.clip(P[ids, 4], 0.25, half_band / 1.5)
    # standard error of delta from the final normal matrix
    res = model(P)[0]
    wsum = np.maximum(segsum(wts), 1.0)
    rms = np.sqrt(segsum(wts * res * res) / np.maximum(wsum - nf, 1.0))
    try:
        cov = np.linalg.inv(JtJ + 1e-9 * np.eye(nf)[None])
        sig = np.sqrt(np.maximum(cov[:, 3, 3], 0.0)) * rms
    except np.linalg.LinAlgError:
        sig = np.full(ids.size, np.inf)
    K_ok = np.zeros(K, bool)
    K_ok[ids] = usable[ids] & np.isfinite(sig) & np.all(np.isfinite(P[ids]), axis=1)
    sigma = np.full(K, np.inf)
    sigma[ids] = sig
    rmsK = np.full(K, np.inf)
    rmsK[ids] = rms
    phik = (np.arange(K) + 0.5) / K * 2 * math.pi - math.pi
    cxp, cyp, ap, bp, tp = p
    u, v = ap * np.cos(phik), bp * np.sin(phik)
    c_, s_ = math.cos(tp), math.sin(tp)
    ex, ey = cxp + c_ * u - s_ * v, cyp + s_ * u + c_ * v
    nx, ny = c_ * u / ap ** 2 - s_ * v / bp ** 2, s_ * u / ap ** 2 + c_ * v / bp ** 2
    nn = np.hypot(nx, ny)
    dk = P[:, 3]
    xy = np.column_stack([ex + dk * nx / nn, ey + dk * ny / nn])
    return _Profiles(xy, sigma, P[:, 2], P[:, 4], rmsK, phik, K_ok)


def _seg_median(v: np.ndarray, seg: np.ndarray, K: int) -> np.ndarray:
    """Per-segment (upper) median of v; NaN for empty segments."""
    order = np.lexsort((v, seg))
    counts = np.bincount(seg, minlength=K)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = np.full(K, np.nan)
    has = counts > 0
    out[has] = v[order][starts[has] + counts[has] // 2]
    return out


def _seg_scale(res: np.ndarray, seg: np.ndarray, K: int) -> np.ndarray:
    """Per-segment robust residual scale (1.4826 MAD about 0), floored by half the
    global one."""
    a = np.abs(res)
    glob = float(np.median(a)) * 1.4826 + 0.3  # + a floor: noise-free frames
    loc = _seg_median(a, seg, K) * 1.4826
    return np.where(np.isfinite(loc), np.maximum(loc, 0.5 * glob), glob)


def _erfc(x: np.ndarray) -> np.ndarray:
    return np.asarray(erfc(x))


def _geometric_fit(p: Ellipse, xy: np.ndarray, sigma: np.ndarray, iterations: int = 12
                   ) -> tuple[Ellipse, np.ndarray]:
    """Ellipse through the points minimising their weighted orthogonal distances
    (Gauss-Newton from a close start), with Tukey's biweight on the normalised residuals;
    returns the parameters and the inliers (within 3.5 robust sigma)."""
    p = np.array(p, float)
    sig = _point_sigma(sigma)
    z = np.zeros(len(xy))
    sc = 1.0
    for _ in range(iterations):
        z = _ellipse_frame(p, xy[:, 0], xy[:, 1])[0] / sig
        sc = max(float(np.median(np.abs(z))) * 1.4826, 0.7)
        u = z / (4.685 * sc)
        wts = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        J = _distance_jacobian(p, xy[:, 0], xy[:, 1]) / sig[:, None]
        Jw = J * wts[:, None]
        try:
            step = np.linalg.solve(Jw.T @ J + 1e-9 * np.eye(5), -(Jw.T @ z))
        except np.linalg.LinAlgError:
            break
        p = p + step
        if not (np.all(np.isfinite(p)) and min(p[2], p[3]) > 5.0):
            raise VisionError("rim image: the ellipse fit diverged")
        if np.max(np.abs(step[:4])) < 1e-5 and abs(step[4]) < 1e-8:
            break
    z = _ellipse_frame(p, xy[:, 0], xy[:, 1])[0] / sig
    return p, np.abs(z) <= 3.5 * sc


MODEL_SIGMA_PX = 0.01  # the blurred-step model's own error on a sharp (0.5 px) edge


def _point_sigma(sigma: np.ndarray) -> np.ndarray:
    """Per-point standard errors floored (a noise-free arc must not outweigh the rest).

    The floor holds the profile model's own error: on a sharp edge (0.5 px blur) a pixel's
    box and the model's Gaussian differ by about 0.01 px with the edge's pixel phase.
    Below that, noise-free arcs' tiny errors made the robust fit reject a quarter of them
    by their phase, which biased e at 0.01 by 0.0007 and which arcs went depended on the
    machine's last bits of rounding."""
    return np.maximum(sigma, 0.5 * float(np.median(sigma)) + MODEL_SIGMA_PX)


def _ellipse_covariance(p: Ellipse, xy: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Covariance of (cx, cy, a, b, theta) from the points the fit kept: the normal
    matrix of their weighted distances, scaled by their actual scatter (so texture or
    compression that the per-arc standard errors miss still counts)."""
    sig = _point_sigma(sigma)
    z = _ellipse_frame(p, xy[:, 0], xy[:, 1])[0] / sig
    J = _distance_jacobian(p, xy[:, 0], xy[:, 1]) / sig[:, None]
    s2 = float(np.sum(z * z)) / max(len(z) - 5, 1)
    return np.linalg.inv(J.T @ J + 1e-12 * np.eye(5)) * s2


def _eccentricity_std(a: float, b: float, cov_ab: np.ndarray) -> float:
    """Standard uncertainty of e = sqrt(1 - (b/a)^2) (a >= b) from the axes' covariance,
    through e^2 (linear in the axes' ratio), so it stays finite at e = 0."""
    g = np.array([2 * b * b / a ** 3, -2 * b / (a * a)])  # d(e^2)/d(a, b)
    var_e2 = float(g @ cov_ab @ g)
    e = math.sqrt(max(0.0, 1.0 - (b / a) ** 2))
    return math.sqrt(max(var_e2, 0.0)) / (2 * max(e, math.sqrt(math.sqrt(max(var_e2, 0.0)))
                                                   + 1e-12))


def _consistent(prof: _Profiles, min_contrast: float) -> np.ndarray:
    """Segments whose edge looks like the rim's: its polarity, enough contrast, close to
    the neighbours' contrast, a like width (a shadow's edge is softer), a good fit (a
    cable or the holder's outline is not one step) and a well-determined position."""
    ok = prof.ok & np.isfinite(prof.contrast) & np.isfinite(prof.sigma)
    if ok.sum() < 12:
        return ok
    sign = 1.0 if np.median(prof.contrast[ok]) > 0 else -1.0
    c = sign * prof.contrast
    ok &= c >= min_contrast
    if ok.sum() < 12:
        return ok
    cm = np.where(ok, c, np.nan)
    nb = np.sort(np.stack([np.roll(cm, s) for s in (-3, -2, -1, 1, 2, 3)]), axis=0)
    n_nb = np.isfinite(nb).sum(axis=0)
    ref = np.where(n_nb > 0, nb[np.maximum(n_nb - 1, 0) // 2, np.arange(len(c))], np.nan)
    ok &= ~np.isfinite(ref) | (np.abs(c - ref) <= 0.3 * np.abs(ref))
    s_med = float(np.median(prof.width[ok]))
    ok &= (prof.width <= 1.6 * s_med + 0.3) & (prof.width >= 0.5 * s_med - 0.2)
    ok &= prof.rms <= 2.0 * float(np.median(prof.rms[ok])) + 1.0
    ok &= prof.sigma <= 4.0 * float(np.median(prof.sigma[ok])) + 0.01
    return ok


def _refine(gray: np.ndarray, p: Ellipse, min_contrast: float, rounds: int = 4,
            lens: Lens | None = None) -> tuple[Ellipse, np.ndarray, _Profiles, np.ndarray]:
    """Alternate edge profiles along the current ellipse and a geometric fit to their
    points; segments whose edge is not the rim's (a holder, a cable, a shadow's soft
    edge) are left out (:func:`_consistent`, then the fit's own outliers).

    With a ``lens`` the rim, a circle seen as an ellipse, is an ellipse only in the
    undistorted image: the arcs are measured where they are in the frame (along an ellipse
    fitted to them there, which the arcs' offsets follow to within their band) and the
    ellipse that counts is fitted to their points undistorted. Returns that ellipse, the
    points it was fitted to (undistorted with a lens), the profiles and the arcs used."""
    half_band = 9.0
    p_fit = p if lens is None else _undistorted_ellipse(p, lens)
    for rnd in range(rounds):
        prof = _edge_profiles(gray, p, half_band)
        ok = _consistent(prof, min_contrast)
        if ok.sum() < 12:
            raise VisionError("rim image: too few rim edge segments of one polarity and "
                              "contrast could be measured")
        xy = prof.xy if lens is None else lens.undistort(prof.xy)
        new, inl = _geometric_fit(p_fit, xy[ok], prof.sigma[ok])
        use = np.zeros_like(ok)
        use[np.flatnonzero(ok)[inl]] = True
        moved = np.max(np.abs(_ellipse_frame(new, xy[:, 0], xy[:, 1])[0]
                              - _ellipse_frame(p_fit, xy[:, 0], xy[:, 1])[0]))
        p_fit = new
        # the next arcs along the rim as the frame shows it
        p = new if lens is None else _geometric_fit(p, prof.xy[use], prof.sigma[use])[0]
        half_band = float(np.clip(3.0 * float(np.median(prof.width[use])) + 5.0, 8.0, 12.0))
        if rnd >= 1 and moved < 2e-3:
            break
    return p_fit, xy, prof, use


def _undistorted_ellipse(p: Ellipse, lens: Lens) -> Ellipse:
    """The ellipse through ``p``'s points undistorted (a start for the fit there)."""
    t = np.linspace(0.0, 2 * math.pi, 180, endpoint=False)
    cx, cy, a, b, th = (float(v) for v in p)
    c, s = math.cos(th), math.sin(th)
    pts = np.column_stack([cx + a * np.cos(t) * c - b * np.sin(t) * s,
                           cy + a * np.cos(t) * s + b * np.sin(t) * c])
    return _params_from_conic(fit_ellipse(lens.undistort(pts)))


def _quality(p: Ellipse, xy: np.ndarray, use: np.ndarray) -> tuple[float, float]:
    """The rms distance (px) of the arcs' points kept (``xy[use]``) from the ellipse, and
    the fraction of the arcs kept."""
    kept = xy[use]
    r = _ellipse_frame(p, kept[:, 0], kept[:, 1])[0]
    return (float(np.sqrt(np.mean(r ** 2))) if r.size else math.inf), float(use.mean())


def fit_rim(image: np.ndarray, radius_mm: float | None = 150.0, height_mm: float | None = 800.0,
            *, min_contrast: float = 15.0, max_rms_px: float = 0.25,
            min_coverage: float = 0.6, max_eccentricity_std: float | None = None,
            lens: Lens | None = None) -> RimFit:
    """Fit the turntable rim's outer edge; eccentricity and (with R, h) camera zenith.

    ``lens``: the camera's (``cameras[].lens``); the ellipse, its centre and e are then
    those of the undistorted image (a round rim 100 px off the principal point of a
    webcam's lens, k1 -0.08 at 1000 px, reads e = 0.057 in the frame itself).

    The whole rim (or most of it) must be in view: at the reference rig's 160 um/px a
    150 mm rim is larger than the frame, so calibrate with a wider view or a smaller
    concentric disc. Raises VisionError when no elliptical rim is visible, when less
    than ``min_coverage`` of its circumference could be measured, or when e's standard
    uncertainty exceeds ``max_eccentricity_std`` (a third of the bound the caller needs:
    at small e, low contrast and high noise one frame cannot support a tight bound).
    """
    gray = despeckle(as_gray(image, "rim image"))  # hot and dead pixels (edges.despeckle)
    check_usable(gray, min_contrast, "rim image")
    first: VisionError | None = None
    for k in _coarse_ellipses(gray, min_contrast):
        try:
            p, pts, prof, use = _refine(gray, _params_from_conic(k), min_contrast, lens=lens)
            rms, cover = _quality(p, pts, use)
            if cover < min_coverage or rms > max_rms_px:
                # a cable loop or a half-hidden rim fits some ellipse: flag it, do not guess
                raise VisionError(
                    f"rim image: the rim's edge was traced over only {100 * cover:.0f} % "
                    f"of its circumference (rms {rms:.2f} px); need "
                    f"{100 * min_coverage:.0f} % within {max_rms_px:g} px")
        except VisionError as exc:
            first = first or exc
            continue
        if first is not None:
            log.info("rim image: the first coarse candidate failed (%s); a later one fits",
                     first)
        break
    else:
        raise first or VisionError("rim image: no elliptical rim found")
    cov = _ellipse_covariance(p, pts[use], prof.sigma[use])[2:4, 2:4]
    cx, cy, a, b, t = (float(v) for v in p)
    if b > a:
        a, b, t = b, a, t + math.pi / 2
        cov = cov[::-1, ::-1]
    ang = (math.degrees(t) + 90.0) % 180.0 - 90.0
    e = math.sqrt(max(0.0, 1.0 - (b / a) ** 2))
    e_std = _eccentricity_std(a, b, cov)
    if max_eccentricity_std is not None and not e_std <= max_eccentricity_std:
        raise VisionError(f"rim image: e = {e:.4f} is uncertain by {e_std:.4f} (one standard "
                          f"uncertainty), more than the {max_eccentricity_std:g} asked for; "
                          f"average several frames, raise the rim's contrast or lower noise")
    zen = (camera_zenith_from_eccentricity(e, radius_mm, height_mm)
           if radius_mm and height_mm else math.nan)
    return RimFit(center_px=np.array([cx, cy]), axes_px=(a, b), angle_deg=ang, eccentricity=e,
                  camera_zenith_deg=zen, rms_px=rms, n_points=int(use.sum()),
                  conic=_conic_from_params(np.array([cx, cy, a, b, math.radians(ang)])),
                  eccentricity_std=e_std)


# ---- perspective correction --------------------------------------------------------------
class PlaneRectifier:
    """Maps image points to the turntable plane (mm, origin on the rim's centre) and back.

    Built from a rim fit, the focal length and the principal point, assuming (as the rig is
    set up) that the optical axis meets the plane at the rim's centre. The tilt's sense
    along the minor axis comes from the ellipse centre's shift toward the near side, which
    needs the principal point to about a pixel; ``far_direction`` (image unit vector
    pointing to the far side) overrides it.
    """

    def __init__(self, zenith_deg: float, distance_mm: float, far_direction: np.ndarray,
                 focal_px: float, principal_px: tuple[float, float]) -> None:
        th = math.radians(zenith_deg)
        s, c = math.sin(th), math.cos(th)
        m = np.asarray(far_direction, float)
        m = m / (np.linalg.norm(m) or 1.0)
        self.n = np.array([s * m[0], s * m[1], -c])  # plane normal toward the camera
        self.distance_mm = float(distance_mm)
        self.height_mm = c * distance_mm  # camera height above the plane
        self.focal_px = float(focal_px)
        self.principal_px = (float(principal_px[0]), float(principal_px[1]))
        self.zenith_deg = float(zenith_deg)
        x0 = np.array([0.0, 0.0, self.distance_mm])
        self.x0 = x0
        e1 = np.array([1.0, 0.0, 0.0]) - self.n[0] * self.n
        self.e1 = e1 / np.linalg.norm(e1)
        self.e2 = np.cross(self.e1, self.n)

    @classmethod
    def from_rim(cls, fit: RimFit, focal_px: float, principal_px: tuple[float, float],
                 radius_mm: float, far_direction: np.ndarray | None = None) -> PlaneRectifier:
        zen, rho = zenith_from_ellipse(fit.axes_px[0], fit.axes_px[1], focal_px)
        psi = math.radians(fit.angle_deg)
        minor = np.array([-math.sin(psi), math.cos(psi)])
        if far_direction is None:
            off = np.asarray(fit.center_px, float) - np.asarray(principal_px, float)
            # the ellipse centre lies toward the near side
            far_direction = -minor if float(off @ minor) > 0 else minor
        return cls(zen, radius_mm / rho, far_direction, focal_px, principal_px)

    def to_plane_mm(self, points_px: np.ndarray, plane_height_mm: float = 0.0) -> np.ndarray:
        """Image points (N, 2) -> (N, 2) mm in the plane ``plane_height_mm`` above the
        turntable; x along the image x, y along the image y, origin on the axis."""
        p = np.atleast_2d(np.asarray(points_px, float))
        r = np.column_stack([(p[:, 0] - self.principal_px[0]) / self.focal_px,
                             (p[:, 1] - self.principal_px[1]) / self.focal_px,
                             np.ones(len(p))])
        d = -(self.height_mm - plane_height_mm)
        X = r * (d / (r @ self.n))[:, None]
        rel = X - (self.x0 + plane_height_mm * self.n)
        return np.column_stack([rel @ self.e1, rel @ self.e2])

    def to_image_px(self, points_mm: np.ndarray, plane_height_mm: float = 0.0) -> np.ndarray:
        """Inverse of :meth:`to_plane_mm`."""
        q = np.atleast_2d(np.asarray(points_mm, float))
        X = (self.x0 + plane_height_mm * self.n)[None] + q[:, :1] * self.e1 + q[:, 1:] * self.e2
        return np.column_stack([self.principal_px[0] + self.focal_px * X[:, 0] / X[:, 2],
                                self.principal_px[1] + self.focal_px * X[:, 1] / X[:, 2]])


def fit_rim_frames(images: Sequence[np.ndarray], radius_mm: float | None = 150.0,
                   height_mm: float | None = 800.0, *,
                   max_eccentricity_std: float | None = None,
                   lens: Lens | None = None) -> RimFit:
    """:func:`fit_rim` on the mean of several frames of one static view (``lens`` as
    there).

    At small e one frame's sensor noise is the largest part of e's uncertainty (e = 0.01
    is an axes' difference of 0.01 px on a 200 px rim): the mean of N frames has 1/sqrt(N)
    of their noise. What the frames share (the disc's texture, JPEG coding of a still
    view) does not average out; ``eccentricity_std``, scaled by the points' scatter about
    the fitted ellipse, still counts it. A fine disc texture moves each arc's edge by a few
    hundredths of a pixel, which no per-arc model separates from the edge at a like noise
    (docs/vision.md, Rim): frames taken with the turntable turned between them carry the
    texture elsewhere each time while the rim's ellipse stays, so their mean averages it
    too. When the mean cannot be fitted (a holder standing on a turning turntable lies over
    the rim at a fraction of its contrast in several places), the mean without each
    pixel's outlying frames (:func:`_robust_mean`) is fitted instead; it is not used first,
    since where the mean can be fitted it was no better (12 such scenes: one 2.4 u off with
    it, 0.5 u without; a holder's soft shadow stays in some frames' samples and not in
    others'). Frames are taken to grey levels first, so 12-bit words and 8-bit frames mean
    the same."""
    if not images:
        raise VisionError("rim frames: no frame given")
    grays = [as_gray(im, f"rim frame {i + 1}") for i, im in enumerate(images)]
    shapes = {g.shape for g in grays}
    if len(shapes) != 1:
        raise VisionError(f"rim frames: frames of different sizes {sorted(shapes)}")
    if len(grays) == 1:
        return fit_rim(grays[0], radius_mm, height_mm,
                       max_eccentricity_std=max_eccentricity_std, lens=lens)
    mean = np.stack(grays).mean(axis=0, dtype=np.float32)
    try:
        return fit_rim(mean, radius_mm, height_mm, max_eccentricity_std=max_eccentricity_std,
                       lens=lens)
    except VisionError as exc:
        if len(grays) < 3:
            raise
        # frames at several turntable angles: a holder on it, smeared over the mean, can
        # hide the rim; without what covers a pixel in few frames it may show
        try:
            fit = fit_rim(_robust_mean(grays), radius_mm, height_mm,
                          max_eccentricity_std=max_eccentricity_std, lens=lens)
        except VisionError:
            raise exc from None
        log.info("rim frames: fitted without what covered a pixel in few frames (%s)", exc)
        return fit


OUTLIER_SCALES = 8.0  # a frame's pixel this many robust scales off the pixel's median is left out


def _robust_mean(grays: Sequence[np.ndarray], bins: int = 16) -> np.ndarray:
    """Per-pixel mean of the frames without the samples far off the pixel's median.

    Frames taken with the turntable turned between them show a holder standing on it at a
    different place each time: in the plain mean it lies over the rim at 1/N of its
    contrast in N places (the coarse search missed the rim in 3 of 200 corpus scenes).
    Each pixel's samples more than ``OUTLIER_SCALES`` robust scales
    of the frames' spread off its median are left out, so what covers a pixel in fewer
    than half the frames goes; the scale is the frames' spread (noise, a turning texture)
    at the pixel's grey level (shot noise grows with it: one scale for all left out the
    tails of bright pixels' noise). Frames of a still view differ by their noise alone, and
    almost nothing is left out: their mean."""
    st = np.stack(grays).astype(np.float32)
    n_f = len(grays)
    if n_f < 3:
        return st.mean(axis=0)
    med = np.median(st, axis=0)
    dev = np.abs(st - med)
    # the spread by grey level: the median deviation per bin of the pixels' medians
    # (sqrt(n / (n - 1)): the median is fitted to the same samples)
    lo, hi = float(med.min()), float(med.max())
    idx = np.clip(((med - lo) / max(hi - lo, 1e-6) * bins).astype(int), 0, bins - 1)
    dev_med = np.median(dev, axis=0)  # per pixel, then per bin (fast, robust)
    glob = float(np.median(dev_med))
    per_bin = np.full(bins, glob)
    counts = np.bincount(idx.ravel(), minlength=bins)
    for k in np.flatnonzero(counts >= 500):
        per_bin[k] = float(np.median(dev_med[idx == k]))
    scale = 1.4826 * math.sqrt(n_f / (n_f - 1.0)) * per_bin[idx]
    keep = dev <= np.maximum(OUTLIER_SCALES * scale, 1.0)[None]
    n = keep.sum(axis=0)
    total = np.where(keep, st, np.float32(0.0)).sum(axis=0)
    return np.where(n > 0, total / np.maximum(n, 1), med).astype(np.float32)
