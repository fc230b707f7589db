"""Report overlays: tracked paths, the fitted centre with its uncertainty ellipse, bisectors,
the rim ellipse and the side camera's lines, drawn on a copy of a frame (BGR out).

Drawing uses OpenCV's fixed-point coordinates (``shift``) so sub-pixel positions are drawn
where they are, not rounded to the nearest pixel.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from alignd.vision.rim import RimFit
from alignd.vision.side import SideMeasurement

__all__ = ["draw_centre", "draw_paths", "draw_rim", "draw_side", "to_bgr"]

_SHIFT = 4
_ONE = 1 << _SHIFT
COLOURS = [(0, 200, 255), (0, 255, 0), (255, 128, 0), (255, 0, 255), (0, 128, 255)]


def to_bgr(image: np.ndarray) -> np.ndarray:
    """A uint8 BGR copy of a grey or BGR image."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    return img[:, :, :3].copy()


def _fx(p: Sequence[float] | np.ndarray) -> tuple[int, int]:
    return round(p[0] * _ONE), round(p[1] * _ONE)


def draw_paths(image: np.ndarray, paths: np.ndarray, *, radius: float = 2.0) -> np.ndarray:
    """Feature paths (frames, features, 2) px, one colour per feature; NaN points skipped."""
    out = to_bgr(image)
    paths = np.asarray(paths, float)
    for k in range(paths.shape[1]):
        col = COLOURS[k % len(COLOURS)]
        pts = paths[:, k]
        good = np.all(np.isfinite(pts), axis=1)
        for a, b in zip(pts[:-1][good[:-1] & good[1:]], pts[1:][good[:-1] & good[1:]],
                        strict=True):
            cv2.line(out, _fx(a), _fx(b), col, 1, cv2.LINE_AA, _SHIFT)
        for p in pts[good]:
            cv2.circle(out, _fx(p), int(radius * _ONE), col, 1, cv2.LINE_AA, _SHIFT)
    return out


def draw_centre(image: np.ndarray, center_px: Sequence[float], cov_px2: np.ndarray | None = None,
                *, k_sigma: float = 2.0, magnify: float = 1.0,
                bisectors: Sequence[tuple[Sequence[float], Sequence[float]]] = (),
                colour: tuple[int, int, int] = (0, 0, 255)) -> np.ndarray:
    """The fitted centre (cross), its k-sigma uncertainty ellipse (scaled by ``magnify``
    so a 0.05 px ellipse can be seen) and optional bisectors (point, direction) pairs."""
    out = to_bgr(image)
    c = np.asarray(center_px, float)
    h, w = out.shape[:2]
    for p_in, d_in in bisectors:
        p = np.asarray(p_in, float)
        d = np.asarray(d_in, float)
        d = d / (np.linalg.norm(d) or 1.0)
        L = float(w + h)
        cv2.line(out, _fx(p - L * d), _fx(p + L * d), (160, 160, 160), 1, cv2.LINE_AA, _SHIFT)
    arm = 8.0
    dx, dy = np.array([arm, 0.0]), np.array([0.0, arm])
    cv2.line(out, _fx(c - dx), _fx(c + dx), colour, 1, cv2.LINE_AA, _SHIFT)
    cv2.line(out, _fx(c - dy), _fx(c + dy), colour, 1, cv2.LINE_AA, _SHIFT)
    if cov_px2 is not None:
        vals, vecs = np.linalg.eigh(np.asarray(cov_px2, float))
        vals = np.clip(vals, 0, None)
        ax = k_sigma * magnify * np.sqrt(vals)
        ang = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
        cv2.ellipse(out, _fx(c), (max(int(ax[1] * _ONE), 1), max(int(ax[0] * _ONE), 1)), ang,
                    0, 360, colour, 1, cv2.LINE_AA, _SHIFT)
        if magnify != 1.0:
            cv2.putText(out, f"x{magnify:g}", (int(c[0]) + 10, int(c[1]) - 10),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, 1, cv2.LINE_AA)
    return out


def draw_rim(image: np.ndarray, fit: RimFit, colour: tuple[int, int, int] = (255, 200, 0)
             ) -> np.ndarray:
    """The fitted rim ellipse, its centre and its eccentricity."""
    out = to_bgr(image)
    a, b = fit.axes_px
    cv2.ellipse(out, _fx(fit.center_px), (int(a * _ONE), int(b * _ONE)), fit.angle_deg, 0, 360,
                colour, 1, cv2.LINE_AA, _SHIFT)
    cv2.drawMarker(out, (round(fit.center_px[0]), round(fit.center_px[1])), colour,
                   cv2.MARKER_CROSS, 10, 1)
    cv2.putText(out, f"e = {fit.eccentricity:.4f}", (10, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                colour, 1, cv2.LINE_AA)
    return out


def draw_side(image: np.ndarray, m: SideMeasurement) -> np.ndarray:
    """The side camera's fitted sample (red) and pole (green) lines and the tilt."""
    out = to_bgr(image)
    h = out.shape[0]
    for edges, col in ((m.sample_edges, (0, 0, 255)), (m.pole_edges, (0, 255, 0))):
        for e in edges:
            y0, y1 = max(e.rows[0], 0), min(e.rows[1], h - 1)
            p0 = (float(e.line.minor_at(y0)), float(y0))
            p1 = (float(e.line.minor_at(y1)), float(y1))
            cv2.line(out, _fx(p0), _fx(p1), col, 1, cv2.LINE_AA, _SHIFT)
    cv2.putText(out, f"tilt = {m.tilt_deg:+.4f} deg", (10, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                (0, 0, 255), 1, cv2.LINE_AA)
    return out
