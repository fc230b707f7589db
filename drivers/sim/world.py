"""The one simulated world: stage positions set the sample holder's pose.

Frames (all lengths in mm, angles in degrees):
- **lab frame**: origin on the turntable axis at the turntable's top plane, z up; x and y
  are aligned with the top camera's image at zero tilt (x right, y down in the image), so
  the image convention of the design notes holds: turning by +a moves points by R(a).
- **turntable frame**: the lab frame turned by the turntable's true angle.

Everything on the turntable lives in the turntable frame: the platform's x/y axes (not
square to each other), the translator along the sample normal, the holder with its yaw.
Mechanical imperfections (axis wobble, encoder error, backlash, repeatability, camera
tilt) are configurable; the truth (the target point's offset from the axis, yaw, tilt) is
available to tests and to the simulator's report, never to the alignment loop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.config import SimWorldConfig
from drivers.sim.kinematics import SimAxis


def rot2(deg: float) -> np.ndarray:
    """R(a) = [[cos a, -sin a], [sin a, cos a]] of the design notes."""
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


@dataclass(frozen=True)
class PinholeCamera:
    """A pinhole camera: position (mm, lab), rotation (camera-to-lab), focal length (px)."""

    center_mm: np.ndarray  # (3,)
    rot: np.ndarray  # (3, 3) columns = camera x, y, optical axis in lab coordinates
    focal_px: float
    principal_px: tuple[float, float]
    size_px: tuple[int, int] = (1280, 720)

    def project(self, pts_mm: np.ndarray) -> np.ndarray:
        """Project (N, 3) lab points to (N, 2) pixel coordinates."""
        p = (np.asarray(pts_mm, float) - self.center_mm) @ self.rot
        z = p[:, 2]
        return np.column_stack([self.principal_px[0] + self.focal_px * p[:, 0] / z,
                                self.principal_px[1] + self.focal_px * p[:, 1] / z])


def top_camera(cfg: SimWorldConfig, height_mm: float = 800.0,
               azimuth_deg: float = 30.0) -> PinholeCamera:
    """The top camera above the axis, tilted by the configured zenith angle.

    With zero tilt a point on the turntable plane maps to ``axis_px + xy / pixel_size``.
    """
    f = height_mm / (cfg.pixel_size_um / 1000.0)
    # looking down: camera x = lab x, camera y = lab y, optical axis = -z (lab); a camera
    # turned about its optical axis or mirrored (variants of real rigs) changes x and y
    r = math.radians(cfg.camera_rotation_deg)
    cx = np.array([math.cos(r), math.sin(r), 0.0])
    cy = np.array([-math.sin(r), math.cos(r), 0.0])
    if cfg.camera_mirror:
        cx = -cx
    base = np.column_stack([cx, cy, [0, 0, -1.0]])
    z = math.radians(cfg.top_camera_zenith_deg)
    az = math.radians(azimuth_deg)
    axis = np.array([-math.sin(az), math.cos(az), 0.0])  # tilt about this horizontal axis
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = (np.eye(3) + math.sin(z) * K + (1 - math.cos(z)) * K @ K) @ base
    # place the camera so its optical axis still meets the turntable axis at z = 0
    d = rot[:, 2]
    center = (height_mm / -d[2]) * -d
    return PinholeCamera(center_mm=center, rot=rot, focal_px=f,
                         principal_px=(float(cfg.axis_px[0]), float(cfg.axis_px[1])),
                         size_px=cfg.top_frame_px)


@dataclass(frozen=True)
class TopScene:
    """What the top camera sees, in lab mm (for the renderer)."""

    holder_corners_mm: np.ndarray  # (4, 3) top face of the holder, in drawing order
    sample_face_mm: np.ndarray  # (2, 3) ends of the sample surface line (top edge)
    target_mm: np.ndarray  # (3,) middle of the sample surface
    rim_center_mm: np.ndarray  # (3,) turntable rim centre (on the axis, at z = 0)
    rim_radius_mm: float
    turntable_deg: float


@dataclass(frozen=True)
class SideScene:
    """What the side camera sees: line angles from vertical (deg) and positions (mm)."""

    sample_edge_angle_deg: float  # tilt of the sample surface edge, in the image
    pole_angle_deg: float
    sample_x_mm: float
    pole_x_mm: float
    sample_height_mm: tuple[float, float]  # bottom, top (z)


class World:
    """Holder pose from the stage axes; ground truth for tests and the sim's report."""

    HOLDER_TOP_Z_MM = 30.0
    SAMPLE_HEIGHT_MM = 50.0

    def __init__(self, cfg: SimWorldConfig, axes: dict[str, SimAxis],
                 rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.axes = axes
        if cfg.initial_offset_mm is None:
            r = cfg.initial_offset_max_mm * math.sqrt(rng.uniform(0.25, 1.0))
            phi = rng.uniform(0, 2 * math.pi)
            self.offset0 = np.array([r * math.cos(phi), r * math.sin(phi)])
        else:
            self.offset0 = np.asarray(cfg.initial_offset_mm, float)
        self.yaw_deg = (cfg.yaw_deg if cfg.yaw_deg is not None
                        else float(rng.choice([-1, 1]) * rng.uniform(1.0, 2.0)))
        self.mount_deg = float(rng.uniform(-3.0, 3.0))  # stage stack vs turntable zero
        self.wobble_phase = rng.uniform(0, 2 * math.pi, size=2)
        self.encoder_phase = float(rng.uniform(0, 2 * math.pi))
        self.top_camera = top_camera(cfg)

    # ---- stage positions -------------------------------------------------------------
    def _pos(self, role: str, at: float | None = None) -> float:
        ax = self.axes.get(role)
        return ax.load_position(at) if ax is not None else 0.0

    def now(self) -> float:
        """The simulated time (the axes' clock)."""
        ax = next(iter(self.axes.values()), None)
        return ax.clock.now() if ax is not None else 0.0

    def _nominal(self, role: str) -> float:
        """Mid-travel: the stage position at which the configured initial offset holds."""
        ax = self.axes.get(role)
        return (ax.p.travel_min + ax.p.travel_max) / 2 if ax is not None else 0.0

    def turntable_deg(self, at: float | None = None) -> float:
        """True mechanical angle: load position plus a periodic encoder error (``at``: a
        time of the axes' clock, default now; as for every pose below)."""
        a = self._pos("turntable", at)
        true = self.cfg.turntable_direction * self.cfg.turntable_scale * a
        return true + self.cfg.turntable_encoder_error_deg * math.sin(
            math.radians(a) * 3 + self.encoder_phase)

    def wobble_mm(self, angle_deg: float) -> np.ndarray:
        """Radial error motion of the bearing: not a rigid rotation, so not absorbable."""
        a = math.radians(angle_deg)
        w = self.cfg.wobble_um / 1000.0
        return w * np.array([math.cos(2 * a + self.wobble_phase[0]),
                             math.sin(3 * a + self.wobble_phase[1])])

    # ---- geometry in the turntable frame ---------------------------------------------
    def stage_directions(self) -> dict[str, np.ndarray]:
        """Unit vectors (turntable frame) of the x, y and translator motions."""
        m = self.mount_deg
        ex = rot2(m) @ np.array([1.0, 0.0])
        ey = rot2(m + self.cfg.stage_skew_deg) @ np.array([0.0, 1.0])
        et = rot2(self.yaw_deg + self.cfg.translator_skew_deg) @ np.array([0.0, -1.0])
        # the config's roles as wired: swapped cables, a motor turning the other way
        if self.cfg.swap_xy:
            ex, ey = ey, ex
        if self.cfg.invert_x:
            ex = -ex
        if self.cfg.invert_y:
            ey = -ey
        return {"x": ex, "y": ey, "translator": et}

    def holder_center_tt(self, at: float | None = None) -> np.ndarray:
        """Holder centre in the turntable frame (mm)."""
        d = self.stage_directions()
        c = self.offset0 - self._holder_to_target_tt()
        for role in ("x", "y", "translator"):
            c = c + d[role] * (self._pos(role, at) - self._nominal(role))
        return c

    def _holder_to_target_tt(self) -> np.ndarray:
        _w, depth = self.cfg.holder_size_mm
        return rot2(self.yaw_deg) @ np.array([0.0, -(depth / 2 + self.cfg.sample_thickness_mm)])

    def holder_corners_tt(self, at: float | None = None) -> np.ndarray:
        w, depth = self.cfg.holder_size_mm
        local = np.array([[-w / 2, -depth / 2], [w / 2, -depth / 2], [w / 2, depth / 2],
                          [-w / 2, depth / 2]])
        return self.holder_center_tt(at) + local @ rot2(self.yaw_deg).T

    def target_tt(self, at: float | None = None) -> np.ndarray:
        """The middle of the sample surface, turntable frame (mm)."""
        return self.holder_center_tt(at) + self._holder_to_target_tt()

    # ---- lab frame -------------------------------------------------------------------
    def to_lab(self, pts_tt: np.ndarray, z: float, at: float | None = None) -> np.ndarray:
        a = self.turntable_deg(at)
        xy = np.atleast_2d(pts_tt) @ rot2(a).T + self.wobble_mm(a)
        return np.column_stack([xy, np.full(len(xy), z)])

    def top_scene(self, at: float | None = None) -> TopScene:
        """What the top camera sees at time ``at`` (default now)."""
        z = self.HOLDER_TOP_Z_MM + self._pos("z", at) - self._nominal("z")
        w, depth = self.cfg.holder_size_mm
        c = self.holder_center_tt(at)
        face = c + np.array([[-w / 2, -depth / 2 - self.cfg.sample_thickness_mm],
                             [w / 2, -depth / 2 - self.cfg.sample_thickness_mm]]) @ rot2(
            self.yaw_deg).T
        a = self.turntable_deg(at)
        return TopScene(
            holder_corners_mm=self.to_lab(self.holder_corners_tt(at), z, at),
            sample_face_mm=self.to_lab(face, z, at),
            target_mm=self.to_lab(self.target_tt(at), z, at)[0],
            rim_center_mm=np.array([*self.wobble_mm(a), 0.0]),
            rim_radius_mm=self.cfg.rim_radius_mm,
            turntable_deg=a,
        )

    def side_scene(self) -> SideScene:
        """Side view along the sample surface: its edge leans by the tilt; the pole is true."""
        tgt = self.to_lab(self.target_tt(), 0.0)[0]
        return SideScene(sample_edge_angle_deg=self.cfg.tilt_deg, pole_angle_deg=0.0,
                         sample_x_mm=float(tgt[1]), pole_x_mm=-40.0,
                         sample_height_mm=(self.HOLDER_TOP_Z_MM - self.SAMPLE_HEIGHT_MM + 30,
                                           self.HOLDER_TOP_Z_MM + 20))

    # ---- truth -----------------------------------------------------------------------
    def truth(self) -> dict[str, object]:
        """Ground truth for tests and the simulator's labelled ``truth`` block."""
        off = self.target_tt() * 1000.0
        return {"offset_um": [float(off[0]), float(off[1])],
                "offset_norm_um": float(np.hypot(*off)),
                "yaw_deg": self.yaw_deg, "tilt_deg": self.cfg.tilt_deg}
