"""Synthetic sweeps with known truth, for tests, benchmarks and the simulator's checks.

The default geometry is the thesis prototype: a 60 x 40 mm holder seen at 160 um/px
(375 x 250 px), its four corners tracked while the turntable sweeps -10 to +10 deg, the
holder centre a few mm off the axis, 0.3 px detection noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sweep import Sweep

__all__ = ["SyntheticTruth", "holder_corners", "make_sweep", "project"]


@dataclass(frozen=True)
class SyntheticTruth:
    """What generated a synthetic sweep."""

    center_px: np.ndarray        # (2,) rotation centre
    template_px: np.ndarray      # (K, 2) feature positions at angle 0
    angles_deg: np.ndarray       # (F,) true turntable angles
    outlier_mask: np.ndarray     # (F, K) points replaced by gross errors
    missing_mask: np.ndarray     # (F, K) points reported as missed
    noise_px: float


def holder_corners(center_px: np.ndarray, holder_offset_px: np.ndarray, size_px: np.ndarray,
                   yaw_deg: float) -> np.ndarray:
    """The four corners of a rectangle (at angle 0), in image order TL, TR, BR, BL."""
    hw, hh = size_px[0] / 2.0, size_px[1] / 2.0
    loc = np.array([[-hw, -hh], [hw, -hh], [hw, hh], [-hw, hh]])
    y = np.deg2rad(yaw_deg)
    R = np.array([[np.cos(y), -np.sin(y)], [np.sin(y), np.cos(y)]])
    return center_px + holder_offset_px + loc @ R.T


def project(center_px: np.ndarray, template_px: np.ndarray, angles_deg: np.ndarray) -> np.ndarray:
    """Noise-free points (F, K, 2): p = c + R(a) (q - c), y-down convention."""
    a = np.deg2rad(np.asarray(angles_deg, dtype=float))
    cs, sn = np.cos(a)[:, None], np.sin(a)[:, None]
    d = template_px - center_px
    x = cs * d[None, :, 0] - sn * d[None, :, 1]
    y = sn * d[None, :, 0] + cs * d[None, :, 1]
    return np.stack([x, y], axis=-1) + center_px


def make_sweep(n_frames: int = 21, sweep_deg: float = 10.0, *,
               center_px: tuple[float, float] = (640.0, 360.0),
               holder_size_mm: tuple[float, float] = (60.0, 40.0),
               holder_offset_mm: tuple[float, float] = (3.0, -2.0),
               holder_yaw_deg: float = 4.0,
               pixel_size_um: float = 160.0,
               noise_px: float = 0.3,
               outlier_fraction: float = 0.0,
               outlier_px: tuple[float, float] = (5.0, 60.0),
               miss_fraction: float = 0.0,
               readback_scale_error: float = 0.0,
               readback_offset_deg: float = 0.0,
               readback_noise_deg: float = 0.0,
               template_px: np.ndarray | None = None,
               seed: int | np.random.Generator = 0) -> tuple[Sweep, SyntheticTruth]:
    """A sweep from -sweep_deg to +sweep_deg with its truth.

    ``outlier_fraction`` of the detections are moved by a random 5-60 px (gross tracking
    errors); ``miss_fraction`` are reported as missed (NaN). The readback may carry a scale
    error, an offset and noise, as an imperfect turntable would; the points always follow
    the true angles. ``template_px`` replaces the holder corners with arbitrary features.
    """
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    c = np.asarray(center_px, dtype=float)
    px_mm = 1000.0 / pixel_size_um
    if template_px is None:
        q = holder_corners(c, np.asarray(holder_offset_mm) * px_mm,
                           np.asarray(holder_size_mm) * px_mm, holder_yaw_deg)
    else:
        q = np.asarray(template_px, dtype=float)
    angles = np.linspace(-sweep_deg, sweep_deg, n_frames)
    pts = project(c, q, angles) + rng.normal(0.0, noise_px, (n_frames, len(q), 2))
    out = rng.random((n_frames, len(q))) < outlier_fraction
    n_out = int(out.sum())
    if n_out:
        mag = rng.uniform(outlier_px[0], outlier_px[1], n_out)
        ang = rng.uniform(0, 2 * np.pi, n_out)
        pts[out] += np.stack([mag * np.cos(ang), mag * np.sin(ang)], axis=-1)
    miss = rng.random((n_frames, len(q))) < miss_fraction
    pts[miss] = np.nan
    out &= ~miss
    readback = (angles * (1.0 + readback_scale_error) + readback_offset_deg
                + rng.normal(0.0, readback_noise_deg, n_frames) if readback_noise_deg
                else angles * (1.0 + readback_scale_error) + readback_offset_deg)
    sweep = Sweep(angles_deg=readback, points=pts, pixel_size_um=pixel_size_um)
    truth = SyntheticTruth(center_px=c, template_px=q, angles_deg=angles, outlier_mask=out,
                           missing_mask=miss, noise_px=noise_px)
    return sweep, truth
