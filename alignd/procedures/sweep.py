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
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from scipy.stats import chi2 as chi2_dist

from alignd.config import AligndConfig, HolderConfig
from alignd.errors import ConfigError, SolveError, VisionError
from alignd.procedures.angles import (
    NEAR_DIAGONAL_DEG,
    AngleMap,
    ReferenceOrder,
    check_sweep_angles,
    holder_frame_order,
    nearest_order,
)
from alignd.procedures.budget import Budget, Contribution, u_of
from alignd.procedures.continuous import frame_angles, run_continuous_sweep
from alignd.procedures.events import ProgressCallback, ProgressEvent
from alignd.procedures.holder_geometry import holder_pose, holder_poses, rot
from alignd.procedures.recorder import RunRecorder
from alignd.procedures.rig import Rig, check_abort
from alignd.procedures.runout import RunoutMap
from alignd.procedures.target_side import check_target_side, image_frame, swapped_frame_error
from alignd.procedures.tools import Tools
from alignd.solve.common import paule_mandel, weighted_mean
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


def grab_frames(cam: Camera, n: int, abort: threading.Event | None = None) -> list[Frame]:
    """``n`` frames of a still view, each exposed after the one before (a real camera's
    frames have independent noise, which their mean averages)."""
    frames = []
    for _ in range(n):
        check_abort(abort)
        frames.append(grab_fresh(cam, cam.clock.now()))
    return frames


def rim_turn_angles(start_deg: float, n: int, turn_deg: float, lim_min: float,
                    lim_max: float) -> np.ndarray:
    """The turntable angles of ``n`` rim frames ``turn_deg`` apart, centred on
    ``start_deg`` and shifted inside the soft limits; ConfigError if they cannot fit."""
    offsets = (np.arange(n) - (n - 1) / 2) * turn_deg
    if offsets[-1] - offsets[0] > lim_max - lim_min:
        raise ConfigError(f"procedure.precheck.rim_turn_deg {turn_deg:g} x {n - 1} steps "
                          f"exceeds the turntable's soft limits [{lim_min:g}, {lim_max:g}]; "
                          "take a smaller step or fewer rim_frames")
    centre = min(max(start_deg, lim_min - offsets[0]), lim_max - offsets[-1])
    return centre + offsets


def grab_rim_frames(rig: Rig, cam: Camera, n: int, turn_deg: float = 0.0,
                    abort: threading.Event | None = None) -> list[Frame]:
    """``n`` top frames for the rim, each exposed after the one before. With ``turn_deg``
    > 0 the turntable steps that far between them (:func:`rim_turn_angles`) and goes back
    where it stood: the disc and its texture turn while the rim's ellipse stays, so the
    texture's pull on e, which no number of still frames averages, averages out."""
    if turn_deg <= 0 or n < 2:
        return grab_frames(cam, n, abort)
    tt = rig.axis("turntable")
    lim = tt.config.soft_limits
    start = tt.position()
    frames = []
    for angle in rim_turn_angles(start, n, turn_deg, lim.min, lim.max):
        check_abort(abort)
        tt.move_to(float(angle))
        frames.append(grab_fresh(cam, cam.clock.now()))
    check_abort(abort)
    tt.move_to(start)
    return frames


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


def map_point(H: np.ndarray, c: np.ndarray, cov: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """A point and its covariance through a homography (first order)."""
    c = np.asarray(c, float)
    out = apply_h(H, c[None, :])[0]
    eps = 1e-3
    Jm = np.column_stack([(apply_h(H, (c + eps * e)[None, :])[0] - out) / eps
                          for e in np.eye(2)])
    return out, Jm @ np.asarray(cov, float) @ Jm.T


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
    mode: Literal["step", "continuous"] = "step"  # continuous: angles are priors
    # frames tracked with the tracker's warning (a holder clipped all round: a glint may
    # do it at some angles only), and the first such warning
    warned_frames: int = 0
    warning: str = ""

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


@dataclass(frozen=True)
class SweepPlan:
    """How one sweep measures: half-width (deg), number of steps, frames averaged per step.

    The procedure starts with the configured plan and widens it (within the turntable's
    soft limits and ``procedure.max_sweep_deg``) or averages more frames when a
    measurement cannot decide."""

    half_deg: float
    steps: int
    frames_per_step: int = 1

    def angles(self, centre_deg: float = 0.0) -> np.ndarray:
        return centre_deg + np.linspace(-self.half_deg, self.half_deg, self.steps)

    def to_dict(self) -> dict[str, float]:
        return {"half_deg": self.half_deg, "steps": self.steps,
                "frames_per_step": self.frames_per_step}


@dataclass
class Measurement:
    """The target's offset from the mean rotation axis, turntable frame, with its uncertainty."""

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
    budget: Budget
    compute_s: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)
    n_sweeps: int = 1
    sigma_random_um: float = 0.0  # statistical part only (no floor), worst axis, 1 sigma
    sweep_centre_px: np.ndarray | None = None
    p_within: float | None = None
    plan: SweepPlan | None = None
    runout_corrected: bool = False
    excess_um: float = 0.0  # between-sweep scatter beyond the fits' own (1 sigma per axis)
    predicted: bool = False  # the offset after a small move, predicted (no sweep after it)
    moved_um: float = 0.0  # that move's length
    # the centre fit's sigma over what independent corner errors would give (alignd.solve.
    # rigid: corners on shared sides, one corner's path biased)
    centre_widened: float = 1.0

    @property
    def norm_um(self) -> float:
        return float(np.hypot(*self.offset_um))

    @property
    def U_um(self) -> float:  # noqa: N802 - the contract name
        """Expanded uncertainty (k = 2) of the offset vector: 2 sqrt(trace(cov))."""
        return 2.0 * math.sqrt(max(float(np.trace(self.cov_offset_um2)), 0.0))

    @property
    def sigma_axis_um(self) -> float:
        """Root-mean-square 1-sigma per axis (the offset's scatter, either direction)."""
        return math.sqrt(max(float(np.trace(self.cov_offset_um2)) / 2.0, 0.0))

    def to_dict(self) -> dict[str, Any]:
        return {
            "centre_px": self.centre_px.tolist(),
            "cov_centre_px2": self.cov_centre_px2.tolist(),
            "offset_px": self.offset_px.tolist(),
            "offset_um": self.offset_um.tolist(),
            "offset_norm_um": self.norm_um,
            "cov_offset_um2": self.cov_offset_um2.tolist(),
            "U_um": self.U_um,
            "budget": self.budget.to_dict(),
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
            "plan": None if self.plan is None else self.plan.to_dict(),
            "runout_corrected": self.runout_corrected, "excess_um": self.excess_um,
            "predicted": self.predicted, "moved_um": self.moved_um,
            "centre_widened": self.centre_widened,
        }


@dataclass
class _Centre:
    """A solver result moved to another frame (for results that are not dataclasses)."""

    center_px: np.ndarray
    cov_px2: np.ndarray
    src: Any

    @property
    def rms_residual_px(self) -> float:
        return float(getattr(self.src, "rms_residual_px", float("nan")))

    @property
    def inliers(self) -> int:
        return int(getattr(self.src, "inliers", 0))

    @property
    def outliers(self) -> int:
        return int(getattr(self.src, "outliers", 0))


CHI2_CENTRE_MOVED = 18.4  # 2 dof, p = 1e-4: a sweep's centre disagrees with the pool


@dataclass
class PooledCentre:
    """The centre of rotation pooled over the sweeps of one run (the axis does not move
    when the stages do, so every sweep measures the same centre).

    ``cov_px2`` includes the between-sweep excess ``excess_px2`` (per axis); ``cov_fit_px2``
    is what the fits alone claim."""

    center_px: np.ndarray
    cov_px2: np.ndarray
    rms_residual_px: float
    inliers: int
    outliers: int
    n_sweeps: int
    cov_fit_px2: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    excess_px2: float = 0.0
    chi2: float = 0.0
    widened: float = 1.0  # the fits' sigma over what independent corner errors would give


class CentrePool:
    """Weighted mean of the per-sweep centres, random-effects style.

    Each sweep's centre has its fit covariance C_i; what the fits cannot know (residual
    error motion that differs between sweeps, drift) shows as scatter beyond the C_i. When
    that scatter is significant (chi-square beyond its 99 % point), the excess variance
    tau^2 per axis is the Paule-Mandel estimate (the tau^2 at which the weighted scatter
    equals its degrees of freedom) and each sweep is weighted by (C_i + tau^2 I)^-1. That
    is the floor measured from repeated sweeps. (Estimated always, tau^2 would follow the
    noise of two or three sweeps and inflate U by chance.) A fit's excess for a corner's
    biased path (``features_excess_px2``) is kept apart and added to the pooled
    covariance at its weighted mean, not averaged down: the same place repeats it.
    """

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
        cs = [c for c, _, _ in self.items]
        extras = [getattr(r, "extra", {}) for *_, r in self.items]
        # a fit's excess for one corner's biased path (alignd.solve.rigid) is bias, not
        # noise: a sweep over the same place repeats it, so it is not averaged down
        bias = [np.asarray(x.get("features_excess_px2", np.zeros((2, 2))), float)
                for x in extras]
        covs = [cov - b for (_, cov, _), b in zip(self.items, bias, strict=True)]
        dof = 2 * (len(cs) - 1)
        plain = weighted_mean(cs, covs)
        tau2 = (paule_mandel(cs, covs)
                if dof > 0 and plain.q > float(chi2_dist.ppf(0.99, dof)) else 0.0)
        pooled = weighted_mean(cs, covs, tau2) if tau2 > 0.0 else plain
        w = [float(np.trace(pooled.cov @ np.linalg.inv(c + tau2 * np.eye(2)))) / 2
             for c in covs]
        cov_bias = sum((wi * b for wi, b in zip(w, bias, strict=True)), np.zeros((2, 2)))
        mean, q0 = pooled.mean, plain.q
        cov_p, cov0 = pooled.cov + cov_bias, plain.cov + cov_bias
        last = self.items[-1][2]
        indep = [np.asarray(x.get("cov_independent_px2", cov), float)
                 for x, (_, cov, _) in zip(extras, self.items, strict=True)]
        cov_indep = weighted_mean(cs, indep).cov
        widened = math.sqrt(max(float(np.trace(cov0) / max(np.trace(cov_indep), 1e-300)), 1.0))
        return PooledCentre(mean, cov_p, float(getattr(last, "rms_residual_px", np.nan)),
                            int(sum(getattr(r, "inliers", 0) for *_, r in self.items)),
                            int(sum(getattr(r, "outliers", 0) for *_, r in self.items)),
                            len(self.items), cov_fit_px2=cov0, excess_px2=tau2, chi2=q0,
                            widened=widened)


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
              recorder: RunRecorder, frames_per_step: int = 1,
              angles: np.ndarray | None = None,
              approach: Literal["+", "-"] | None = None) -> SweepData:
    """Turn through the sweep, grabbing and tracking settled frames at every step.

    ``angles`` default to the configured sweep. With ``frames_per_step`` > 1 the corners of
    the frames at one step are averaged (the sensor noise is independent per frame; the
    pose is the same). ``approach`` turns the sweep in that direction, every step
    approached from that side (default: the turntable's configured approach).
    """
    tt = rig.axis("turntable")
    cam = rig.camera("top")
    assert cam is not None  # validate_rig guarantees it
    angles = sweep_angles(cfg) if angles is None else np.asarray(angles, float)
    if (approach or tt.config.approach) == "-":
        angles = angles[::-1]
    n = len(angles)
    points = np.full((n, 4, 2), np.nan)
    readback: list[float] = []
    hashes: list[str] = []
    t_track = t_grab = t_motion = 0.0
    warned, warning = 0, ""
    for i, a in enumerate(angles):
        check_abort(abort)
        t0 = time.perf_counter()
        readback.append(tt.move_to(float(a)) if approach is None
                        else tt.move_to(float(a), approach))
        settled = cam.clock.now()
        t1 = time.perf_counter()
        t_motion += t1 - t0
        found: list[np.ndarray] = []
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
            if det.ok:  # (one order for the step's frames: they are averaged)
                found.append(nearest_order(det.corners_px, found[0]) if found
                             else det.corners_px)
                if det.warning:
                    warned += 1
                    warning = warning or det.warning
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
                     track_s=t_track, grab_s=t_grab, motion_s=t_motion,
                     warned_frames=warned, warning=warning)
    return data


def _wrap180(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class Floor:
    """What no sweep averages out, per axis (1 sigma, um), and where the number comes from."""

    sigma_um: float
    basis: str
    kind: Literal["A", "B"] = "B"


def runout_floor(runout: RunoutMap | None, assumed_um: float) -> Floor:
    """The per-axis floor a runout map leaves: the map's own uncertainty.

    Taken as the commissioning fit's per-point scatter ``residual_um`` (not divided down by
    the number of angles: model mismatch, perspective and the tracker's own systematic
    errors do not average out), plus, for a map short of a full turn, the error motion
    the rigid fit over the covered range may mistake for axis and arm: the amplitude times
    the missing fraction of the turn (0.25 um for 4 um over 340 deg; the simulator's maps
    come out within 0.3 um rms of its bearing). Without a map the error motion is not
    corrected and ``assumed_um`` stands for it.
    """
    if runout is None:
        return Floor(assumed_um, f"assumed procedure.systematic_um {assumed_um:g} um/axis "
                     "(no runout map: run alignctl commission)", "B")
    a = runout.angles_deg
    step = float(np.median(np.diff(a)))
    missing = 0.0 if runout.full_turn else max(360.0 - float(a[-1] - a[0]) - step, 0.0) / 360
    u_partial = missing * runout.amplitude_um
    u = math.hypot(runout.residual_um, u_partial)
    return Floor(u, f"runout map: {runout.residual_um:.2f} um per point over {len(a)} angles"
                 + (f", {u_partial:.2f} um for the {360 * missing:.0f} deg it misses"
                    if missing else ""), "A")


def measure_offset(data: SweepData, centre: Any, holder: HolderConfig,
                   floor: Floor | float = 0.0) -> Measurement:
    """Target offset from the centre, in the turntable frame at angle 0, with covariance.

    Each tracked frame i gives the target t_i at readback angle a_i; rotating it back about
    the centre, ``R(-a_i) (t_i - c)``, gives the same vector in every frame. Its mean is the
    offset; its covariance is the centre's (propagated through the mean rotation) plus the
    scatter of the per-frame values over n (the target point's own noise). The holder's
    size sets the px-to-mm scale, with its scatter propagated as a relative error.
    ``floor`` (per axis, 1 sigma) stands for what no sweep averages out: the error motion
    the runout map leaves. Each part is a line of the measurement's budget.
    """
    if not isinstance(floor, Floor):
        floor = Floor(float(floor), "assumed", "B")
    ok = data.tracked
    idx = np.flatnonzero(ok)
    c = np.asarray(centre.center_px, float)
    cov_c = np.asarray(centre.cov_px2, float)
    cov_fit = np.asarray(getattr(centre, "cov_fit_px2", cov_c), float)
    n_sw = int(getattr(centre, "n_sweeps", 1))
    widened = float(getattr(centre, "widened", 1.0))
    poses = holder_poses(data.points[idx], holder)
    ang = np.asarray(data.readback_deg, float)[idx]
    rback = rot(-ang)  # (n, 2, 2)
    targets = poses.target_px
    per_frame = np.einsum("nij,nj->ni", rback, targets - c)
    n = len(idx)
    off = per_frame.mean(axis=0)
    cov_t = np.cov(per_frame.T, ddof=1) / n if n > 1 else np.zeros((2, 2))
    A = rback.mean(axis=0)
    cov_off = A @ cov_c @ A.T + cov_t
    scales = poses.scale_px_per_mm
    s = float(scales.mean())
    rel_s = float(scales.std(ddof=1) / math.sqrt(n) / s) if n > 1 else 0.0
    off_mm = off / s
    to_um2 = 1e6 / s**2
    cov_centre_fit = A @ cov_fit @ A.T * to_um2
    cov_excess = A @ (cov_c - cov_fit) @ A.T * to_um2
    cov_target = cov_t * to_um2
    cov_scale = rel_s**2 * np.outer(off_mm, off_mm) * 1e6
    cov_floor = floor.sigma_um**2 * np.eye(2)
    cov_rand = cov_centre_fit + cov_excess + cov_target + cov_scale
    cov_um = cov_rand + cov_floor
    excess_um = math.sqrt(max(float(np.trace(cov_excess)) / 2, 0.0) * n_sw)
    motion_basis = floor.basis + (
        f"; sweep-to-sweep excess {excess_um:.2f} um/axis over {n_sw} sweeps"
        if n_sw > 1 else "")
    budget = Budget((
        Contribution("centre fit", u_of(cov_centre_fit), "A",
                     f"pooled centre of rotation over {n_sw} sweep(s)" + (
                         f"; x{widened:.2f} for corner errors that are not independent "
                         "(corners on shared sides, clutter under one corner's path, a lens "
                         "not modelled)" if widened > 1.005 else "")),
        Contribution("target point", u_of(cov_target), "A",
                     f"scatter of the target over {n} frames"),
        Contribution("pixel scale", u_of(cov_scale), "A",
                     f"holder-size scale {s:.3f} px/mm, rel. {rel_s:.1e}"),
        Contribution("residual error motion", u_of(cov_floor + cov_excess), floor.kind,
                     motion_basis),
        Contribution("stage repeatability", 0.0, "B",
                     "none: the verdict's sweep followed the last move"),
    ))
    yaw = [_wrap180(float(p) - a) for p, a in zip(poses.angle_deg, ang, strict=True)]
    yaw_ref = yaw[0]
    yaw_deg = _wrap180(yaw_ref + float(np.mean([_wrap180(y - yaw_ref) for y in yaw])))
    sigma_c = math.sqrt(max(float(np.linalg.eigvalsh(cov_c).max()), 0.0)) / s * 1000.0
    return Measurement(
        centre_px=c, cov_centre_px2=cov_c, offset_px=off, cov_offset_px2=cov_off,
        scale_px_per_mm=s, offset_um=off_mm * 1000.0, cov_offset_um2=cov_um,
        yaw_deg=yaw_deg, sigma_centre_um=sigma_c,
        rms_residual_px=float(centre.rms_residual_px),
        n_frames=len(data.readback_deg), n_tracked=n,
        inliers=int(getattr(centre, "inliers", n * 4)),
        outliers=int(getattr(centre, "outliers", 0)), budget=budget,
        sigma_random_um=math.sqrt(max(float(np.linalg.eigvalsh(cov_rand).max()), 0.0)),
        excess_um=excess_um, centre_widened=widened)


def map_floor_cov(runout: RunoutMap, data: SweepData, centre: Any, holder: HolderConfig,
                  pixel_size_mm: float, harmonics: tuple[int, ...] = (2, 3, 4, 5),
                  method: str = "rigid-known") -> np.ndarray:
    """The offset's covariance (um^2) from the runout map's own uncertainty, propagated
    through this sweep.

    Why not just the map's per-point scatter: over +-10 deg a translation that changes
    linearly with the angle is read as a rotation about a shifted centre, so a map error's
    *slope* in the swept range moves the centre about 1/(half-width in rad) times as much
    (six times for 10 deg). The map's coefficients (harmonics, with the rigid terms they
    trade with on a partial turn) have covariance s^2 (A'A)^-1 with s its per-point scatter;
    each coefficient's effect on this sweep's offset comes from re-fitting the sweep with
    that harmonic added (``rigid-known``: linear and fast; the free-angle fit responds the
    same to a common translation); G Cov G' is the result.
    """
    from alignd.procedures.runout import _harmonic_columns, _rigid_columns
    from alignd.solve import Sweep, solve_centre

    am = np.radians(runout.angles_deg)
    n = len(am)
    hs = tuple(k for k in harmonics if k >= 2)
    while hs and 4 + 4 * len(hs) > n:
        hs = hs[:-1]
    if not hs:
        return np.zeros((2, 2))
    A = np.hstack([_rigid_columns(am, 1), _harmonic_columns(am, hs)])
    s_mm = runout.residual_um / 1000.0
    cov_coef = s_mm**2 * np.linalg.pinv(A.T @ A)[4:, 4:]
    ang = np.asarray(data.readback_deg, float)
    basis = _harmonic_columns(np.radians(ang), hs)  # (2F, 4K): x rows, y rows interleaved

    def offset(points: np.ndarray) -> np.ndarray:
        res = solve_centre(Sweep(ang, points, None), method=method)
        return measure_offset(dataclasses.replace(data, points=points), res, holder).offset_um

    base = offset(data.points)
    step_mm = 0.001  # 1 um of the harmonic: the fit is linear in it
    G = np.zeros((2, basis.shape[1]))
    for j in range(basis.shape[1]):
        d = basis[:, j].reshape(-1, 2) * step_mm / pixel_size_mm  # (F, 2) px per frame
        G[:, j] = (offset(data.points + d[:, None, :]) - base) / step_mm
    return G @ cov_coef @ G.T


def measure(rig: Rig, cfg: AligndConfig, tools: Tools, *, kind: str, iteration: int,
            abort: threading.Event | None, progress: ProgressCallback,
            recorder: RunRecorder, pixel_size_um: float | None,
            pool: CentrePool | None = None, frames_per_step: int = 1,
            floor_um: float = 0.0, rectify: bool = True, angle_map: AngleMap | None = None,
            runout: RunoutMap | None = None, holder: HolderConfig | None = None,
            plan: SweepPlan | None = None,
            approach: Literal["+", "-"] | None = None) -> tuple[SweepData, Measurement, str]:
    """Sweep, check the tracking and the angles, correct for the runout map, solve the
    centre (pooled), locate the target.

    ``angle_map`` turns read-back angles into the image convention (config or commission
    record); the sweep's own images must agree with it (``check_sweep_angles``, which stops
    the run on a reversed or mis-scaled turntable). With a ``runout`` map every frame's
    corners are moved back by the error motion at its read-back angle before anything is
    fitted, so the centre is the mean axis of rotation; the floor is then the map's
    uncertainty (plus the sweep-to-sweep excess), else ``floor_um``. ``holder`` replaces
    ``cfg.holder`` (a commissioned holder size). ``approach``: the sweep's direction
    (``run_sweep``). Returns the raw data (angles in the image convention), the
    measurement and a warning ('' if none).
    """
    p = cfg.procedure
    plan = plan or SweepPlan(p.sweep_deg, p.sweep_steps, frames_per_step)
    amap = angle_map or AngleMap(p.turntable_direction, 1.0, "config")
    holder = holder or cfg.holder
    if p.sweep_mode == "continuous":
        raw = run_continuous_sweep(rig, cfg, tools, kind=kind, iteration=iteration,
                                   abort=abort, progress=progress, recorder=recorder,
                                   half_deg=plan.half_deg,
                                   frames_per_step=plan.frames_per_step, approach=approach)
    else:
        raw = run_sweep(rig, cfg, tools, kind=kind, iteration=iteration, abort=abort,
                        progress=progress, recorder=recorder,
                        frames_per_step=plan.frames_per_step, angles=plan.angles(),
                        approach=approach)
    points, ref = _one_corner_order(raw, holder)
    raw = dataclasses.replace(raw, points=points)
    config_holder = holder
    if ref is not None and ref.swapped:  # refused below, once the axis names the target
        holder = image_frame(holder, ref)
    data = dataclasses.replace(raw, readback_deg=amap.image_angles(raw.readback_deg).tolist())
    n_ok = int(data.tracked.sum())
    n = len(data.readback_deg)
    recorder.sweep(kind, iteration, data.to_json(pixel_size_um), raw.commanded_deg,
                   raw.readback_deg)
    if n_ok < max(3, math.ceil(MIN_TRACKED_FRACTION * n)):
        raise VisionError(f"holder tracked in only {n_ok} of {n} frames of the {kind} sweep "
                          f"(need {max(3, math.ceil(MIN_TRACKED_FRACTION * n))}); no move made")
    check_sweep_angles(raw.readback_deg, raw.points, amap, kind)
    progress(ProgressEvent("solve", f"solving the centre from {n_ok} frames",
                           iteration=iteration))
    t0 = time.perf_counter()
    P = rectifier(data.points, holder) if rectify else np.eye(3)
    pts = apply_h(P, data.points)
    scale = 1.0
    if runout is not None:  # the map is in the rectified view, indexed by read-back angle
        ok = data.tracked
        scale = float(np.mean([holder_pose(pts[i], holder).scale_px_per_mm
                               for i in np.flatnonzero(ok)]))
        pts = runout.correct_px(np.asarray(raw.readback_deg), pts, 1.0 / scale)
    rect = dataclasses.replace(data, points=pts)
    if raw.mode == "continuous":  # each frame's angle from the images, the read-back its prior
        rect = dataclasses.replace(rect, readback_deg=frame_angles(
            np.asarray(data.readback_deg), pts).tolist())
    try:
        centre = tools.solve(np.asarray(rect.readback_deg), rect.points, pixel_size_um)
    except SolveError:
        raise
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise SolveError(f"{kind} sweep {iteration}: centre solve failed: {exc}") from exc
    t1 = time.perf_counter()
    # the config's target against the axis, before the sweep joins the pool or anything
    # moves on it (target_side)
    Pinv = np.linalg.inv(P)

    def to_image(p: np.ndarray) -> np.ndarray:
        return apply_h(Pinv, p)

    if ref is not None and ref.swapped:
        raise swapped_frame_error(rect.points, rect.readback_deg, centre.center_px,
                                  config_holder, ref, to_image)
    check_target_side(rect.points, rect.readback_deg, centre.center_px, holder, to_image)
    warning = ""
    used: CentreResult | PooledCentre = centre
    if pool is not None:
        # pool in the camera's own image frame: each sweep's rectifier differs a little
        # (it depends on where the holder is), the axis' image point does not
        c_img, cov_img = map_point(Pinv, centre.center_px, centre.cov_px2)
        if dataclasses.is_dataclass(centre):
            # the fit's parts of its covariance go the same way (the pool keeps them apart)
            extra: dict[str, Any] = dict(centre.extra)
            for k in ("features_excess_px2", "cov_independent_px2"):
                if k in extra:
                    extra[k] = map_point(Pinv, centre.center_px, extra[k])[1]
            pooled, warning = pool.add(dataclasses.replace(
                centre, center_px=c_img, cov_px2=cov_img, extra=extra))
        else:
            pooled, warning = pool.add(_Centre(c_img, cov_img, centre))
        c_r, cov_r = map_point(P, pooled.center_px, pooled.cov_px2)
        _, cov_fit_r = map_point(P, pooled.center_px, pooled.cov_fit_px2)
        used = dataclasses.replace(pooled, center_px=c_r, cov_px2=cov_r, cov_fit_px2=cov_fit_r)
        if not warning and pooled.excess_px2 > 0:
            what = "the runout map" if runout is not None else "each other"
            warning = (f"the sweeps' centres disagree with {what} (chi2 {pooled.chi2:.1f} over "
                       f"{pooled.n_sweeps} sweeps): the floor is taken from their scatter"
                       + ("; re-run alignctl commission to refresh the map"
                          if runout is not None else ""))
    floor = runout_floor(runout, floor_um)
    if runout is not None:
        try:
            cov_map = map_floor_cov(runout, rect, used, holder, 1.0 / scale)
            u_axis = math.sqrt(max(float(np.trace(cov_map)) / 2.0, 0.0))
            floor = Floor(u_axis, f"runout map ({runout.residual_um:.2f} um per point over "
                          f"{len(runout.angles_deg)} angles) propagated through this sweep",
                          "A")
        except (SolveError, ValueError, np.linalg.LinAlgError) as exc:
            log.warning("runout map uncertainty not propagated (%s); using its scatter", exc)
    m = measure_offset(rect, used, holder, floor)
    m.n_sweeps = int(getattr(used, "n_sweeps", 1))
    m.sweep_centre_px = np.asarray(centre.center_px, float)
    m.plan = plan
    m.runout_corrected = runout is not None
    m.p_within = conformance_probability(m.offset_um, m.cov_offset_um2, p.tolerance_um)
    t2 = time.perf_counter()
    m.timings = {"track_s": data.track_s, "solve_s": t1 - t0, "offset_s": t2 - t1,
                 "grab_s": data.grab_s, "motion_s": data.motion_s}
    m.compute_s = data.track_s + (t2 - t0)
    return data, m, warning


def _one_corner_order(data: SweepData, holder: HolderConfig
                      ) -> tuple[np.ndarray, ReferenceOrder | None]:
    """The corners of every frame in the order of the frame nearest turntable 0 (the
    holder frame of the config), and that frame's order: a tracker may restart its order
    when the holder has turned far, as over a +-45 deg sweep, which would turn the target
    round the holder. ConfigError where that frame's numbering is the noise's (a square
    holder at its diagonal), before anything is fitted or moved on it."""
    points, ref = holder_frame_order(data.points, data.readback_deg, holder.size_mm)
    if ref is not None and ref.ambiguous:
        raise ConfigError(
            "holder frame ambiguous: the holder is square (holder.size_mm "
            f"{list(holder.size_mm)}) and at turntable 0 its diagonal lies within "
            f"{NEAR_DIAGONAL_DEG:g} deg of level in the top image, where which corner comes "
            "first is decided by noise alone (the target would turn a quarter round the "
            "holder from one sweep to the next). Fix: turn the top camera or the holder by "
            "10 deg or more; no stage was moved on this sweep's data")
    return points, ref


def sweep_runout(rig: Rig, cfg: AligndConfig, tools: Tools, *, half_deg: float = 180.0,
                 step_deg: float = 5.0, frames_per_step: int = 2,
                 abort: threading.Event | None = None,
                 progress: ProgressCallback | None = None,
                 recorder: RunRecorder | None = None,
                 harmonics: tuple[int, ...] = (2, 3, 4, 5)) -> RunoutMap:
    """Map the turntable's error motion with one wide sweep (what commissioning does).

    The holder's centre (the mean of its four corners, whatever order a tracker gives them
    in over a wide turn) is tracked at every step; its path, less the best rigid rotation,
    is the error motion (``fit_runout``). A full turn (the default) maps it about the mean
    axis; the turntable's soft limits must allow the sweep.
    """
    from alignd.procedures.recorder import NullRecorder
    from alignd.procedures.runout import fit_runout

    angles = np.arange(-half_deg, half_deg - 1e-9 if half_deg >= 180.0 else half_deg + 1e-9,
                       step_deg)
    data = run_sweep(rig, cfg, tools, kind="runout", iteration=0, abort=abort,
                     progress=progress or (lambda _ev: None),
                     recorder=recorder or NullRecorder(), frames_per_step=frames_per_step,
                     angles=angles)
    ok = data.tracked
    if int(ok.sum()) < 8:
        raise VisionError(f"runout sweep: holder tracked in only {int(ok.sum())} of "
                          f"{len(angles)} frames")
    # perspective first, as for every sweep: a camera a little off the axis images the
    # holder's circle as an ellipse, which the fit would take for error motion. The
    # holder plane's rectifier does not depend on the pose; it is learnt from the frames
    # near the zero, where a tracker keeps the corners in one order.
    near = np.abs(np.asarray(data.readback_deg)) <= 30.0
    P = rectifier(np.where(near[:, None, None], data.points, np.nan), cfg.holder)
    data = dataclasses.replace(data, points=apply_h(P, data.points))
    # the scale from the holder's edges, longer to longer (order-free)
    long_mm, short_mm = max(cfg.holder.size_mm), min(cfg.holder.size_mm)
    scales = []
    for i in np.flatnonzero(ok):
        c = data.points[i]
        e = np.hypot(*(np.roll(c, -1, axis=0) - c).T)  # the four edge lengths
        a_len, b_len = (e[0] + e[2]) / 2, (e[1] + e[3]) / 2
        scales.append((max(a_len, b_len) / long_mm + min(a_len, b_len) / short_mm) / 2)
    centres = data.points.mean(axis=1)  # NaN rows where tracking failed
    readback = np.asarray(data.readback_deg)
    return fit_runout(image_angles_deg(data.points, readback), centres,
                      1.0 / float(np.mean(scales)), harmonics=harmonics)


def image_angles_deg(points: np.ndarray, readback_deg: np.ndarray) -> np.ndarray:
    """Each frame's turntable angle from the holder's own orientation (its longer edges,
    whatever order the tracker gives the corners in), the read-back only resolving the
    180 deg ambiguity and the zero. Why: an encoder's periodic error turns the holder's
    arm by a few millidegrees, which a runout fit on the read-back angles would take for
    error motion (about 1 um at a 20 mm arm for 3 mdeg)."""
    rb = np.asarray(readback_deg, float)
    theta = np.full(len(rb), np.nan)
    for i, c in enumerate(np.asarray(points, float)):
        if not np.all(np.isfinite(c)):
            continue
        e = np.roll(c, -1, axis=0) - c
        lengths = np.hypot(e[:, 0], e[:, 1])
        k = 0 if lengths[0] + lengths[2] >= lengths[1] + lengths[3] else 1
        d = e[k] - e[k + 2]  # the two long edges run opposite ways round the rectangle
        theta[i] = math.degrees(math.atan2(d[1], d[0]))
    rel = (theta - rb + 90.0) % 180.0 - 90.0  # orientation less read-back, mod 180
    ok = np.isfinite(rel)
    if not ok.any():
        return rb
    # the common zero: a circular mean on the doubled angle (mod 180)
    z = np.exp(2j * np.radians(rel[ok]))
    zero = math.degrees(float(np.angle(z.mean()))) / 2.0
    dev = (rel - zero + 90.0) % 180.0 - 90.0
    return np.where(ok, rb + dev - float(np.nanmean(dev)), rb)
