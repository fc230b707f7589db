"""The measuring functions a procedure uses, injectable so tests can stand in for them.

``default_tools()`` binds the real vision (``alignd.vision``) and solver (``alignd.solve``);
tests may pass their own (e.g. a tracker projecting the simulated world's corners).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from alignd.config import AligndConfig
from drivers.camera import Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Corners:
    """A holder detection reduced to what the procedure needs."""

    corners_px: np.ndarray  # (4, 2), the tracker's consistent order
    ok: bool
    quality: float = 1.0
    reason: str = ""


TrackFn = Callable[[Frame], Corners]
SolveFn = Callable[[np.ndarray, np.ndarray, float | None], Any]  # angles, points, px -> result
ScalarFn = Callable[[Frame], float]


@dataclass
class Tools:
    """track: frame -> corners; solve: (angles, points, pixel size) -> centre result
    (``center_px``, ``cov_px2``, ``rms_residual_px``, ``inliers``, ``outliers``);
    tilt: side frame -> sample tilt (deg); eccentricity: top frame -> rim eccentricity."""

    track: TrackFn
    solve: SolveFn
    tilt: ScalarFn | None = None
    eccentricity: ScalarFn | None = None
    names: dict[str, str] | None = None


def expected_holder_px(cfg: AligndConfig) -> tuple[float, float] | None:
    """The holder's long and short side in top-camera px, from ``holder.size_mm`` and the
    top camera's ``pixel_size_um`` (None when the pixel size is not configured)."""
    cam = cfg.camera("top")
    px = cam.pixel_size_um if cam is not None else None
    if px is None and cfg.sim is not None:
        px = cfg.sim.world.pixel_size_um
    if px is None:
        return None
    a, b = cfg.holder.size_mm
    return (max(a, b) * 1000.0 / px, min(a, b) * 1000.0 / px)


def as_corners(det: Any) -> Corners:
    """Normalise a vision ``HolderDetection`` (or anything with ``corners_px``/``ok``)."""
    ok = bool(getattr(det, "ok", True))
    corners = getattr(det, "corners_px", None)
    if corners is None:
        return Corners(np.full((4, 2), np.nan), False, 0.0, "no corners")
    c = np.asarray(corners, float).reshape(-1, 2)
    if c.shape != (4, 2) or not np.all(np.isfinite(c)):
        ok = False
    quality = float(getattr(det, "quality", 1.0) or 0.0)
    return Corners(c if c.shape == (4, 2) else np.full((4, 2), np.nan), ok, quality,
                   str(getattr(det, "reason", "") or ""))


def default_tools(cfg: AligndConfig | None = None) -> Tools:
    """The real vision and solver (imported here, so the procedures load without them).

    With a config the tracker knows the holder's size in px (``holder.size_mm`` and the top
    camera's ``pixel_size_um``: a target of another size is never taken for the holder)
    and seeds each frame's search with the previous frame's corners; the side camera's
    regions of interest come from ``side_camera``.
    """
    from alignd import solve as solver
    from alignd.errors import StateError, VisionError

    try:
        from alignd import vision
    except ImportError as exc:
        raise StateError(f"alignd.vision cannot be imported: {exc}") from exc
    missing = [n for n in ("track_holder", "measure_tilt", "fit_rim") if not hasattr(vision, n)]
    if missing or not hasattr(solver, "solve_centre"):
        raise StateError("measuring functions missing: "
                         + ", ".join([f"alignd.vision.{n}" for n in missing]
                                     + ([] if hasattr(solver, "solve_centre")
                                        else ["alignd.solve.solve_centre"])))
    expected = expected_holder_px(cfg) if cfg is not None else None
    side = cfg.side_camera if cfg is not None else None
    last: list[np.ndarray] = []  # the previous frame's corners (tracking seed)

    def track(frame: Frame) -> Corners:
        hint = last[0] if last else None
        try:
            det = vision.track_holder(frame.gray, expected_size_px=expected, hint=hint)
        except VisionError as exc:
            return Corners(np.full((4, 2), np.nan), False, 0.0, str(exc))
        out = as_corners(det)
        if out.ok:
            last[:] = [out.corners_px]
        return out

    def solve(angles: np.ndarray, points: np.ndarray, pixel_size_um: float | None) -> Any:
        sweep = solver.Sweep(angles_deg=np.asarray(angles, float),
                             points=np.asarray(points, float), pixel_size_um=pixel_size_um)
        return solver.solve_centre(sweep, method="auto")

    def tilt(frame: Frame) -> float:
        res = vision.measure_tilt(frame.gray,
                                  pole_roi_px=side.pole_roi_px if side else None,
                                  sample_roi_px=side.sample_roi_px if side else None)
        return float(getattr(res, "tilt_deg", res))

    def eccentricity(frame: Frame) -> float:
        res = vision.fit_rim(frame.gray)
        return float(getattr(res, "eccentricity", res))

    return Tools(track=track, solve=solve, tilt=tilt, eccentricity=eccentricity,
                 names={"track": "alignd.vision.track_holder",
                        "solve": "alignd.solve.solve_centre(auto)",
                        "tilt": "alignd.vision.measure_tilt",
                        "eccentricity": "alignd.vision.fit_rim"})
