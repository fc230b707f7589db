"""Stage-to-image calibration: how a move of each correction axis shows up in the image.

The correction axes ride on the turntable and need not be square to each other or to the
image, and the holder's top face is nearer the camera than the turntable plane, so the
mapping is learnt, not assumed: at a known turntable angle each axis makes small moves
(+step, -step, back) while the holder is tracked; a straight-line fit of the holder centre
against the read-back position gives that axis' image direction and length in px/mm.
Expressed at turntable angle 0 (``J``), it maps stage moves to offset changes in the
turntable frame at any angle, because the stages turn with the table.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from alignd.config import AligndConfig
from alignd.errors import AligndError, VisionError
from alignd.procedures.events import ProgressCallback, ProgressEvent
from alignd.procedures.holder_geometry import rot
from alignd.procedures.recorder import RunRecorder
from alignd.procedures.rig import Rig, check_abort
from alignd.procedures.sweep import grab_fresh
from alignd.procedures.tools import Tools

log = logging.getLogger(__name__)

MIN_AXIS_SINE = 0.5  # the two axes must be at least 30 deg from parallel


class CalibrationError(AligndError):
    """The stage-to-image mapping is implausible (stuck stage, wrong role, wrong scale)."""


@dataclass
class Calibration:
    """``J[:, k]`` = image displacement (px, turntable frame at angle 0) per mm of axis k."""

    roles: tuple[str, str]
    angle_deg: float  # turntable read-back during the calibration moves
    J: np.ndarray
    residual_px: float  # rms residual of the straight-line fits
    sigma_rel: float  # relative 1-sigma uncertainty of the columns
    refreshes: int = 0
    updates: int = 0

    @property
    def pixel_size_um(self) -> float:
        """Apparent pixel size at the holder's face: 1000 / mean column length."""
        return 1000.0 / float(np.mean(np.hypot(self.J[0], self.J[1])))

    @property
    def axis_angles_deg(self) -> tuple[float, float]:
        """Direction of each axis in the turntable frame (image axes, y down)."""
        a = np.degrees(np.arctan2(self.J[1], self.J[0]))
        return float(a[0]), float(a[1])

    @property
    def skew_deg(self) -> float:
        """Deviation of the angle between the two axes from 90 deg."""
        a0, a1 = self.axis_angles_deg
        return float(((a1 - a0 + 180.0) % 360.0 - 180.0) - math.copysign(90.0, a1 - a0))

    def step_for(self, offset_px: np.ndarray) -> np.ndarray:
        """Stage moves (mm, per role) that bring an offset (px, turntable frame) to zero."""
        return -np.linalg.solve(self.J, np.asarray(offset_px, float))

    def predict(self, ds_mm: np.ndarray) -> np.ndarray:
        """Offset change (px, turntable frame) a stage move should cause."""
        return self.J @ np.asarray(ds_mm, float)

    def update(self, ds_mm: np.ndarray, observed_px: np.ndarray) -> None:
        """Broyden rank-one update from a well-determined correction move."""
        ds = np.asarray(ds_mm, float)
        resid = np.asarray(observed_px, float) - self.J @ ds
        self.J = self.J + np.outer(resid, ds) / float(ds @ ds)
        self.updates += 1

    def to_dict(self) -> dict[str, Any]:
        return {"roles": list(self.roles), "angle_deg": self.angle_deg,
                "J_px_per_mm": self.J.tolist(), "pixel_size_um": self.pixel_size_um,
                "axis_angles_deg": list(self.axis_angles_deg), "skew_deg": self.skew_deg,
                "residual_px": self.residual_px, "sigma_rel": self.sigma_rel,
                "refreshes": self.refreshes, "updates": self.updates}


def _plan(base: float, step: float, lo: float, hi: float) -> list[float]:
    """+step, -step, back to base; shifted inside the soft limits when near an end."""
    plan = [base + step, base - step, base]
    if plan[0] > hi:
        plan = [base - step, base - 2 * step, base]
    elif plan[1] < lo:
        plan = [base + step, base + 2 * step, base]
    if any(not lo <= p <= hi for p in plan):
        raise CalibrationError(f"no room for calibration moves of {step:g} mm around "
                               f"{base:.4f} within the soft limits [{lo:g}, {hi:g}]")
    return plan


def configured_pixel_size_um(cfg: AligndConfig) -> float | None:
    cam = cfg.camera("top")
    if cam is not None and cam.pixel_size_um is not None:
        return cam.pixel_size_um
    return cfg.sim.world.pixel_size_um if cfg.sim is not None else None


def calibrate(rig: Rig, cfg: AligndConfig, tools: Tools, *, abort: threading.Event | None,
              progress: ProgressCallback, recorder: RunRecorder, frames_per_position: int = 2,
              angle_deg: float = 0.0, refreshes: int = 0) -> Calibration:
    """Learn ``J`` with small moves of each correction axis at turntable ``angle_deg``."""
    p = cfg.procedure
    roles = tuple(p.correction_axes)
    tt = rig.axis("turntable")
    cam = rig.camera("top")
    assert cam is not None
    check_abort(abort)
    a_cal = tt.move_to(angle_deg)
    columns: list[np.ndarray] = []
    residuals: list[float] = []
    sig: list[float] = []
    frames_json: list[dict[str, Any]] = []
    commanded: list[float] = []
    readback: list[float] = []
    total = len(roles) * 4 * frames_per_position
    step_no = 0
    for role in roles:
        ax = rig.axis(role)
        base = ax.position()
        lim = ax.config.soft_limits
        targets = [None, *_plan(base, p.calibration_step_mm, lim.min, lim.max)]
        s_list: list[float] = []
        c_list: list[np.ndarray] = []
        for target in targets:
            check_abort(abort)
            pos = ax.position() if target is None else ax.move_to(target)
            for _ in range(frames_per_position):
                frame = grab_fresh(cam, cam.clock.now())
                det = tools.track(frame)
                step_no += 1
                recorder.frame(frame.image, f"calibration-{role}-{step_no:03d}")
                commanded.append(float(base if target is None else target))
                readback.append(float(pos))
                frames_json.append({"angle_deg": float(a_cal), "features": (
                    [[float(x), float(y)] for x, y in det.corners_px] if det.ok
                    else [None] * 4)})
                if det.ok:
                    s_list.append(pos)
                    c_list.append(det.corners_px.mean(axis=0))
                progress(ProgressEvent("calibrate", f"calibrating {role} at {pos:.4f} mm",
                                       step=step_no, total=total))
        if len(set(np.round(s_list, 6))) < 2 or len(s_list) < 3:
            raise VisionError(f"calibration of {role}: holder tracked in only {len(s_list)} "
                              f"of {4 * frames_per_position} frames; no correction possible")
        s = np.asarray(s_list)
        c = np.asarray(c_list)
        X = np.column_stack([np.ones_like(s), s - s.mean()])
        coef, *_ = np.linalg.lstsq(X, c, rcond=None)
        res = c - X @ coef
        dof = max(len(s) - 2, 1)
        s2 = float((res**2).sum() / (2 * dof))
        slope = coef[1]
        slope_sigma = math.sqrt(s2 / float(((s - s.mean()) ** 2).sum()))
        columns.append(slope)
        residuals.append(math.sqrt(float((res**2).mean())))
        sig.append(slope_sigma / max(float(np.hypot(*slope)), 1e-12))
        log.info("calibration %s: %.3f px/mm at %.2f deg (image), sigma %.2g rel",
                 role, float(np.hypot(*slope)),
                 math.degrees(math.atan2(slope[1], slope[0])), sig[-1])
    recorder.sweep("calibration", 0, {"version": 1, "pixel_size_um": None,
                                      "frames": frames_json}, commanded, readback)
    J = rot(-a_cal) @ np.column_stack(columns)
    cal = Calibration(roles=(roles[0], roles[1]), angle_deg=float(a_cal), J=J,
                      residual_px=float(np.sqrt(np.mean(np.square(residuals)))),
                      sigma_rel=float(max(sig)), refreshes=refreshes)
    check_calibration(cal, configured_pixel_size_um(cfg), p.pixel_size_tolerance)
    recorder.event(f"calibration: pixel size {cal.pixel_size_um:.2f} um/px at the holder face, "
                   f"axis angles {cal.axis_angles_deg[0]:.2f}/{cal.axis_angles_deg[1]:.2f} deg, "
                   f"skew {cal.skew_deg:+.2f} deg")
    return cal


def check_calibration(cal: Calibration, configured_um: float | None, tolerance: float) -> None:
    """Refuse a mapping that cannot be right: wrong scale per axis, or axes near parallel."""
    for k, role in enumerate(cal.roles):
        length = float(np.hypot(*cal.J[:, k]))
        if length <= 0:
            raise CalibrationError(f"calibration: moving {role} did not move the holder "
                                   "in the image (stage stuck or wrong axis role?)")
        if configured_um is not None:
            px_um = 1000.0 / length
            if abs(px_um / configured_um - 1.0) > tolerance:
                raise CalibrationError(
                    f"calibration: axis {role} gives {px_um:.1f} um/px, the top camera is "
                    f"configured for {configured_um:g} um/px (tolerance "
                    f"{tolerance:.0%}): stage scale, axis role or camera config is wrong")
    a, b = cal.J[:, 0], cal.J[:, 1]
    sine = abs(float(a[0] * b[1] - a[1] * b[0])) / float(np.hypot(*a) * np.hypot(*b))
    if sine < MIN_AXIS_SINE:
        raise CalibrationError(f"calibration: axes {cal.roles[0]} and {cal.roles[1]} move the "
                               f"holder in nearly the same direction (sin {sine:.2f})")
