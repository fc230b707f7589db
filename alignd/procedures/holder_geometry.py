"""The holder frame in one top image: its centre, axes, scale and the target point.

The holder frame (docs/configure.md) has its origin at the four corners' centre, u along
corner 0 -> 1 and v towards corner 3. Its scale comes from the holder's own size, so the
target lands right even though the holder's top face is nearer the camera than the
turntable plane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from alignd.config import HolderConfig
from alignd.errors import VisionError


def turned(target_mm: tuple[float, float], quarter_turns: int) -> tuple[float, float]:
    """A holder-frame point turned by quarter turns (u towards v), as a camera turned the
    other way by as much numbers it (no -0.0: the values are printed in messages)."""
    tu, tv = target_mm
    u, v = {0: (tu, tv), 1: (-tv, tu), 2: (-tu, -tv), 3: (tv, -tu)}[quarter_turns % 4]
    return u + 0.0, v + 0.0


def rot(deg: float | np.ndarray) -> np.ndarray:
    """R(a) of the design notes; stacked (N, 2, 2) for an array of angles."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


@dataclass(frozen=True)
class HolderPoses:
    """The holder in n images (a continuous sweep has hundreds), from their corners."""

    center_px: np.ndarray  # (n, 2): the corners' centre
    u_hat: np.ndarray  # (n, 2): along corner 0 -> 1 (the holder's u axis)
    v_hat: np.ndarray  # (n, 2): perpendicular, towards corner 3
    target_px: np.ndarray  # (n, 2)
    scale_px_per_mm: np.ndarray  # (n,)
    angle_deg: np.ndarray  # (n,): direction of u in the image

    def at(self, target_mm: tuple[float, float]) -> np.ndarray:
        """(n, 2): another point of the holder frame (mm) in each image."""
        tu, tv = target_mm
        return self.center_px + self.scale_px_per_mm[:, None] * (tu * self.u_hat
                                                                 + tv * self.v_hat)


@dataclass(frozen=True)
class HolderPose:
    """The holder in one image."""

    center_px: np.ndarray
    u_hat: np.ndarray
    v_hat: np.ndarray
    scale_px_per_mm: float
    angle_deg: float
    target_px: np.ndarray


def holder_poses(corners: np.ndarray, holder: HolderConfig) -> HolderPoses:
    """The holder frame and target point of (n, 4, 2) corners in the tracker's order (all
    finite)."""
    c = np.asarray(corners, float).reshape(-1, 4, 2)
    u_vec = ((c[:, 1] - c[:, 0]) + (c[:, 2] - c[:, 3])) / 2
    v_vec = ((c[:, 3] - c[:, 0]) + (c[:, 2] - c[:, 1])) / 2
    su, sv = holder.size_mm
    nu, nv = np.hypot(*u_vec.T), np.hypot(*v_vec.T)
    if np.any(nu == 0) or np.any(nv == 0):
        raise VisionError("degenerate holder corners (zero-length edge)")
    u_hat = u_vec / nu[:, None]
    v_perp = v_vec - u_hat * np.sum(u_hat * v_vec, axis=1)[:, None]
    v_hat = v_perp / np.hypot(*v_perp.T)[:, None]
    scale = (nu / su + nv / sv) / 2
    tu, tv = holder.target_mm
    centre = c.mean(axis=1)
    target = centre + scale[:, None] * (tu * u_hat + tv * v_hat)
    return HolderPoses(centre, u_hat, v_hat, target, scale,
                       np.degrees(np.arctan2(u_hat[:, 1], u_hat[:, 0])))


def holder_pose(corners: np.ndarray, holder: HolderConfig) -> HolderPose:
    """``holder_poses`` of one image's four corners."""
    p = holder_poses(np.asarray(corners, float)[None], holder)
    return HolderPose(p.center_px[0], p.u_hat[0], p.v_hat[0], float(p.scale_px_per_mm[0]),
                      float(p.angle_deg[0]), p.target_px[0])
