"""The solver's answer: a centre with its covariance, and the solve-output contract."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["CentreResult"]


@dataclass
class CentreResult:
    """Centre of rotation in pixel coordinates with a calibrated covariance.

    ``inlier_mask[f, k]`` marks the detections the final fit used; ``outliers`` counts
    detections rejected as gross errors (misses are neither). ``rms_residual_px`` is the rms
per residual component of the inliers (comparable with the per-axis detection noise; for
``circles``/``thesis`` the radial residuals). ``angles_deg`` are the angles
    the fit used: estimated from the images for ``rigid``, the readback otherwise.
    """

    center_px: np.ndarray
    cov_px2: np.ndarray
    method: str
    rms_residual_px: float
    inliers: int
    outliers: int
    inlier_mask: np.ndarray
    angles_deg: np.ndarray
    n_frames: int
    extra: dict[str, Any] = field(default_factory=dict)

    def center_um(self, pixel_size_um: float) -> np.ndarray:
        """Centre in um (same axes and origin as the pixel coordinates)."""
        return np.asarray(self.center_px, dtype=float) * float(pixel_size_um)

    def cov_um2(self, pixel_size_um: float) -> np.ndarray:
        """Covariance in um^2."""
        return np.asarray(self.cov_px2, dtype=float) * float(pixel_size_um) ** 2

    def std_px(self) -> np.ndarray:
        """1-sigma standard deviations along x and y."""
        return np.sqrt(np.diag(self.cov_px2))

    def to_json(self, file: str | None = None,
                pixel_size_um: float | None = None) -> dict[str, Any]:
        """The contract's solve output object (``center_um``/``cov_um2`` with a pixel size)."""
        out: dict[str, Any] = {}
        if file is not None:
            out["file"] = file
        c = np.asarray(self.center_px, dtype=float)
        cov = np.asarray(self.cov_px2, dtype=float)
        out.update({
            "center_px": [float(c[0]), float(c[1])],
            "cov_px2": [[float(cov[0, 0]), float(cov[0, 1])], [float(cov[1, 0]), float(cov[1, 1])]],
            "method": self.method,
            "rms_residual_px": float(self.rms_residual_px),
            "inliers": int(self.inliers),
            "outliers": int(self.outliers),
            "n_frames": int(self.n_frames),
        })
        if pixel_size_um is not None:
            cu = self.center_um(pixel_size_um)
            vu = self.cov_um2(pixel_size_um)
            out["pixel_size_um"] = float(pixel_size_um)
            out["center_um"] = [float(cu[0]), float(cu[1])]
            out["cov_um2"] = [[float(vu[0, 0]), float(vu[0, 1])],
                              [float(vu[1, 0]), float(vu[1, 1])]]
        return out
