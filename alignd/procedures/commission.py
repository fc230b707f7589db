"""Commissioning: measure a rig's conventions once, instead of assuming them.

A lab's rig differs from the reference one in ways nobody writes down: the turntable turns
the other way, the camera is mounted turned or mirrored, the cables of x and y are swapped,
the holder was measured wrong. ``run_commission`` finds each of them with small, safe moves
and records what it found, each item with its uncertainty and a pass / warn / fail finding
that names the fix (``config_fix``: the config keys to change, where a key can fix it):

- turntable: direction (the sign between the commanded angle and the image's rotation),
  angle scale (read-back degrees against the holder's turning in the images), backlash
  (arrivals from both sides) and its error motion over the widest sweep the config allows
  (``commission.sweep_deg``), a ``RunoutMap`` later sweeps subtract;
- each translation axis: direction and length in the image and in the holder frame, which
  config role moves which way (swapped or inverted named as such), skew between x and y,
  backlash and repeatability from there-and-back moves, and the same moves at a second
  turntable angle (the stages must turn with the table);
- top camera: pixel size at the holder's face (from the stage moves) against the config,
  roll (the holder's edge in the image), rim eccentricity and zenith; the holder's size
  (its edges times that pixel size) against ``holder.size_mm``;
- side camera: pole and sample found, and which way a positive tilt leans (from a
  translator move);
- devices: identities, stage models and soft limits against the configured travel;
- each camera's frames: what the camera does to them (its tone curve against
  ``cameras[].gamma``, sharpening, coding, clipping), from 8 frames of its still view.

``align`` and ``check`` use the latest valid record (``CommissionRecord``): the measured
turntable direction and scale, the runout map, the measured pixel size; it is valid while
the config hash and the device identities are the ones it was measured with.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from alignd.config import AligndConfig, config_hash
from alignd.errors import AligndError, ConfigError, DeviceError, SolveError, StateError, VisionError
from alignd.procedures.angles import (
    AngleMap,
    ReferenceOrder,
    fit_angle_error,
    fit_slope,
    holder_frame_order,
    holder_image_angles,
    nearest_order,
    reference_order,
)
from alignd.procedures.calibrate import configured_pixel_size_um
from alignd.procedures.events import Phase, ProgressCallback, ProgressEvent, no_progress
from alignd.procedures.holder_geometry import rot, turned
from alignd.procedures.recorder import NullRecorder, RunRecorder
from alignd.procedures.rig import AbortRequested, Rig, check_abort, validate_rig
from alignd.procedures.runout import RunoutMap, fit_runout
from alignd.procedures.sweep import (
    apply_h,
    grab_frames,
    grab_fresh,
    grab_rim_frames,
    rectifier,
)
from alignd.procedures.target_side import image_frame
from alignd.procedures.tools import RimInfo, Tools, default_tools
from drivers.camera import Camera, Frame
from drivers.config import ToneCurve
from drivers.tone_curves import curve_text, disagrees

log = logging.getLogger(__name__)

FindingVerdict = Literal["pass", "warn", "fail"]
CommissionVerdict = Literal["commissioned", "failed", "aborted", "fault"]
COMMISSION_EXIT: dict[str, int] = {"commissioned": 0, "failed": 1, "aborted": 1, "fault": 3}

FRAMES_PER_POSE = 2
FRAMES_PER_SWEEP_STEP = 2  # once per rig: worth halving the noise of the runout map
ANGLE_SCALE_WARN = 0.002  # relative angle-scale error that warns
ANGLE_ERROR_WARN_DEG = 0.01  # periodic encoder error that warns
ROLE_CONE_DEG = 30.0  # a role moving within this of an axis of the holder frame "moves along" it
SECOND_ANGLE_DEG = 90.0
MAX_TURN_DISAGREE_DEG = 1.0  # stage directions at two table angles, turned back, must agree
CAMERA_CHECK_FRAMES = 8  # a still view's frames for what the camera does (its tone curve)


@runtime_checkable
class ReportsTravel(Protocol):
    """An axis whose controller reports its travel limits (SMC100: SL?/SR?)."""

    def software_limits(self) -> tuple[float, float]: ...


@dataclass
class Finding:
    """One measured item: value with its 1-sigma uncertainty, what the config says, verdict."""

    item: str
    verdict: FindingVerdict
    message: str
    value: Any = None
    sigma: Any = None
    expected: Any = None
    unit: str = ""
    config_fix: dict[str, Any] | None = None  # config key path -> value that fixes it
    name: str = ""  # the named deviation: "reversed", "swapped", "inverted", ...

    def to_json(self) -> dict[str, Any]:
        return {"item": self.item, "verdict": self.verdict, "message": self.message,
                "value": _plain(self.value), "sigma": _plain(self.sigma),
                "expected": _plain(self.expected), "unit": self.unit,
                "config_fix": _plain(self.config_fix), "name": self.name}


# e's standard uncertainty above which commissioning's rim item warns: a third of the 0.003
# the vision holds e to (docs/vision.md, Rim), so that e within 3 u supports that bound
RIM_U_CERTAIN = 0.001
MIN_RIM_TURN_DEG = 5.0  # a turn between rim frames below this averages little of a texture
# the turn is advised where e from turned frames is at least this much more certain: a
# texture's share goes (2324 #64: 0.0012 -> 0.0008-0.0009, docs/vision.md), noise's does not move
RIM_TURN_GAIN = 0.85
# what makes e more certain once a disc's texture is averaged (or was not what limited it)
RIM_LEFT = ("more rim_frames, more light or contrast on the rim, a wider rim in the image "
            "(e's error falls as 1 / its radius squared), or less of it hidden")


def rim_advice(frames: int, turn_deg: float, lim_min: float, lim_max: float
               ) -> tuple[str, dict[str, Any] | None]:
    """What makes the rim pre-check's e more certain, and the config keys that do it.

    One frame: more frames (noise). Still frames: the disc turned between them, 180 /
    ``frames`` deg (it cancels a texture's second harmonic, what moves e), or the most
    the turntable's soft limits hold. What is left to a lab: a wider rim in view or a
    smoother disc."""
    if frames < 2:
        return ("average more frames (procedure.precheck.rim_frames 8: one frame's noise "
                "is most of e's uncertainty at small e)",
                {"procedure.precheck.rim_frames": 8})
    if turn_deg <= 0:
        step = math.floor(10 * min(180.0 / frames, 45.0,
                                   (lim_max - lim_min) / (frames - 1))) / 10
        if step >= MIN_RIM_TURN_DEG:
            return (f"what still frames share (the disc's texture, a still view's JPEG "
                    f"coding) their mean keeps; turning the disc {step:g} deg between the "
                    f"{frames} frames averages it out (procedure.precheck.rim_turn_deg "
                    f"{step:g}: the turntable then goes about {step * (frames - 1):g} deg out "
                    "and back before each run); more rim_frames help where the frames' "
                    "noise is what is left", {"procedure.precheck.rim_turn_deg": step})
        return (f"the turntable's soft limits [{lim_min:g}, {lim_max:g}] leave too little "
                f"turn to average a textured disc over {frames} frames; a smoother disc, a "
                "wider rim in the image, or more rim_frames where the frames' noise is what "
                "is left", None)
    return ("the disc turned between the frames averages its texture; what is left is the "
            f"frames' noise and the rim's own edge: {RIM_LEFT}", None)


def _plain(v: Any) -> Any:
    """JSON-ready: numpy to Python, tuples to lists, non-finite floats to None."""
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return round(f, 6) if math.isfinite(f) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


@dataclass
class AxisMeasurement:
    """What the there-and-back moves of one translation axis showed (turntable at 0)."""

    role: str
    image_px_per_mm: np.ndarray  # (2,) image displacement per mm of the axis
    sigma_px_per_mm: float
    holder_uv: tuple[float, float]  # unit direction in the holder frame
    backlash_mm: float
    backlash_sigma_mm: float
    repeatability_mm: float
    turn_check_deg: float | None = None  # disagreement at the second table angle

    @property
    def length_px_per_mm(self) -> float:
        return float(np.hypot(*self.image_px_per_mm))

    @property
    def image_angle_deg(self) -> float:
        return math.degrees(math.atan2(self.image_px_per_mm[1], self.image_px_per_mm[0]))

    def to_json(self) -> dict[str, Any]:
        return _plain({"image_px_per_mm": self.image_px_per_mm,
                       "px_per_mm": self.length_px_per_mm,
                       "sigma_px_per_mm": self.sigma_px_per_mm,
                       "image_angle_deg": self.image_angle_deg,
                       "holder_frame_uv": self.holder_uv,
                       "backlash_um": self.backlash_mm * 1000,
                       "backlash_sigma_um": self.backlash_sigma_mm * 1000,
                       "repeatability_um": self.repeatability_mm * 1000,
                       "turn_check_deg": self.turn_check_deg})


@dataclass
class CommissionRecord:
    """A rig's measured conventions, tied to the config hash and the device identities."""

    run_id: str
    verdict: CommissionVerdict
    reason: str
    findings: list[Finding] = field(default_factory=list)
    turntable_sign: int | None = None
    angle_scale: float | None = None
    angle_error: tuple[tuple[int, float, float], ...] = ()  # periodic encoder error
    pixel_size_um: float | None = None  # at the holder's face
    axis_px: tuple[float, float] | None = None  # the rotation axis in the top image
    holder_size_mm: tuple[float, float] | None = None
    runout: RunoutMap | None = None
    axes: dict[str, AxisMeasurement] = field(default_factory=dict)
    config_hash: str = ""
    devices: dict[str, dict[str, str]] = field(default_factory=dict)
    truth: dict[str, Any] | None = None
    details: dict[str, Any] = field(default_factory=dict)
    config_error: bool = False

    @property
    def exit_code(self) -> int:
        if self.verdict == "fault" and self.config_error:
            return 2
        return COMMISSION_EXIT[self.verdict]

    @property
    def ok(self) -> bool:
        return self.verdict == "commissioned"

    def finding(self, item: str) -> Finding | None:
        return next((f for f in self.findings if f.item == item), None)

    def angle_map(self, label: str) -> AngleMap:
        return AngleMap(self.turntable_sign or 1, self.angle_scale or 1.0, label,
                        self.angle_error)

    def to_json(self) -> dict[str, Any]:
        counts = {v: sum(f.verdict == v for f in self.findings) for v in ("pass", "warn", "fail")}
        out: dict[str, Any] = {
            "run_id": self.run_id, "kind": "commission", "verdict": self.verdict,
            "reason": self.reason, "counts": counts,
            "findings": [f.to_json() for f in self.findings],
            "conventions": _plain({
                "turntable_direction": self.turntable_sign, "angle_scale": self.angle_scale,
                "angle_error_harmonics": [list(e) for e in self.angle_error],
                "pixel_size_um": self.pixel_size_um, "holder_size_mm": self.holder_size_mm,
                "axis_px": self.axis_px,
                "axes": {r: a.to_json() for r, a in self.axes.items()}}),
            "runout": None if self.runout is None else self.runout.to_json(),
            "config_hash": self.config_hash, "devices": self.devices,
            # the run-result contract's keys, so history and the CLI show a commission too
            "offset_um": None, "offset_norm_um": None, "U_um": None, "iterations": 0,
            "tilt_deg": None, "yaw_deg": None,
        }
        if self.truth is not None:
            out["truth"] = _plain(self.truth)
        return out

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> CommissionRecord:
        """A stored record back (for align/check); ``ValueError`` if it is malformed."""
        try:
            conv = d.get("conventions") or {}
            hs = conv.get("holder_size_mm")
            rec = cls(run_id=str(d["run_id"]), verdict=d["verdict"], reason=str(d["reason"]),
                      findings=[Finding(**f) for f in d.get("findings", [])],
                      turntable_sign=conv.get("turntable_direction"),
                      angle_scale=conv.get("angle_scale"),
                      angle_error=tuple((int(h), float(c), float(d)) for h, c, d in
                                        conv.get("angle_error_harmonics") or []),
                      pixel_size_um=conv.get("pixel_size_um"),
                      holder_size_mm=None if hs is None else (float(hs[0]), float(hs[1])),
                      runout=None if d.get("runout") is None
                      else RunoutMap.from_json(d["runout"]),
                      config_hash=str(d.get("config_hash", "")),
                      devices=dict(d.get("devices") or {}))
        except (KeyError, TypeError, IndexError) as exc:
            raise ValueError(f"malformed commission record: {exc}") from None
        return rec

    def valid_for(self, cfg_hash: str, devices: dict[str, dict[str, str]]) -> str:
        """'' if this record applies to the rig as it is now, else why not."""
        if self.verdict != "commissioned":
            return f"its verdict is {self.verdict}"
        if self.config_hash != cfg_hash:
            return "the config changed since (config hash differs)"
        for role, ident in self.devices.items():
            now = devices.get(role)
            if now is not None and (now.get("serial"), now.get("model")) != (
                    ident.get("serial"), ident.get("model")):
                return (f"the {role} device changed (s/n {ident.get('serial')} -> "
                        f"{now.get('serial')})")
        return ""


def run_commission(rig: Rig, cfg: AligndConfig, *, progress: ProgressCallback | None = None,
                   abort: threading.Event | None = None, recorder: RunRecorder | None = None,
                   tools: Tools | None = None, run_id: str | None = None,
                   commission: CommissionRecord | None = None) -> CommissionRecord:
    """Measure the rig's conventions (see the module docstring); never raises for the rig.
    ``commission`` (a previous record) is not used: commissioning measures afresh."""
    return _Commission(rig, cfg, progress, abort, recorder, tools, run_id).execute()


@dataclass
class _Pose:
    """The holder in one settled view: corners averaged over a few frames."""

    corners: np.ndarray  # (4, 2)
    sigma_px: float  # scatter of the corners between the frames (per coordinate)
    warning: str = ""  # the tracker's, from any of the frames (clipped all round, faint)
    faint: bool = False  # any frame's holder found only by the tracker's fainter search

    @property
    def centre(self) -> np.ndarray:
        return self.corners.mean(axis=0)


class _Commission:
    def __init__(self, rig: Rig, cfg: AligndConfig, progress: ProgressCallback | None,
                 abort: threading.Event | None, recorder: RunRecorder | None,
                 tools: Tools | None, run_id: str | None) -> None:
        self.rig = rig
        self.cfg = cfg
        self.c = cfg.commission
        self.progress = progress or no_progress
        self.abort = abort
        self.recorder = recorder or NullRecorder()
        self.tools = tools
        self.run_id = run_id or getattr(recorder, "run_id", None) or uuid.uuid4().hex[:12]
        self.rec = CommissionRecord(self.run_id, "fault", "", config_hash=config_hash(cfg))
        self.n_frames = 0
        self.motion_s = 0.0
        self.rim_centre: np.ndarray | None = None
        self.start_pose: _Pose | None = None
        self.start_order: ReferenceOrder | None = None  # its corners' holder-frame order
        self.frame_target = cfg.holder.target_mm  # holder.target_mm in the image's frame
        self.holder_px: tuple[float, float] = (math.nan, math.nan)
        self.axis_px: np.ndarray = np.full(2, np.nan)

    # ---- plumbing --------------------------------------------------------------------
    def _emit(self, phase: Phase, message: str, step: int | None = None,
              total: int | None = None) -> None:
        try:
            self.progress(ProgressEvent(phase, message, step=step, total=total))
        except Exception:  # an observer must not break the run
            log.exception("progress callback failed")

    def _add(self, f: Finding) -> Finding:
        self.rec.findings.append(f)
        level = {"pass": logging.INFO, "warn": logging.WARNING, "fail": logging.WARNING}
        log.log(level[f.verdict], "commission %s: %s: %s", f.item, f.verdict, f.message)
        self.recorder.event(f"commission {f.item}: {f.verdict}: {f.message}")
        return f

    def _move(self, role: str, target: float, approach: Literal["+", "-"] | None = None
              ) -> float:
        check_abort(self.abort)
        t0 = time.perf_counter()
        pos = self.rig.axis(role).move_to(target, approach)
        self.motion_s += time.perf_counter() - t0
        return pos

    def _look(self, label: str, frames: int = FRAMES_PER_POSE) -> _Pose | None:
        """The holder's corners averaged over ``frames`` settled frames (None: not found)."""
        cam = self.rig.camera("top")
        assert cam is not None and self.tools is not None
        settled = cam.clock.now()
        found: list[np.ndarray] = []
        warning, faint = "", False
        for j in range(frames):
            frame = grab_fresh(cam, settled)
            self.n_frames += 1
            self.recorder.frame(frame.image, f"commission-{label}-{j}")
            det = self.tools.track(frame)
            if det.ok:  # (one order for the frames averaged)
                found.append(nearest_order(det.corners_px, found[0]) if found
                             else det.corners_px)
                warning = warning or det.warning
                faint = faint or det.faint
        if not found:
            return None
        arr = np.asarray(found)
        sig = float(arr.std(axis=0, ddof=1).mean()) if len(arr) > 1 else float("nan")
        return _Pose(arr.mean(axis=0), sig, warning, faint)

    def _need(self, label: str) -> _Pose:
        pose = self._look(label)
        if pose is None:
            raise VisionError(f"holder not found in the top camera ({label}); commissioning "
                              "needs the holder in view, on the turntable")
        return pose

    # ---- top level -------------------------------------------------------------------
    def execute(self) -> CommissionRecord:
        t0 = time.time()
        rec = self.rec
        try:
            with self.rig.abort_guard(self.abort):
                self._prepare()
                self._devices()
                self._top_camera_static()
                self._translation_axes()
                self._scales()
                self._turntable()
                self._side_camera()
                self._move("turntable", 0.0)
            fails = [f for f in rec.findings if f.verdict == "fail"]
            warns = [f for f in rec.findings if f.verdict == "warn"]
            if fails:
                rec.verdict = "failed"
                rec.reason = (f"{len(fails)} finding(s) failed: "
                              + "; ".join(f"{f.item}: {f.message}" for f in fails))
            else:
                rec.verdict = "commissioned"
                rec.reason = (f"{len(rec.findings)} items measured, "
                              f"{len(warns)} warning(s)" + (": " + "; ".join(
                                  f"{f.item} ({f.name or f.verdict})" for f in warns)
                                  if warns else ""))
        except AbortRequested as exc:
            errs = self.rig.stop_all()
            rec.verdict, rec.reason = "aborted", f"aborted: {exc}" + (
                f" (stop failed: {'; '.join(errs)})" if errs else "")
        except (ConfigError, StateError) as exc:
            self.rig.stop_all()
            rec.verdict, rec.reason, rec.config_error = "fault", f"refused: {exc}", True
        except DeviceError as exc:
            errs = self.rig.stop_all()
            rec.verdict, rec.reason = "fault", f"device error: {exc}" + (
                f" (stop failed: {'; '.join(errs)})" if errs else "")
        except AligndError as exc:
            self.rig.stop_all()
            rec.verdict, rec.reason = "fault", f"measurement failed: {exc}"
        except Exception as exc:  # a run must always end in a verdict
            log.exception("internal error during commission run %s", self.run_id)
            self.rig.stop_all()
            rec.verdict, rec.reason = "fault", f"internal error: {type(exc).__name__}: {exc}"
        rec.devices = {r: dict(vars(i)) for r, i in self.rig.identities.items()}
        if self.rig.truth is not None:
            try:
                rec.truth = dict(self.rig.truth())
            except Exception:  # truth is a report extra
                log.exception("reading the simulator truth failed")
        rec.details = {"mode": "commission", "started": t0, "finished": time.time(),
                       "frames": self.n_frames, "motion_s": self.motion_s,
                       "record": rec.to_json(),
                       "tools": self.tools.names if self.tools else None}
        self.recorder.event(f"commission finished: {rec.verdict}: {rec.reason}")
        self._emit("done", f"{rec.verdict}: {rec.reason}")
        return rec

    # ---- phases ----------------------------------------------------------------------
    def _prepare(self) -> None:
        validate_rig(self.rig, tuple(self.cfg.procedure.correction_axes))
        self._emit("connect", "connecting and identifying devices")
        self.rig.connect()
        if self.tools is None:
            self.tools = default_tools()
        self._emit("home", "homing where required")
        homed = self.rig.home_where_required(list(self.rig.axes), abort=self.abort)
        if homed:
            self.recorder.event(f"homed: {', '.join(homed)}")
        self._move("turntable", 0.0)

    def _devices(self) -> None:
        for role, ax in self.rig.axes.items():
            ident = self.rig.identities.get(role)
            conf = ax.config
            who = (f"{ident.vendor} {ident.model} s/n {ident.serial} fw {ident.firmware}"
                   if ident else "not identified")
            lim = conf.soft_limits
            msg = (f"{who} on {ax.port}; soft limits [{lim.min:g}, {lim.max:g}] "
                   f"{conf.units}")
            verdict: FindingVerdict = "pass"
            name = ""
            stage = ident.stage if ident else ""
            if stage and conf.stage and stage.upper() != conf.stage.upper():
                verdict, name = "warn", "stage model differs"
                msg += f"; the controller reports stage {stage}, the config says {conf.stage}"
            if isinstance(ax, ReportsTravel):  # the controller knows its stage's travel
                lo, hi = ax.software_limits()
                msg += f"; controller travel [{lo:g}, {hi:g}] {conf.units}"
                if lim.min < lo or lim.max > hi:
                    verdict, name = "fail", "soft limits beyond travel"
                    msg += (f": the config's soft limits reach beyond it; set "
                            f"soft_limits inside [{lo:g}, {hi:g}]")
            pos = ax.position()
            msg += f"; at {pos:.4f} {conf.units}"
            self._add(Finding(f"device.{role}", verdict, msg, value=who,
                              expected=conf.stage or None, name=name))

    def _top_camera_static(self) -> None:
        """Holder found and its roll; the rim's eccentricity and the camera's zenith."""
        self._emit("top", "top camera: holder and rim")
        pose = self._need("start")
        # the holder frame's order (by holder.size_mm where the holder's diagonal lies
        # level in the image and the image's order is the noise's)
        self.start_order = reference_order(pose.corners, self.cfg.holder.size_mm)
        pose = replace(pose, corners=self.start_order.corners)
        u = ((pose.corners[1] - pose.corners[0]) + (pose.corners[2] - pose.corners[3])) / 2
        roll = math.degrees(math.atan2(u[1], u[0]))
        self.start_pose = pose
        self._add(Finding("top.roll", "pass" if abs(roll) <= 10 else "warn",
                          f"the holder's u edge (corner 0 -> 1) runs at {roll:+.2f} deg in the "
                          "image at turntable 0 (camera roll against the holder)",
                          value=roll, sigma=math.degrees(pose.sigma_px / np.hypot(*u))
                          if math.isfinite(pose.sigma_px) else None, unit="deg",
                          name="" if abs(roll) <= 10 else "rolled"))
        if self.start_order.ambiguous:
            self._add(Finding(
                "holder.frame", "fail",
                f"the holder is square and its diagonal lies level in the image (u at "
                f"{roll:+.1f} deg): which corner is first is the noise's, and align refuses "
                "it; turn the top camera or the holder by 10 deg or more",
                value=roll, unit="deg", name="ambiguous"))
        # a holder clipped all round hides how far beyond full scale its step goes, and
        # with it where its edges are; a faint one (found only by the tracker's second,
        # fainter search) is a few DN from not being found: commissioning is where the
        # exposure and the light get set
        kind = "" if not pose.warning else "faint" if pose.faint else "clipped"
        self._add(Finding("top.exposure", "warn" if pose.warning else "pass",
                          f"top camera: {pose.warning}" if pose.warning else
                          "the holder's edges stay within the sensor's range (not clipped "
                          "along all four sides) and step 15 DN or more", name=kind))
        assert self.tools is not None
        cam = self.rig.camera("top")
        assert cam is not None
        pc = self.cfg.procedure.precheck
        # a still view's frames: what the camera does to them (its tone curve against
        # cameras[].gamma, sharpening, coding, clipping), and the rim's when it takes them
        # still
        still = self._camera_check("top", cam, max(pc.rim_frames, CAMERA_CHECK_FRAMES))
        if self.tools.rim is None:
            self._add(Finding("top.rim", "warn", "no rim measuring function: eccentricity and "
                              "zenith not measured", name="not measured"))
            return
        try:
            # the frames the alignment's rim pre-check averages (at small e one frame's
            # noise is most of e's uncertainty), turned as it turns them
            frames = still[:pc.rim_frames] if still and not pc.rim_turn_deg else \
                grab_rim_frames(self.rig, cam, pc.rim_frames, pc.rim_turn_deg, self.abort)
            info = self.tools.rim(frames, self.c.rim_radius_mm, self.c.top_camera_height_mm)
        except AbortRequested:
            raise
        except AligndError as exc:
            self._add(Finding("top.rim", "warn", f"rim not measurable: {exc}",
                              name="not measured"))
            return
        self.rim_centre = np.asarray(info.center_px, float)
        turned = (f", turned {pc.rim_turn_deg:g} deg apart"
                  if pc.rim_turn_deg and len(frames) > 1 else "")
        e_max = self.cfg.procedure.precheck.max_eccentricity
        verdict: FindingVerdict = "pass" if info.eccentricity <= e_max else "fail"
        zen = "" if info.zenith_deg is None else f", camera zenith {info.zenith_deg:.2f} deg"
        u = "" if info.eccentricity_u is None else f" +- {info.eccentricity_u:.4f}"
        advice, fix, tried = "", None, None
        if info.eccentricity_u is not None and info.eccentricity_u > RIM_U_CERTAIN:
            advice, fix, tried = self._rim_uncertain(cam, info.eccentricity_u)
            advice = f"; e is uncertain to more than {RIM_U_CERTAIN:g}: {advice}"
            if verdict == "pass":
                verdict = "warn"
        value: dict[str, Any] = {"eccentricity": info.eccentricity,
                                 "zenith_deg": info.zenith_deg, "center_px": info.center_px}
        sigma: dict[str, Any] = {"eccentricity": info.eccentricity_u}
        if tried is not None:
            value["eccentricity_turned"] = tried.eccentricity
            sigma["eccentricity_turned"] = tried.eccentricity_u
        self._add(Finding("top.rim", verdict,
                          f"rim eccentricity {info.eccentricity:.4f}{u} (limit {e_max:g}; mean "
                          f"of {len(frames)} frames{turned}){zen}{advice}",
                          value=value, sigma=sigma,
                          expected={"max_eccentricity": e_max}, config_fix=fix,
                          name="camera not on the axis" if verdict == "fail"
                          else "uncertain" if verdict == "warn" else ""))

    def _rim_uncertain(self, cam: Camera, u: float
                       ) -> tuple[str, dict[str, Any] | None, RimInfo | None]:
        """Why the rim's e is uncertain (``u``) and what makes it certain
        (:func:`rim_advice`), with the config fix. Where the advice is to turn the disc
        between the frames, frames are taken so here and measured, and the fix stands
        only if their e is clearly more certain (the turned reading is returned too)."""
        assert self.tools is not None and self.tools.rim is not None
        pc = self.cfg.procedure.precheck
        lim = self.rig.axis("turntable").config.soft_limits
        advice, fix = rim_advice(pc.rim_frames, pc.rim_turn_deg, lim.min, lim.max)
        step = (fix or {}).get("procedure.precheck.rim_turn_deg")
        if step is None:
            return advice, fix, None
        try:
            frames = grab_rim_frames(self.rig, cam, pc.rim_frames, float(step), self.abort)
            tried = self.tools.rim(frames, self.c.rim_radius_mm, self.c.top_camera_height_mm)
        except AbortRequested:
            raise
        except AligndError as exc:
            return (f"{advice}; with the disc turned {step:g} deg apart: not measurable "
                    f"({exc})", None, None)
        u2 = tried.eccentricity_u
        read = (f"turned {step:g} deg apart here, e reads {tried.eccentricity:.4f}"
                + ("" if u2 is None else f" +- {u2:.4f}"))
        if u2 is not None and u2 <= RIM_TURN_GAIN * u:
            return f"{advice}; {read}", fix, tried
        return (f"{read}, no more certain: the frames' noise or the rim's own edge limits "
                f"it: {RIM_LEFT}", None, tried)

    def _camera_check(self, role: Literal["top", "side"], cam: Camera, n: int
                      ) -> list[Frame]:
        """``n`` frames of the still view, checked for what the camera does to them
        (``tools.camera``): a ``<role>.frames`` finding, a warning where a camera setting
        should change or the frames' tone curve is not the configured ``gamma`` (the fix
        named). Returns the frames ([] without the tool or when they could not be had)."""
        assert self.tools is not None
        if self.tools.camera is None:
            return []
        item = f"{role}.frames"
        try:
            frames = grab_frames(cam, n, self.abort)
            info = self.tools.camera(frames)
        except AbortRequested:
            raise
        except AligndError as exc:
            self._add(Finding(item, "warn", f"{role} camera not checked: {exc}",
                              name="not measured"))
            return []
        cfg_cam = self.cfg.camera(role)
        configured: ToneCurve = cfg_cam.gamma if cfg_cam is not None else 1.0
        said = list(info.act)
        fix = None
        g, allowed = info.gamma, info.gamma_range
        if g is not None and allowed is not None and disagrees(configured, allowed):
            said.append(f"the frames' noise says the camera's tone curve is {info.text}, "
                        f"the config says {curve_text(configured)}: measure it "
                        f"(docs/configure.md, two exposures) and set cameras[{role}].gamma")
            fix = {f"cameras.{role}.gamma": round(g, 1)}
        message = "; ".join(said) if said else (
            f"tone curve {info.text} (config: {curve_text(configured)}); no setting to change")
        self._add(Finding(item, "warn" if said else "pass", f"{len(frames)} frames of a still "
                          f"view: {message}", value=info.record, sigma={"gamma": info.gamma_u},
                          expected={"gamma": configured}, config_fix=fix,
                          name="camera settings" if said else ""))
        return frames

    def _there_and_back(self, role: str, angle_deg: float, repeats: int
                        ) -> tuple[np.ndarray, float, float, float, float, np.ndarray]:
        """Moves of ``role`` at a table angle: slope (px/mm), its sigma, backlash (px along
        the axis) with sigma, repeatability (px), and the base centre."""
        ax = self.rig.axis(role)
        lim = ax.config.soft_limits
        base = ax.position()
        d = self.c.stage_step_mm
        if base + d > lim.max:
            d = -d
        if not lim.min <= base + d <= lim.max:
            raise ConfigError(f"commission: no room for a {abs(d):g} mm move of {role} around "
                              f"{base:.3f} within [{lim.min:g}, {lim.max:g}]")
        approach = ax.config.approach
        other: Literal["+", "-"] = "-" if approach == "+" else "+"
        far, here, back = [], [], []
        for r in range(repeats):
            self._emit("axes", f"{role}: there-and-back move {r + 1} of {repeats}")
            p_far = self._move(role, base + d)
            far.append((p_far, self._need(f"{role}-{angle_deg:g}-far-{r}").centre))
            p0 = self._move(role, base)
            here.append((p0, self._need(f"{role}-{angle_deg:g}-base-{r}").centre))
            p1 = self._move(role, base, other)
            back.append((p1, self._need(f"{role}-{angle_deg:g}-other-{r}").centre))
        self._move(role, base)
        s = np.array([p for p, _ in far + here])
        c = np.array([z for _, z in far + here])
        X = np.column_stack([np.ones_like(s), s - s.mean()])
        coef, *_ = np.linalg.lstsq(X, c, rcond=None)
        res = c - X @ coef
        s2 = float((res ** 2).sum()) / max(2 * (len(s) - 2), 1)
        slope = coef[1]
        sig = math.sqrt(s2 / float(((s - s.mean()) ** 2).sum()))
        unit = slope / float(np.hypot(*slope))
        a = np.array([float(z @ unit) for _, z in here])
        b = np.array([float(z @ unit) for _, z in back])
        diff = b - a
        # the sign: the load lags the motor, so an arrival moving against the approach
        # direction stops beyond the target (as seen along the approach direction)
        sgn = 1.0 if approach == "+" else -1.0
        backlash = float(sgn * diff.mean())
        bsig = float(diff.std(ddof=1) / math.sqrt(len(diff))) if len(diff) > 1 else math.nan
        rep = float(a.std(ddof=1)) if len(a) > 1 else math.nan
        return slope, sig, backlash, bsig, rep, np.mean([z for _, z in here], axis=0)

    def _translation_axes(self) -> None:
        """Direction, length, backlash and repeatability of x, y and the translator."""
        pose = self.start_pose
        assert pose is not None  # _top_camera_static found it
        c = pose.corners
        u = ((c[1] - c[0]) + (c[2] - c[3])) / 2
        v = ((c[3] - c[0]) + (c[2] - c[1])) / 2
        u_hat = u / np.hypot(*u)
        v_hat = v - u_hat * float(u_hat @ v)
        v_hat = v_hat / np.hypot(*v_hat)
        self.holder_px = (float(np.hypot(*u)), float(np.hypot(*v)))
        roles = [r for r in ("x", "y", "translator") if r in self.rig.axes
                 and self.rig.axis(r).config.units == "mm"]
        for role in roles:
            slope, sig, bl, bsig, rep, _ = self._there_and_back(role, 0.0, self.c.repeats)
            n = float(np.hypot(*slope))
            self.rec.axes[role] = AxisMeasurement(
                role, slope, sig, (float(slope @ u_hat / n), float(slope @ v_hat / n)),
                bl / n, bsig / n if math.isfinite(bsig) else math.nan, rep / n)
        self._roles_findings(roles)
        # the same moves at a second table angle: the stages must turn with the table
        tt = self.rig.axis("turntable").config.soft_limits
        a2 = min(SECOND_ANGLE_DEG, tt.max)
        if a2 >= 20.0:
            self._move("turntable", a2)
            a2r = self.rig.axis("turntable").position()
            sign = self.cfg.procedure.turntable_direction
            for role in ("x", "y"):
                if role not in self.rec.axes:
                    continue
                slope, *_ = self._there_and_back(role, a2, 1)
                # measured slope turned back by the table's image rotation, vs the one at 0
                # (the sign is not known yet here: take the one that agrees better)
                m0 = self.rec.axes[role].image_px_per_mm
                best = min((abs(_angle_between(rot(-s * a2r) @ slope, m0)), s)
                           for s in (sign, -sign))
                self.rec.axes[role].turn_check_deg = best[0]
            self._move("turntable", 0.0)
            worst = max((a.turn_check_deg or 0.0) for a in self.rec.axes.values())
            ok = worst <= MAX_TURN_DISAGREE_DEG
            self._add(Finding(
                "axes.turn_with_table", "pass" if ok else "fail",
                f"x/y moves at {a2r:.1f} deg, turned back, agree with those at 0 within "
                f"{worst:.2f} deg" + ("" if ok else ": the stages do not ride on the "
                                      "turntable, or the table slipped"),
                value=worst, unit="deg", expected=f"<= {MAX_TURN_DISAGREE_DEG}",
                name="" if ok else "stages not on the table"))

    def _turned_half(self) -> None:
        """x, y and the translator all reversed in the holder frame: one finding that says
        what the three mean together, a top camera turned 180 deg against the holder, and
        that the stages are not what to change (the x and y findings alone advise
        reversing them). With x and y alone reversed, stages wired the other way read the
        same, and the two findings stand on their own."""
        other = turned(self.frame_target, 2)
        self._add(Finding(
            "top.turned_half", "warn",
            "x and y both move the holder opposite the holder frame's u and v, and the "
            "translator away from holder.target_mm: the top camera is turned 180 deg "
            "against the holder (or the holder is mounted the other way round), rather than "
            "three stages reversed. Turn the camera back, or keep it and set "
            f"holder.target_mm: [{other[0]:g}, {other[1]:g}] (the sample's side, where the "
            "translator moves); x and y inverted do not stop an alignment (its calibration "
            "learns the mapping)", name="camera turned 180 deg",
            config_fix={"holder.target_mm": list(other)}))

    def _frame_target(self, translator: tuple[float, float] | None) -> tuple[float, float]:
        """holder.target_mm in the image's holder frame. Where u and v are the other way
        round from holder.size_mm, a symmetric rectangle names two targets, opposite each
        other: the one the translator moves towards (the convention, docs/configure.md),
        else the one of a config whose u pointed right in the image."""
        order = self.start_order
        if order is None or not order.swapped:
            return self.cfg.holder.target_mm
        tu, tv = order.image_target_mm(self.cfg.holder.target_mm)
        if translator is not None and not math.isnan(translator[0]) \
                and translator[0] * tu + translator[1] * tv < 0:
            return turned((tu, tv), 2)
        return tu, tv

    def _roles_findings(self, roles: Sequence[str]) -> None:
        """Which config role moves which way in the holder frame; swapped / inverted."""
        names = {(1.0, 0.0): "+u", (-1.0, 0.0): "-u", (0.0, 1.0): "+v", (0.0, -1.0): "-v"}
        along: dict[str, tuple[float, float]] = {}
        for role in roles:
            m = self.rec.axes[role]
            du, dv = m.holder_uv
            best = max(names, key=lambda k: k[0] * du + k[1] * dv)
            cone = math.degrees(math.acos(max(-1.0, min(1.0, best[0] * du + best[1] * dv))))
            along[role] = best if cone <= ROLE_CONE_DEG else (math.nan, math.nan)
        tu, tv = self.frame_target = self._frame_target(along.get("translator"))
        tn = math.hypot(tu, tv) or 1.0
        expected = {"x": (1.0, 0.0), "y": (0.0, 1.0), "translator": (tu / tn, tv / tn)}
        for role in roles:
            m = self.rec.axes[role]
            exp = expected[role]
            got = along[role]
            exp_name = names.get((round(exp[0]), round(exp[1])), f"({exp[0]:.2f}, {exp[1]:.2f})")
            got_name = names.get(got, "no holder axis")
            desc = (f"config role {role} moves the holder along {got_name} of the holder frame "
                    f"(image {m.image_angle_deg:+.1f} deg, {m.length_px_per_mm:.3f} ± "
                    f"{m.sigma_px_per_mm:.3f} px/mm); backlash {m.backlash_mm * 1000:.1f} ± "
                    f"{m.backlash_sigma_mm * 1000:.1f} um, repeatability "
                    f"{m.repeatability_mm * 1000:.2f} um")
            verdict: FindingVerdict = "pass"
            name = ""
            fix: dict[str, object] | None = None
            if role in ("x", "y") and not math.isnan(got[0]):
                other = "y" if role == "x" else "x"
                if abs(got[0]) != abs(exp[0]):  # along the other holder axis
                    o = along.get(other)
                    swapped = o is not None and not math.isnan(o[0]) and \
                        abs(o[0]) != abs(expected[other][0])
                    verdict, name = "fail", "swapped" if swapped else "wrong axis"
                    if swapped:
                        desc += (f": x and y are swapped (the stage the config calls {role} "
                                 f"moves along {got_name}, expected {exp_name}); exchange the "
                                 "roles (or addresses) of x and y in the config")
                        fix = {"swap_roles": ["x", "y"]}
                    else:
                        desc += f": expected along {exp_name}"
                elif got != (round(exp[0]), round(exp[1])):
                    verdict, name = "warn", "inverted"
                    desc += (f": inverted (expected {exp_name}); alignd's calibration copes, "
                             "but the holder-frame convention of docs/configure.md is not met: "
                             "reverse the stage's direction in its controller, or mount the "
                             "holder turned by 180 deg")
            elif math.isnan(got[0]):
                verdict, name = "warn", "oblique"
                desc += f": not within {ROLE_CONE_DEG:g} deg of a holder axis"
            elif role == "translator" and got == (-round(exp[0]), -round(exp[1])):
                verdict, name = "warn", "away from the target"
                far = turned((tu, tv), 2)
                fix = {"holder.target_mm": list(far)}
                desc += (f": it moves away from holder.target_mm [{tu:g}, {tv:g}] (expected "
                         f"{exp_name}). Either the sample is on the holder's other side (the "
                         "top camera turned 180 deg from the one the config was written for, "
                         f"or the holder mounted the other way round: set holder.target_mm: "
                         f"[{far[0]:g}, {far[1]:g}]), or the translator's direction is "
                         "reversed: check the target on the picture")
            elif role == "translator" and got != (round(exp[0]), round(exp[1])):
                verdict, name = "warn", "not along the sample normal"
                desc += (f": expected along the sample normal {exp_name} (towards "
                         "holder.target_mm)")
            self._add(Finding(f"axis.{role}.direction", verdict, desc,
                              value={"holder_uv": m.holder_uv,
                                     "image_angle_deg": m.image_angle_deg},
                              expected=exp_name, name=name, config_fix=fix))
            self._add(Finding(
                f"axis.{role}.backlash", "pass" if abs(m.backlash_mm) * 1000 <= 20 else "warn",
                f"{m.backlash_mm * 1000:.1f} ± {m.backlash_sigma_mm * 1000:.1f} um "
                f"(the configured approach of {self.rig.axis(role).config.backlash_approach:g} "
                f"mm takes it out); repeatability {m.repeatability_mm * 1000:.2f} um",
                value={"backlash_um": m.backlash_mm * 1000,
                       "repeatability_um": m.repeatability_mm * 1000},
                sigma=m.backlash_sigma_mm * 1000, unit="um"))
            ba = self.rig.axis(role).config.backlash_approach
            if abs(m.backlash_mm) > ba > 0:
                self.rec.findings[-1].verdict = "fail"
                self.rec.findings[-1].name = "backlash exceeds approach"
                self.rec.findings[-1].config_fix = {
                    f"axis.{role}.backlash_approach": round(3 * abs(m.backlash_mm), 4)}
        tr = expected["translator"]
        if (along.get("x") == (-1.0, 0.0) and along.get("y") == (0.0, -1.0)
                and along.get("translator") == (-round(tr[0]), -round(tr[1]))):
            self._turned_half()
        if "x" in self.rec.axes and "y" in self.rec.axes:
            a = self.rec.axes["x"].image_px_per_mm
            b = self.rec.axes["y"].image_px_per_mm
            skew = abs(_angle_between(a, b)) - 90.0
            sig = math.degrees(max(self.rec.axes["x"].sigma_px_per_mm / np.hypot(*a),
                                   self.rec.axes["y"].sigma_px_per_mm / np.hypot(*b)))
            self._add(Finding("axes.skew", "pass" if abs(skew) <= 3 else "warn",
                              f"x and y are {90 + skew:.2f} deg apart (skew {skew:+.2f} ± "
                              f"{sig:.2f} deg); the calibration takes it into account",
                              value=skew, sigma=sig, unit="deg",
                              name="" if abs(skew) <= 3 else "not square"))

    def _scales(self) -> None:
        """Pixel size at the holder's face from the stage moves; the holder's size from it."""
        lengths = [self.rec.axes[r].length_px_per_mm for r in ("x", "y") if r in self.rec.axes]
        sig = [self.rec.axes[r].sigma_px_per_mm for r in ("x", "y") if r in self.rec.axes]
        px_um = 1000.0 / float(np.mean(lengths))
        rel_sig = float(np.sqrt(np.mean(np.square(np.asarray(sig) / np.asarray(lengths)))))
        # the two stages should agree: a wrong stage model on one of them shows here
        spread = abs(lengths[0] / lengths[-1] - 1.0) if len(lengths) == 2 else 0.0
        self.rec.pixel_size_um = px_um
        conf = configured_pixel_size_um(self.cfg)
        c = self.c
        if conf is None:
            self._add(Finding("top.pixel_size", "warn", f"{px_um:.2f} um/px at the holder's "
                              "face; the config has no cameras.top.pixel_size_um",
                              value=px_um, sigma=px_um * rel_sig, unit="um/px",
                              config_fix={"cameras.top.pixel_size_um": round(px_um, 2)},
                              name="not configured"))
        else:
            rel = px_um / conf - 1.0
            verdict: FindingVerdict = "pass" if abs(rel) <= c.pixel_size_warn else (
                "warn" if abs(rel) <= c.pixel_size_fail else "fail")
            self._add(Finding(
                "top.pixel_size", verdict,
                f"{px_um:.2f} ± {px_um * rel_sig:.2f} um/px at the holder's face (from the x/y "
                f"moves), config {conf:g} um/px ({rel * 100:+.1f} %)"
                + ("" if verdict == "pass" else
                   f": set cameras.top.pixel_size_um: {px_um:.1f} (or check the stages' "
                   "`stage` models: their scale sets this measurement)"),
                value=px_um, sigma=px_um * rel_sig, expected=conf, unit="um/px",
                config_fix=None if verdict == "pass"
                else {"cameras.top.pixel_size_um": round(px_um, 1)},
                name="" if verdict == "pass" else "pixel size wrong"))
        if spread > 0.02:
            self._add(Finding("axes.scale", "fail",
                              f"x and y disagree on the image scale by {spread * 100:.1f} %: "
                              "one stage's `stage` model (its mm per step) is wrong",
                              value=spread, unit="", name="stage scale"))
        mm_u, mm_v = (p * px_um / 1000.0 for p in self.holder_px)
        self.rec.holder_size_mm = (mm_u, mm_v)
        su, sv = self.cfg.holder.size_mm
        rel_u, rel_v = mm_u / su - 1.0, mm_v / sv - 1.0
        worst = max(abs(rel_u), abs(rel_v))
        swapped = max(abs(mm_u / sv - 1.0), abs(mm_v / su - 1.0)) < c.holder_size_warn < worst
        verdict = "pass" if worst <= c.holder_size_warn else (
            "warn" if worst <= c.holder_size_fail else "fail")
        msg = (f"measured {mm_u:.2f} x {mm_v:.2f} mm (u x v, ± {rel_sig * 100:.1f} %), "
               f"config holder.size_mm {su:g} x {sv:g} ({rel_u * 100:+.1f} %, "
               f"{rel_v * 100:+.1f} %)")
        name = ""
        fix: dict[str, object] | None = None
        if swapped:
            verdict, name = "fail", "u and v swapped"
            tu, tv = self.frame_target
            fix = {"holder.size_mm": [sv, su], "holder.target_mm": [tu, tv]}
            by = ("the side the translator moves towards" if "translator" in self.rec.axes
                  else "if your u pointed right in the image")
            msg += (": u and v are swapped (the camera is turned past the holder's diagonal "
                    "against the holder frame of the config): set holder.size_mm: "
                    f"[{sv:g}, {su:g}] and holder.target_mm: [{tu:g}, {tv:g}] (the same point "
                    f"in the image's frame, {by}), see docs/configure.md")
        elif verdict != "pass":
            name = "holder size wrong"
            msg += f": set holder.size_mm: [{mm_u:.2f}, {mm_v:.2f}] (measure it again)"
            fix = {"holder.size_mm": [round(mm_u, 2), round(mm_v, 2)]}
        self._add(Finding("holder.size", verdict, msg, value=[mm_u, mm_v],
                          sigma=[mm_u * rel_sig, mm_v * rel_sig], expected=[su, sv], unit="mm",
                          name=name, config_fix=fix))

    def _turntable(self) -> None:
        """Wide sweep: direction, angle scale, runout; backlash from both sides at 0."""
        ax = self.rig.axis("turntable")
        lim = ax.config.soft_limits
        half = self.c.sweep_deg / 2.0
        lo, hi = max(-half, lim.min), min(half, lim.max)
        step = self.c.step_deg
        if self.c.sweep_deg >= 360.0 and hi - lo >= 360.0:
            angles = np.arange(lo, lo + 360.0 - step / 2, step)
        else:
            n = max(round((hi - lo) / step) + 1, 3)
            angles = np.linspace(lo, hi, n)
        if ax.config.approach == "-":
            angles = angles[::-1]
        if hi - lo < self.c.sweep_deg - 1e-6:
            self.recorder.event(f"commission sweep clipped to the turntable's soft limits "
                                f"[{lo:g}, {hi:g}] deg (commission.sweep_deg "
                                f"{self.c.sweep_deg:g})")
        readback: list[float] = []
        points = np.full((len(angles), 4, 2), np.nan)
        for i, a in enumerate(angles):
            readback.append(self._move("turntable", float(a)))
            # "commission-0-<step>-<n>", labelled like the other sweeps' frames
            pose = self._look(f"0-{i:03d}", frames=FRAMES_PER_SWEEP_STEP)
            if pose is not None:
                points[i] = pose.corners
            self._emit("turntable", f"runout sweep at {readback[-1]:+.2f} deg",
                       step=i + 1, total=len(angles))
        self.recorder.sweep("commission", 0, {"version": 1, "pixel_size_um":
                                              self.rec.pixel_size_um, "frames": [
            {"angle_deg": float(a), "features": [[float(x), float(y)] for x, y in p]
             if np.all(np.isfinite(p)) else [None] * 4}
            for a, p in zip(readback, points, strict=True)]}, [float(a) for a in angles],
            readback)
        rb = np.asarray(readback)
        ok = np.all(np.isfinite(points), axis=(1, 2))
        if ok.sum() < max(8, 0.6 * len(rb)):
            raise VisionError(f"holder tracked in only {int(ok.sum())} of {len(rb)} frames of "
                              "the commission sweep")
        # perspective first (as every sweep does): a tilted camera images the holder's circle
        # as an ellipse (a harmonic-2 motion that is no part of the bearing's) and its edges
        # turned by a little more or less than the table (no part of the encoder's error)
        # (in the image's own frame where the config's u and v are the other way round,
        # which holder.size names: rectified onto the config's lengths, the holder's
        # square-on view was squashed across, and its turn read as a 1.2 deg periodic
        # angle error and 207 um of error motion)
        ordered, ref = holder_frame_order(points, rb, self.cfg.holder.size_mm)
        holder = self.cfg.holder if ref is None or not ref.swapped else \
            image_frame(self.cfg.holder, ref)
        rectified = apply_h(rectifier(ordered, holder), ordered)
        img_deg = holder_image_angles(rectified)
        fit = fit_slope(rb, img_deg)
        sign = fit.sign
        conf_sign = self.cfg.procedure.turntable_direction
        self.rec.turntable_sign = sign
        self.rec.angle_scale = fit.scale
        if sign == conf_sign:
            self._add(Finding("turntable.direction", "pass",
                              f"image turns {sign:+d} (as configured): slope "
                              f"{fit.slope:+.5f} ± {fit.sigma:.5f}", value=sign,
                              expected=conf_sign))
        else:
            self._add(Finding(
                "turntable.direction", "warn",
                f"reversed: a positive turntable angle turns the image the other way round "
                f"(slope {fit.slope:+.5f} ± {fit.sigma:.5f}; config procedure."
                f"turntable_direction {conf_sign:+d}), or the top camera is mirrored; align "
                "and check use the measured direction while this record is valid; to make "
                f"the config say so, set procedure.turntable_direction: {sign:+d}",
                value=sign, expected=conf_sign, name="reversed",
                config_fix={"procedure.turntable_direction": sign}))
        dev = fit.scale - 1.0
        bound = max(ANGLE_SCALE_WARN, 4 * fit.sigma)
        # compensated while the record is valid (a warning); beyond 10 % it is no scale
        # error but a wrong axis or stage
        verdict: FindingVerdict = "pass" if abs(dev) <= bound else (
            "warn" if abs(dev) <= 0.1 else "fail")
        self._add(Finding(
            "turntable.angle_scale", verdict,
            f"{fit.scale:.5f} ± {fit.sigma:.5f} table degrees per read-back degree "
            f"({dev * 100:+.3f} %, over {float(np.ptp(rb)):.0f} deg)"
            + ("" if verdict == "pass" else ": the turntable's `stage` model or gear ratio is "
               "wrong in its controller or the config; align and check use the measured "
               "scale while this record is valid"),
            value=fit.scale, sigma=fit.sigma, expected=1.0, name="" if verdict == "pass"
            else "mis-scaled"))
        # the encoder's periodic error: the image angle's wiggle about the straight line
        if float(np.ptp(rb)) >= 90.0:
            err = fit_angle_error(rb, img_deg, sign)
            self.rec.angle_error = err.error
            self.rec.angle_scale = err.scale
            verdict = "pass" if err.peak_deg <= ANGLE_ERROR_WARN_DEG else "warn"
            self._add(Finding(
                "turntable.angle_error", verdict,
                f"periodic angle error {err.peak_deg:.4f} deg peak (harmonics "
                f"{', '.join(str(h) for h, _c, _d in err.error) or 'none significant'}; "
                f"{err.sigma_deg:.4f} deg per frame); align and check take it out while this "
                "record is valid", value=err.peak_deg, sigma=err.sigma_deg, unit="deg",
                name="" if verdict == "pass" else "large angle error"))
        px_mm = (self.rec.pixel_size_um or 1.0) / 1000.0
        centres = rectified.mean(axis=1)
        # the runout map in the table's true angles (scale and encoder error taken out: an
        # angle error moves the holder along its circle, which is no error of the bearing),
        # indexed by the read-back angle as later sweeps look it up
        true_deg = sign * self.rec.angle_map("commission").image_angles(rb)
        order = np.argsort(true_deg)
        try:
            rmap = fit_runout(true_deg, centres, px_mm, sign=sign)
            rmap = RunoutMap(np.interp(rmap.angles_deg, true_deg[order], rb[order]),
                             rmap.offset_mm, rmap.residual_um)
        except SolveError as exc:
            self._add(Finding("turntable.runout", "warn", f"not measured: {exc}",
                              name="not measured"))
        else:
            self.rec.runout = rmap
            sysu = self.cfg.procedure.systematic_um
            amp = rmap.amplitude_um
            verdict = "pass" if amp <= 3 * max(sysu, 1.0) else "warn"
            self._add(Finding(
                "turntable.runout", verdict,
                f"error motion {amp:.2f} um peak over {float(np.ptp(rb)):.0f} deg "
                f"({len(rmap.angles_deg)} angles, residual {rmap.residual_um:.2f} um 1 sigma); "
                "align and check subtract it while this record is valid",
                value=amp, sigma=rmap.residual_um, unit="um",
                expected=f"procedure.systematic_um {sysu:g}",
                name="" if verdict == "pass" else "large runout"))
        self.axis_px = _circle_centre(true_deg * sign, centres)
        self.rec.axis_px = (float(self.axis_px[0]), float(self.axis_px[1]))
        rim = self.rim_centre
        if rim is not None:
            d_um = float(np.hypot(*(self.axis_px - rim))) * (self.rec.pixel_size_um or 0)
            self._add(Finding("top.axis_vs_rim", "pass" if d_um <= 500 else "warn",
                              f"the rotation axis is imaged {d_um:.0f} um from the rim "
                              "ellipse's centre (at different heights: a tilted camera "
                              "separates them)", value=d_um, unit="um"))
        self._turntable_backlash()

    def _turntable_backlash(self) -> None:
        ax = self.rig.axis("turntable")
        other: Literal["+", "-"] = "-" if ax.config.approach == "+" else "+"
        assert self.start_pose is not None
        arm = self.start_pose.centre - self.axis_px
        r = float(np.hypot(*arm))
        tang = np.array([-arm[1], arm[0]]) / max(r, 1e-9)  # +a turns the arm this way
        sgn = (self.rec.turntable_sign or 1)
        a, b = [], []
        for k in range(self.c.repeats):
            self._emit("turntable", f"turntable backlash {k + 1} of {self.c.repeats}")
            self._move("turntable", 0.0)
            a.append(float(self._need(f"tt-base-{k}").centre @ tang))
            self._move("turntable", 0.0, other)
            b.append(float(self._need(f"tt-other-{k}").centre @ tang))
        self._move("turntable", 0.0)
        d = (np.asarray(b) - np.asarray(a)) * sgn / r  # rad, in table degrees' sense
        s_appr = 1.0 if ax.config.approach == "+" else -1.0
        bl = math.degrees(s_appr * float(d.mean()))
        sig = math.degrees(float(d.std(ddof=1)) / math.sqrt(len(d))) if len(d) > 1 else math.nan
        ba = ax.config.backlash_approach
        verdict: FindingVerdict = "pass" if abs(bl) <= max(ba, 0.0) or ba == 0 else "fail"
        if ba == 0 and abs(bl) > 3 * (sig if math.isfinite(sig) else 0.0) + 0.001:
            verdict = "warn"
        self._add(Finding("turntable.backlash", verdict,
                          f"{bl:.4f} ± {sig:.4f} deg (configured approach "
                          f"{ba:g} deg takes it out)", value=bl, sigma=sig, unit="deg",
                          name="" if verdict == "pass" else "backlash"))

    def _side_camera(self) -> None:
        side = self.rig.camera("side")
        if side is None:
            self._add(Finding("side.camera", "warn", "no side camera configured: tilt is not "
                              "measured by align", name="absent"))
            return
        assert self.tools is not None
        if self.tools.side is None:
            self._add(Finding("side.camera", "warn", "no side measuring function",
                              name="not measured"))
            return
        self._camera_check("side", side, CAMERA_CHECK_FRAMES)
        try:
            s0 = self.tools.side(grab_fresh(side, side.clock.now()))
        except AligndError as exc:
            self._add(Finding("side.camera", "fail", f"pole or sample not found: {exc}",
                              name="targets not found"))
            return
        self._add(Finding("side.camera", "pass",
                          f"pole found at x {s0.pole_x_px:.1f} px ({s0.pole_angle_deg:+.3f} deg),"
                          f" sample at x {s0.sample_x_px:.1f} px ({s0.sample_angle_deg:+.3f} "
                          f"deg): tilt {s0.tilt_deg:+.3f} deg",
                          value={"tilt_deg": s0.tilt_deg, "pole_x_px": s0.pole_x_px,
                                 "sample_x_px": s0.sample_x_px}))
        if "translator" not in self.rig.axes:
            return
        ax = self.rig.axis("translator")
        base = ax.position()
        d = self.c.stage_step_mm * 2
        lim = ax.config.soft_limits
        if base + d > lim.max:
            d = -d
        self._move("translator", base + d)
        try:
            s1 = self.tools.side(grab_fresh(side, side.clock.now()))
        finally:
            self._move("translator", base)
        shift = (s1.sample_x_px - s0.sample_x_px) * (1 if d > 0 else -1)
        if abs(shift) < 1.0:
            self._add(Finding("side.tilt_sign", "warn", f"a {abs(d):g} mm translator move "
                              f"shifted the sample by only {shift:.2f} px in the side image: "
                              "the side camera does not look along the sample surface",
                              value=shift, unit="px", name="not measurable"))
            return
        toward = "+x" if shift > 0 else "-x"
        self._add(Finding(
            "side.tilt_sign", "pass",
            f"moving the sample along its normal moves it towards {toward} in the side image "
            f"({shift:+.1f} px per {abs(d):g} mm): a positive tilt_deg leans the sample's top "
            f"{'towards' if shift > 0 else 'away from'} its normal",
            value=1 if shift > 0 else -1, unit=""))


def _angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Signed angle (deg) from vector a to vector b."""
    return math.degrees(math.atan2(a[0] * b[1] - a[1] * b[0], float(a @ b)))


def _circle_centre(image_angles_deg: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Centre of rotation (px) from points at known image angles: z = c + R(a) p."""
    ok = np.all(np.isfinite(centres), axis=1)
    a = np.radians(image_angles_deg[ok])
    z = centres[ok]
    n = len(a)
    A = np.zeros((2 * n, 4))
    A[0::2, 0] = 1
    A[1::2, 1] = 1
    A[0::2, 2], A[0::2, 3] = np.cos(a), -np.sin(a)
    A[1::2, 2], A[1::2, 3] = np.sin(a), np.cos(a)
    sol, *_ = np.linalg.lstsq(A, z.reshape(-1), rcond=None)
    return sol[:2]
