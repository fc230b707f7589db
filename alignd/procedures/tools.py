"""The measuring functions a procedure uses, injectable so tests can stand in for them.

``default_tools()`` binds the real vision (``alignd.vision``) and solver (``alignd.solve``);
tests may pass their own (e.g. a tracker projecting the simulated world's corners).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from alignd.config import AligndConfig
from drivers.camera import Frame

if TYPE_CHECKING:  # the solver is imported by default_tools, when it is used
    from alignd.solve.result import CentreResult

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Corners:
    """A holder detection reduced to what the procedure needs."""

    corners_px: np.ndarray  # (4, 2), the tracker's consistent order
    ok: bool
    quality: float = 1.0
    reason: str = ""
    warning: str = ""  # found, but the operator should know (clipped all round, faint)
    faint: bool = False  # found only by the tracker's fainter second search (its warning says)


@dataclass(frozen=True)
class RimInfo:
    """The turntable rim in a top frame: ellipse centre, eccentricity, camera zenith."""

    center_px: tuple[float, float]
    eccentricity: float
    zenith_deg: float | None  # None without the rim radius and camera height
    eccentricity_u: float | None = None  # standard uncertainty of e (k = 1)


@dataclass(frozen=True)
class CameraInfo:
    """What a camera does to its frames, read from a still view's (alignd.vision.
    camera_check): its tone curve with its standard uncertainty (None: not measured), the
    camera settings to change (each "what: advice"; the tone curve apart, which only the
    config can judge), and every number and finding for the record."""

    gamma: float | None
    gamma_u: float | None
    gamma_range: tuple[float, float] | None  # every gamma the noise allows (3 sigma)
    text: str  # the curve as measured ("gamma 2.21 +- 0.04", "gamma 0.9-2.1")
    act: list[str]
    record: dict[str, object]


@dataclass(frozen=True)
class SideInfo:
    """The side camera's view: both targets found, their angles and positions."""

    tilt_deg: float
    sample_angle_deg: float
    pole_angle_deg: float
    sample_x_px: float
    pole_x_px: float


class Detection(Protocol):
    """What a holder tracker reports: ``alignd.vision.HolderDetection`` or the simulator's
    ``SceneDetection`` (read-only attributes)."""

    @property
    def ok(self) -> bool: ...

    @property
    def corners_px(self) -> np.ndarray: ...

    @property
    def quality(self) -> float: ...

    @property
    def reason(self) -> str: ...


@dataclass(frozen=True)
class RimReading:
    """The top camera's rim eccentricity from one or more frames, and its uncertainty."""

    eccentricity: float
    u: float | None  # standard uncertainty (k = 1); None when the tool cannot say
    frames: int = 1


@dataclass(frozen=True)
class TiltReading:
    """The sample tilt from one or more side frames: value and standard uncertainty."""

    tilt_deg: float
    u_deg: float | None  # None when the tool cannot say
    frames: int = 1
    stop: str = ""  # why no more frames were taken (a target uncertainty's frame taking)
    # JPEG-coded frames (a camera streaming MJPEG): the quality found and the coding's
    # bias taken off the tilt (deg); None for raw frames
    jpeg_quality: int | None = None
    jpeg_bias_deg: float | None = None


TrackFn = Callable[[Frame], Corners]
SolveFn = Callable[[np.ndarray, np.ndarray, float | None], "CentreResult"]  # angles, points, px
ScalarFn = Callable[[Frame], float]
MoreFrames = Callable[[int], list[Frame]]  # k -> k further frames of the same still view


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
    rim: Callable[[list[Frame], float | None, float | None], RimInfo] | None = None
    side: Callable[[Frame], SideInfo] | None = None
    # several frames at once; with MoreFrames, more of them while the tilt is uncertain
    tilt_frames: Callable[[list[Frame], MoreFrames | None], TiltReading] | None = None
    # a still view's frames as the camera delivered them -> what it does to them
    camera: Callable[[list[Frame]], CameraInfo] | None = None


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


SIZE_TOLERANCE = 0.12  # a detection this far off the holder's expected size is not it


def size_checked(c: Corners, expected_px: tuple[float, float],
                 tolerance: float = SIZE_TOLERANCE) -> Corners:
    """``c``, or not ok with the reason when its sides are more than ``tolerance`` off the
    holder's expected long and short side (px): a rectangle of another size is never taken
    for the holder."""
    p = np.asarray(c.corners_px, float)
    sides = np.linalg.norm(p - np.roll(p, -1, axis=0), axis=1)
    pair_a, pair_b = (sides[0] + sides[2]) / 2, (sides[1] + sides[3]) / 2
    long_px, short_px = max(pair_a, pair_b), min(pair_a, pair_b)
    if (abs(long_px / expected_px[0] - 1) <= tolerance
            and abs(short_px / expected_px[1] - 1) <= tolerance):
        return c
    return Corners(c.corners_px, False, c.quality,
                   f"rectangle of {long_px:.0f} x {short_px:.0f} px where holder.size_mm and "
                   f"the pixel size expect {expected_px[0]:.0f} x {expected_px[1]:.0f} px "
                   f"(+-{100 * tolerance:.0f} %): not the holder")


def as_corners(det: Detection) -> Corners:
    """Normalise a holder detection; corners that are not four finite points are not ok."""
    ok = bool(det.ok)
    c = np.asarray(det.corners_px, float).reshape(-1, 2)
    if c.shape != (4, 2) or not np.all(np.isfinite(c)):
        ok = False
    quality = float(det.quality or 0.0)
    return Corners(c if c.shape == (4, 2) else np.full((4, 2), np.nan), ok, quality,
                   str(det.reason or ""))


def default_tools(cfg: AligndConfig | None = None) -> Tools:
    """The real vision and solver (imported here, so the procedures load without them).

    With a config the tracker knows the holder's size in px (``holder.size_mm`` and the top
    camera's ``pixel_size_um``): the full search looks for a rectangle of that size
    (within ``SIZE_TOLERANCE``: a configured pixel size that is a few per cent off, as
    commissioning accepts, still finds the holder) and a target of another size is never
    taken for the holder; each frame's search is seeded with the previous frame's corners.
    The side camera's regions of interest come from ``side_camera``. Each camera's frames
    have its tone curve undone first (``cameras[].gamma``, :func:`alignd.vision.linearise`).
    With the top camera's ``lens`` the holder's sides are straightened by it and its
    corners are returned undistorted (every sweep, calibration and offset then in the
    undistorted image), and the rim's ellipse is fitted undistorted (its centre there too).
    """
    from alignd import solve as solver
    from alignd.errors import StateError, VisionError

    try:
        from alignd import vision
    except ImportError as exc:
        raise StateError(f"alignd.vision cannot be imported: {exc}") from exc
    expected = expected_holder_px(cfg) if cfg is not None else None
    side_cfg = cfg.side_camera if cfg is not None else None
    pole_roi = side_cfg.pole_roi_px if side_cfg else None
    sample_roi = side_cfg.sample_roi_px if side_cfg else None
    # the previous frame's detection: its corners seed the search and, where the holder
    # has not moved, its sides' blur widths are reused (track_holder)
    last: list[vision.HolderDetection] = []
    cams = {role: cfg.camera(role) if cfg is not None else None for role in ("top", "side")}
    gammas = {role: cam.gamma if cam is not None else 1.0 for role, cam in cams.items()}
    top_cam = cams["top"]
    lens = None if top_cam is None or top_cam.lens is None else vision.Lens.of(top_cam.lens)

    def top(frame: Frame) -> np.ndarray:
        return vision.linearise(frame.gray, gammas["top"])

    def seen(frame: Frame) -> np.ndarray:
        return vision.linearise(frame.gray, gammas["side"])

    def track(frame: Frame) -> Corners:
        hint = last[0] if last else None
        try:
            det = vision.track_holder(top(frame), expected_size_px=expected, hint=hint,
                                      size_tolerance=SIZE_TOLERANCE, lens=lens)
        except VisionError as exc:
            return Corners(np.full((4, 2), np.nan), False, 0.0, str(exc))
        out = dataclasses.replace(as_corners(det), warning=det.warning, faint=det.faint)
        if out.ok and lens is not None:
            # in the undistorted image, where the turntable turns the holder rigidly and
            # the stages move it in straight lines (the corners stay frame pixels in det,
            # the next frame's seed)
            out = dataclasses.replace(out, corners_px=lens.undistort(out.corners_px))
        if out.ok and expected is not None:
            out = size_checked(out, expected)
        if out.ok:
            last[:] = [det]
            # the previous frame seeds the search, not the corners' order: that stays the
            # image's own (top-left first), as the sweeps and the calibration expect; a
            # seed from the end of the last sweep (up to twice the sweep away) would rotate
            # the labels of a whole sweep
            out = dataclasses.replace(out, corners_px=vision.order_corners(out.corners_px))
        return out

    def solve(angles: np.ndarray, points: np.ndarray,
              pixel_size_um: float | None) -> CentreResult:
        sweep = solver.Sweep(angles_deg=np.asarray(angles, float),
                             points=np.asarray(points, float), pixel_size_um=pixel_size_um)
        return solver.solve_centre(sweep, method="auto")

    def tilt(frame: Frame) -> float:
        return float(vision.measure_tilt(seen(frame), pole_roi_px=pole_roi,
                                  sample_roi_px=sample_roi).tilt_deg)

    pc = cfg.procedure.precheck if cfg is not None else None

    def tilt_frames(frames: list[Frame], more: MoreFrames | None = None) -> TiltReading:
        # the frames as the camera coded them: the JPEG bias step reads that coding, and
        # the tone curve is undone inside
        grab = None if more is None else (lambda k: [f.gray for f in more(k)])
        av = vision.measure_tilt_frames(
            [f.gray for f in frames], pole_roi_px=pole_roi, sample_roi_px=sample_roi,
            more=grab, u_target_deg=pc.tilt_u_target_deg if pc else None,
            max_frames=pc.tilt_max_frames if pc else None, gamma=gammas["side"])
        return TiltReading(av.tilt_deg, av.u_deg, av.n, av.stop, av.jpeg_quality,
                           av.jpeg_bias_deg)

    def eccentricity(frame: Frame) -> float:
        return float(vision.fit_rim(top(frame), lens=lens).eccentricity)

    def rim(frames: list[Frame], radius_mm: float | None, height_mm: float | None) -> RimInfo:
        res = vision.fit_rim_frames([top(f) for f in frames], radius_mm, height_mm, lens=lens)
        z, u = float(res.camera_zenith_deg), float(res.eccentricity_std)
        return RimInfo((float(res.center_px[0]), float(res.center_px[1])),
                       float(res.eccentricity), z if z == z else None, u if u == u else None)

    def side(frame: Frame) -> SideInfo:
        res = vision.measure_tilt(seen(frame), pole_roi_px=pole_roi,
                                  sample_roi_px=sample_roi)
        xs = [e.x_mid_px for e in res.sample_edges] or [float("nan")]
        xp = [e.x_mid_px for e in res.pole_edges] or [float("nan")]
        return SideInfo(float(res.tilt_deg), float(res.sample_angle_deg),
                        float(res.pole_angle_deg), float(np.mean(xs)), float(np.mean(xp)))

    def camera(frames: list[Frame]) -> CameraInfo:
        from alignd.vision.camera_check import check_frames, gamma_text
        c = check_frames([f.gray for f in frames])  # as delivered: the curve is measured
        ok = math.isfinite(c.gamma)  # (NaN: not measured)
        return CameraInfo(c.gamma if ok else None, c.gamma_u if ok else None,
                          c.gamma_range if ok else None, gamma_text(c),
                          [f"{f.what}: {f.advice}" for f in c.findings
                           if f.level == "act" and f.key != "gamma"], c.to_json())

    return Tools(track=track, solve=solve, tilt=tilt, eccentricity=eccentricity,
                 rim=rim, side=side, tilt_frames=tilt_frames, camera=camera,
                 names={"track": "alignd.vision.track_holder",
                        "solve": "alignd.solve.solve_centre(auto)",
                        "tilt": "alignd.vision.measure_tilt",
                        "eccentricity": "alignd.vision.fit_rim"})
