"""One measurement: sweep the turntable, track the holder, solve the centre, locate the target.

The sweep turns from ``-sweep_deg`` to ``+sweep_deg`` in ``sweep_steps`` steps, always in
the turntable's approach direction (so backlash is taken out once, not per step), grabs a
frame exposed after each settled move, and tracks the holder's four corners. The solver
gives the centre of rotation with its covariance; the target point (``holder.target_mm``
in the holder frame) is located in every frame from the tracked corners and rotated back
to turntable angle 0 about the centre. Its mean is the offset in the turntable frame.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from alignd.config import AligndConfig, HolderConfig
from alignd.errors import SolveError, VisionError
from alignd.procedures.events import ProgressCallback, ProgressEvent
from alignd.procedures.recorder import RunRecorder
from alignd.procedures.rig import Rig, check_abort
from alignd.procedures.tools import Tools
from drivers.camera import Camera, Frame
from drivers.errors import CameraError

if TYPE_CHECKING:
    from alignd.solve.result import CentreResult

log = logging.getLogger(__name__)

MIN_TRACKED_FRACTION = 0.6  # fewer tracked frames than this: the sweep is not used


def grab_fresh(cam: Camera, after: float) -> Frame:
    """A frame exposed after ``after``. A camera that hands back an older one (a stale
    buffer, a driver bug) raises ``CameraError``: a frame from before the stage settled
    shows the wrong pose, and no move may be based on it."""
    frame = cam.grab(after=after)
    if frame.timestamp < after:
        raise CameraError(f"stale frame: exposed {after - frame.timestamp:.3f} s before it "
                          "was asked for (before the stage settled)",
                          device=cam.name, port=cam.source, command="grab")
    return frame


def rot(deg: float | np.ndarray) -> np.ndarray:
    """R(a) of the design notes; stacked (N, 2, 2) for an array of angles."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


@dataclass(frozen=True)
class HolderPose:
    """The holder in one image, from its four corners."""

    center_px: np.ndarray
    u_hat: np.ndarray  # along corner 0 -> 1 (the holder's u axis)
    v_hat: np.ndarray  # perpendicular, towards corner 3
    scale_px_per_mm: float
    angle_deg: float  # direction of u in the image
    target_px: np.ndarray


def holder_pose(corners: np.ndarray, holder: HolderConfig) -> HolderPose:
    """Holder frame and target point from four corners in the tracker's order.

    The holder frame (config) has its origin at the corners' centre, u along corner 0 -> 1
    and v towards corner 3. The scale comes from the holder's own size, so the target lands
    right even though the holder's top face is nearer the camera than the turntable plane.
    """
    c = np.asarray(corners, float)
    u_vec = ((c[1] - c[0]) + (c[2] - c[3])) / 2
    v_vec = ((c[3] - c[0]) + (c[2] - c[1])) / 2
    su, sv = holder.size_mm
    nu, nv = float(np.hypot(*u_vec)), float(np.hypot(*v_vec))
    if nu == 0 or nv == 0:
        raise VisionError("degenerate holder corners (zero-length edge)")
    u_hat = u_vec / nu
    v_perp = v_vec - u_hat * float(u_hat @ v_vec)
    v_hat = v_perp / float(np.hypot(*v_perp))
    scale = (nu / su + nv / sv) / 2
    center = c.mean(axis=0)
    tu, tv = holder.target_mm
    target = center + scale * (tu * u_hat + tv * v_hat)
    return HolderPose(center, u_hat, v_hat, scale, math.degrees(math.atan2(u_hat[1], u_hat[0])),
                      target)


def _homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The 3x3 homography taking 4 points ``src`` to ``dst`` (DLT, exact for 4 points)."""
    rows = []
    for (x, y), (u, v) in zip(src, dst, strict=True):
        rows.append([x, y, 1, 0, 0, 0, -u * x, -u * y, -u])
        rows.append([0, 0, 0, x, y, 1, -v * x, -v * y, -v])
    _, _, vt = np.linalg.svd(np.asarray(rows, float))
    H = vt[-1].reshape(3, 3)
    return H / H[2, 2]


def _similarity(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares similarity (rotation, scale, translation) src -> dst, as 3x3 (Umeyama)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, d])
    R = U @ D @ Vt
    scale = float(np.trace(np.diag(S) @ D) / (a**2).sum())
    T = np.eye(3)
    T[:2, :2] = scale * R
    T[:2, 2] = md - scale * R @ ms
    return T


def apply_h(H: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to (..., 2) points (NaN stays NaN)."""
    p = np.asarray(pts, float)
    q = p @ H[:2, :2].T + H[:2, 2]
    w = p @ H[2, :2] + H[2, 2]
    return q / w[..., None]


def rectifier(points: np.ndarray, holder: HolderConfig) -> np.ndarray:
    """An image-to-image homography that undoes the perspective of the holder's plane.

    A camera not exactly on the axis sees the holder plane through a homography, not a
    similarity: the image scale changes across the field, so the holder is not a rigid
    body in the image and the centre and the target come out biased (several um for
    0.5 deg of camera tilt). Each frame's four corners and the holder's known rectangle
    give that frame's homography H_i; ``S_i H_i^-1`` (S_i the best similarity) maps the
    image to a view in which the plane is imaged by a similarity. The maps of all frames
    agree up to noise and are averaged.
    """
    su, sv = holder.size_mm
    rect = np.array([[-su / 2, -sv / 2], [su / 2, -sv / 2], [su / 2, sv / 2],
                     [-su / 2, sv / 2]])
    maps = []
    for c in points:
        if not np.all(np.isfinite(c)):
            continue
        src = rect.copy()
        e1, e3 = c[1] - c[0], c[3] - c[0]
        if e1[0] * e3[1] - e1[1] * e3[0] < 0:  # corners in the other turning sense
            src[:, 1] *= -1
        H = _homography(src, c)
        P = _similarity(src, c) @ np.linalg.inv(H)
        maps.append(P / P[2, 2])
    if not maps:
        return np.eye(3)
    return np.mean(maps, axis=0)


@dataclass
class SweepData:
    """The raw record of one sweep."""

    kind: str
    iteration: int
    commanded_deg: list[float]
    readback_deg: list[float]
    points: np.ndarray  # (F, 4, 2), NaN where tracking failed
    frame_hashes: list[str]
    track_s: float = 0.0
    grab_s: float = 0.0
    motion_s: float = 0.0

    @property
    def tracked(self) -> np.ndarray:
        return np.all(np.isfinite(self.points), axis=(1, 2))

    def to_json(self, pixel_size_um: float | None) -> dict[str, Any]:
        """The sweep-file contract (features in order, ``null`` for a missed detection)."""
        frames = []
        for a, pts in zip(self.readback_deg, self.points, strict=True):
            feats = [[float(p[0]), float(p[1])] if np.all(np.isfinite(p)) else None
                     for p in pts]
            frames.append({"angle_deg": float(a), "features": feats})
        return {"version": 1, "pixel_size_um": pixel_size_um, "frames": frames}


@dataclass
class Measurement:
    """The target's offset from the rotation axis, turntable frame, with its uncertainty."""

    centre_px: np.ndarray
    cov_centre_px2: np.ndarray
    offset_px: np.ndarray  # target - centre, rotated back to turntable angle 0
    cov_offset_px2: np.ndarray
    scale_px_per_mm: float  # at the holder's top face, from the holder's size
    offset_um: np.ndarray
    cov_offset_um2: np.ndarray
    yaw_deg: float
    sigma_centre_um: float
    rms_residual_px: float
    n_frames: int
    n_tracked: int
    inliers: int
    outliers: int
    compute_s: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)
    n_sweeps: int = 1
    sigma_random_um: float = 0.0  # noise part only (no systematic floor), worst axis
    sweep_centre_px: np.ndarray | None = None
    p_within: float | None = None

    @property
    def norm_um(self) -> float:
        return float(np.hypot(*self.offset_um))

    @property
    def U_um(self) -> float:  # noqa: N802 - the contract name
        """Expanded uncertainty (k = 2) of the offset vector: 2 sqrt(trace(cov))."""
        return 2.0 * math.sqrt(max(float(np.trace(self.cov_offset_um2)), 0.0))

    def to_dict(self) -> dict[str, Any]:
        return {
            "centre_px": self.centre_px.tolist(),
            "cov_centre_px2": self.cov_centre_px2.tolist(),
            "offset_px": self.offset_px.tolist(),
            "offset_um": self.offset_um.tolist(),
            "offset_norm_um": self.norm_um,
            "cov_offset_um2": self.cov_offset_um2.tolist(),
            "U_um": self.U_um,
            "scale_px_per_mm": self.scale_px_per_mm,
            "yaw_deg": self.yaw_deg,
            "sigma_centre_um": self.sigma_centre_um,
            "rms_residual_px": self.rms_residual_px,
            "frames": self.n_frames, "tracked": self.n_tracked,
            "inliers": self.inliers, "outliers": self.outliers,
            "compute_s": self.compute_s, "sweeps_pooled": self.n_sweeps,
            "sweep_centre_px": None if self.sweep_centre_px is None
            else self.sweep_centre_px.tolist(),
            "p_within": self.p_within, "sigma_random_um": self.sigma_random_um,
        }


CHI2_CENTRE_MOVED = 18.4  # 2 dof, p = 1e-4: a sweep's centre disagrees with the pool


@dataclass
class PooledCentre:
    """The centre of rotation pooled over the sweeps of one run (the axis does not move
    when the stages do, so every sweep measures the same centre)."""

    center_px: np.ndarray
    cov_px2: np.ndarray
    rms_residual_px: float
    inliers: int
    outliers: int
    n_sweeps: int


class CentrePool:
    """Inverse-covariance weighted mean of the per-sweep centres, with a consistency check."""

    def __init__(self) -> None:
        self.items: list[tuple[np.ndarray, np.ndarray, CentreResult]] = []

    def add(self, res: CentreResult) -> tuple[PooledCentre, str]:
        """Add a sweep's centre; returns the pooled centre and a warning ('' if none)."""
        c = np.asarray(res.center_px, float)
        cov = np.asarray(res.cov_px2, float)
        warning = ""
        if self.items:
            prev = self.pooled()
            d = c - prev.center_px
            chi2 = float(d @ np.linalg.solve(cov + prev.cov_px2, d))
            if chi2 > CHI2_CENTRE_MOVED:
                warning = (f"the centre moved between sweeps by {np.hypot(*d):.2f} px "
                           f"(chi2 {chi2:.0f}); earlier sweeps dropped from the pool")
                self.items.clear()
        self.items.append((c, cov, res))
        return self.pooled(), warning

    def pooled(self) -> PooledCentre:
        W = sum(np.linalg.inv(cov) for _, cov, _ in self.items)
        b = sum(np.linalg.solve(cov, c) for c, cov, _ in self.items)
        cov_p = np.linalg.inv(W)
        last = self.items[-1][2]
        return PooledCentre(cov_p @ b, cov_p, float(last.rms_residual_px),
                            int(sum(r.inliers for *_, r in self.items)),
                            int(sum(r.outliers for *_, r in self.items)),
                            len(self.items))


def conformance_probability(offset_um: np.ndarray, cov_um2: np.ndarray,
                            tolerance_um: float) -> float:
    """P(|true offset| <= tolerance) given the measurement (Gaussian, the larger variance
    taken for both axes, which is conservative)."""
    from scipy.stats import ncx2

    var = max(float(np.linalg.eigvalsh(cov_um2).max()), 1e-12)
    nc = float(offset_um @ offset_um) / var
    return float(ncx2.cdf(tolerance_um**2 / var, 2, max(nc, 1e-12)))


def sweep_angles(cfg: AligndConfig, centre_deg: float = 0.0) -> np.ndarray:
    p = cfg.procedure
    return centre_deg + np.linspace(-p.sweep_deg, p.sweep_deg, p.sweep_steps)


def run_sweep(rig: Rig, cfg: AligndConfig, tools: Tools, *, kind: str, iteration: int,
              abort: threading.Event | None, progress: ProgressCallback,
              recorder: RunRecorder, frames_per_step: int = 1) -> SweepData:
    """Turn through the sweep, grabbing and tracking settled frames at every step.

    With ``frames_per_step`` > 1 the corners of the frames at one step are averaged (the
    sensor noise is independent per frame; the pose is the same).
    """
    tt = rig.axis("turntable")
    cam = rig.camera("top")
    assert cam is not None  # validate_rig guarantees it
    angles = sweep_angles(cfg)
    if tt.config.approach == "-":
        angles = angles[::-1]
    n = len(angles)
    points = np.full((n, 4, 2), np.nan)
    readback: list[float] = []
    hashes: list[str] = []
    t_track = t_grab = t_motion = 0.0
    for i, a in enumerate(angles):
        check_abort(abort)
        t0 = time.perf_counter()
        readback.append(tt.move_to(float(a)))
        settled = time.monotonic()
        t1 = time.perf_counter()
        t_motion += t1 - t0
        found = []
        why = ""
        for j in range(max(frames_per_step, 1)):
            t1 = time.perf_counter()
            frame = grab_fresh(cam, settled)
            t2 = time.perf_counter()
            det = tools.track(frame)
            t3 = time.perf_counter()
            t_grab += t2 - t1
            t_track += t3 - t2
            hashes.append(recorder.frame(frame.image, f"{kind}-{iteration}-{i:03d}-{j}"))
            if det.ok:
                found.append(det.corners_px)
            else:
                why = det.reason or "no detection"
        if found:
            points[i] = np.mean(found, axis=0)
        else:
            log.warning("%s sweep %d: holder not tracked at %.3f deg (%s)", kind, iteration,
                        readback[-1], why)
        progress(ProgressEvent("sweep" if kind != "verify" else "verify",
                               f"{kind} sweep at {readback[-1]:+.3f} deg"
                               + ("" if found else " (holder not found)"),
                               step=i + 1, total=n, iteration=iteration))
    data = SweepData(kind, iteration, [float(a) for a in angles], readback, points, hashes,
                     track_s=t_track, grab_s=t_grab, motion_s=t_motion)
    return data


def _wrap180(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def measure_offset(data: SweepData, centre: CentreResult | PooledCentre, holder: HolderConfig,
                   floor_um: float = 0.0) -> Measurement:
    """Target offset from the centre, in the turntable frame at angle 0, with covariance.

    Each tracked frame i gives the target t_i at readback angle a_i; rotating it back about
    the centre, ``R(-a_i) (t_i - c)``, gives the same vector in every frame. Its mean is the
    offset; its covariance is the centre's (propagated through the mean rotation) plus the
    scatter of the per-frame values over n (the target point's own noise). The holder's
    size sets the px-to-mm scale, with its scatter propagated as a relative error.
    ``floor_um`` (per axis, 1 sigma) stands for what no sweep averages out: the turntable's
    error motion and perspective.
    """
    ok = data.tracked
    idx = np.flatnonzero(ok)
    c = np.asarray(centre.center_px, float)
    cov_c = np.asarray(centre.cov_px2, float)
    poses = [holder_pose(data.points[i], holder) for i in idx]
    ang = np.asarray(data.readback_deg, float)[idx]
    rback = rot(-ang)  # (n, 2, 2)
    targets = np.array([p.target_px for p in poses])
    per_frame = np.einsum("nij,nj->ni", rback, targets - c)
    n = len(idx)
    off = per_frame.mean(axis=0)
    cov_t = np.cov(per_frame.T, ddof=1) / n if n > 1 else np.zeros((2, 2))
    A = rback.mean(axis=0)
    cov_off = A @ cov_c @ A.T + cov_t
    scales = np.array([p.scale_px_per_mm for p in poses])
    s = float(scales.mean())
    rel_s = float(scales.std(ddof=1) / math.sqrt(n) / s) if n > 1 else 0.0
    off_mm = off / s
    cov_rand = cov_off / s**2 + rel_s**2 * np.outer(off_mm, off_mm)
    cov_mm = cov_rand + (floor_um / 1000.0) ** 2 * np.eye(2)
    yaw = [_wrap180(p.angle_deg - a) for p, a in zip(poses, ang, strict=True)]
    yaw_ref = yaw[0]
    yaw_deg = _wrap180(yaw_ref + float(np.mean([_wrap180(y - yaw_ref) for y in yaw])))
    sigma_c = math.sqrt(max(float(np.linalg.eigvalsh(cov_c).max()), 0.0)) / s * 1000.0
    return Measurement(
        centre_px=c, cov_centre_px2=cov_c, offset_px=off, cov_offset_px2=cov_off,
        scale_px_per_mm=s, offset_um=off_mm * 1000.0, cov_offset_um2=cov_mm * 1e6,
        yaw_deg=yaw_deg, sigma_centre_um=sigma_c,
        rms_residual_px=float(centre.rms_residual_px),
        n_frames=len(data.readback_deg), n_tracked=n,
        inliers=int(centre.inliers),
        outliers=int(centre.outliers),
        sigma_random_um=math.sqrt(max(float(np.linalg.eigvalsh(cov_rand).max()), 0.0)) * 1e3)


def measure(rig: Rig, cfg: AligndConfig, tools: Tools, *, kind: str, iteration: int,
            abort: threading.Event | None, progress: ProgressCallback,
            recorder: RunRecorder, pixel_size_um: float | None,
            pool: CentrePool | None = None, frames_per_step: int = 1,
            floor_um: float = 0.0, rectify: bool = True) -> tuple[SweepData, Measurement, str]:
    """Sweep, check the tracking, solve the centre (pooled), locate the target.

    Returns the raw data, the measurement and a warning from the pool ('' if none).
    """
    data = run_sweep(rig, cfg, tools, kind=kind, iteration=iteration, abort=abort,
                     progress=progress, recorder=recorder, frames_per_step=frames_per_step)
    n_ok = int(data.tracked.sum())
    n = len(data.readback_deg)
    recorder.sweep(kind, iteration, data.to_json(pixel_size_um), data.commanded_deg,
                   data.readback_deg)
    if n_ok < max(3, math.ceil(MIN_TRACKED_FRACTION * n)):
        raise VisionError(f"holder tracked in only {n_ok} of {n} frames of the {kind} sweep "
                          f"(need {max(3, math.ceil(MIN_TRACKED_FRACTION * n))}); no move made")
    progress(ProgressEvent("solve", f"solving the centre from {n_ok} frames",
                           iteration=iteration))
    t0 = time.perf_counter()
    P = rectifier(data.points, cfg.holder) if rectify else np.eye(3)
    rect = dataclasses.replace(data, points=apply_h(P, data.points))
    try:
        centre = tools.solve(np.asarray(data.readback_deg), rect.points, pixel_size_um)
    except SolveError:
        raise
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise SolveError(f"{kind} sweep {iteration}: centre solve failed: {exc}") from exc
    t1 = time.perf_counter()
    warning = ""
    used: CentreResult | PooledCentre = centre
    if pool is not None:
        used, warning = pool.add(centre)
    m = measure_offset(rect, used, cfg.holder, floor_um)
    m.n_sweeps = used.n_sweeps if isinstance(used, PooledCentre) else 1
    m.sweep_centre_px = np.asarray(centre.center_px, float)
    m.p_within = conformance_probability(m.offset_um, m.cov_offset_um2,
                                         cfg.procedure.tolerance_um)
    t2 = time.perf_counter()
    m.timings = {"track_s": data.track_s, "solve_s": t1 - t0, "offset_s": t2 - t1,
                 "grab_s": data.grab_s, "motion_s": data.motion_s}
    m.compute_s = data.track_s + (t2 - t0)
    return data, m, warning
