"""Radial lens distortion (OpenCV's model with k1 only): pixel <-> ideal pinhole image.

Edges are measured where they are in the (distorted) frame; undistorting the measured edge
points before the line fits makes the sides straight again, and the corners are mapped back
to the frame, so a wide-angle lens does not bend the result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.config import LensConfig

__all__ = ["Lens"]


@dataclass(frozen=True)
class Lens:
    """Focal length and principal point (px) and the radial coefficient k1 (normalised)."""

    focal_px: float
    principal_px: tuple[float, float]
    k1: float = 0.0

    @classmethod
    def of(cls, cfg: LensConfig) -> Lens:
        """A camera config's ``lens`` (``cameras[].lens``)."""
        return cls(cfg.focal_px, (cfg.principal_px[0], cfg.principal_px[1]), cfg.k1)

    def undistort(self, pts: np.ndarray) -> np.ndarray:
        """Frame pixels (N, 2) -> ideal pinhole pixels."""
        p = np.asarray(pts, float).reshape(-1, 1, 2)
        if self.k1 == 0.0 or p.size == 0:
            return p.reshape(-1, 2).copy()
        cx, cy = self.principal_px
        d = np.stack([(p[:, 0, 0] - cx) / self.focal_px, (p[:, 0, 1] - cy) / self.focal_px])
        # the ideal radius r of r_d = r (1 + k1 r^2), by Newton's method from r_d (to
        # rounding in 3-5 steps; the fixed point x_n = x_d / (1 + k1 r_n^2) took 12-20)
        rd = np.sqrt(d[0] * d[0] + d[1] * d[1])
        r = rd.copy()
        for _ in range(12):
            r2 = r * r
            step = (r * (1.0 + self.k1 * r2) - rd) / (1.0 + 3.0 * self.k1 * r2)
            r -= step
            if float(np.max(np.abs(step))) <= 1e-15:
                break
        scale = np.divide(r, rd, out=np.ones_like(rd), where=rd > 0)
        return np.column_stack([cx + self.focal_px * d[0] * scale,
                                cy + self.focal_px * d[1] * scale])

    def distort(self, pts: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixels (N, 2) -> frame pixels."""
        p = np.asarray(pts, float).reshape(-1, 2)
        if self.k1 == 0.0:
            return p.copy()
        cx, cy = self.principal_px
        xn = (p[:, 0] - cx) / self.focal_px
        yn = (p[:, 1] - cy) / self.focal_px
        s = 1.0 + self.k1 * (xn * xn + yn * yn)
        return np.column_stack([cx + self.focal_px * xn * s, cy + self.focal_px * yn * s])
