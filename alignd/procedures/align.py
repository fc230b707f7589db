"""The closed loop: measure the target's offset from the rotation axis, move, repeat, verify.

``run_alignment``: connect, identify and home; pre-checks (top-camera eccentricity,
side-camera tilt); calibrate the stage-to-image mapping; then iterate: sweep -> centre with
covariance -> target offset with uncertainty -> stage moves in the rotating frame (clamped
to the maximum step and the soft limits) -> move, until the offset plus its expanded
uncertainty is within the tolerance; then a separate verification sweep decides the
verdict. ``run_check`` makes the same measurement without moving any translation stage.

Nothing moves on data that failed a check (tracking lost, centre too uncertain); an abort
or a device error stops every axis. The simulator's truth is read only after the run.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from alignd.config import AligndConfig
from alignd.errors import AligndError, ConfigError, DeviceError, StateError, VisionError
from alignd.procedures.calibrate import Calibration, calibrate, configured_pixel_size_um
from alignd.procedures.events import ProgressCallback, ProgressEvent, no_progress
from alignd.procedures.recorder import NullRecorder, RunRecorder
from alignd.procedures.result import RunResult
from alignd.procedures.rig import AbortRequested, Rig, check_abort, validate_rig
from alignd.procedures.sweep import CentrePool, Measurement, grab_fresh, measure
from alignd.procedures.tools import Tools, default_tools

log = logging.getLogger(__name__)

MAX_CAL_REFRESHES = 2
CAL_DISAGREE_REL = 0.15  # observed vs predicted change of offset, beyond noise
BROYDEN_MIN_SNR = 30.0  # update J only from moves this far above the noise
DIVERGE_RATIO = 1.5
HOLDER_LOOK_FRAMES = 3
# the loop keeps correcting until the measured offset is below this fraction of the
# tolerance or within its own noise (2 sigma): moves are cheap, chasing noise is not
RESIDUAL_FRACTION = 0.3
CONFORMANCE = 0.95  # "within tolerance" needs P(|offset| <= tolerance) >= this
# ``procedure.systematic_um``: the 1-sigma per axis that no sweep averages out, the
# turntable's radial error motion. Over a +-10 deg sweep a radial error motion that changes
# with the angle is indistinguishable from a shifted centre (a 2 um third-harmonic wobble
# shifts it by up to 6 um), and every sweep sees the same one. 3 um suits a precision
# rotation stage; a rig with a better or worse bearing sets its own value.


class _Stop(AligndError):
    """Ends the loop with a verdict that is not an error (refusal, not converged)."""

    def __init__(self, verdict: str, reason: str, measurement: Measurement | None = None):
        super().__init__(reason)
        self.verdict = verdict
        self.reason = reason
        self.measurement = measurement


@dataclass
class _State:
    iterations: int = 0
    last: Measurement | None = None
    tilt_deg: float | None = None
    warnings: list[str] = field(default_factory=list)
    history: list[dict[str, Any]] = field(default_factory=list)
    calibration: Calibration | None = None
    compute_s: float = 0.0
    motion_s: float = 0.0


def run_alignment(rig: Rig, cfg: AligndConfig, *, progress: ProgressCallback | None = None,
                  abort: threading.Event | None = None, recorder: RunRecorder | None = None,
                  tools: Tools | None = None, run_id: str | None = None,
                  frames_per_step: int | None = None,
                  systematic_um: float | None = None) -> RunResult:
    """Align the sample's target point onto the rotation axis (see the module docstring)."""
    return _Run(rig, cfg, "align", progress, abort, recorder, tools, run_id,
                frames_per_step, systematic_um).execute()


def run_check(rig: Rig, cfg: AligndConfig, *, progress: ProgressCallback | None = None,
              abort: threading.Event | None = None, recorder: RunRecorder | None = None,
              tools: Tools | None = None, run_id: str | None = None,
              frames_per_step: int | None = None,
                  systematic_um: float | None = None) -> RunResult:
    """Measure the offset against the tolerance; no translation stage moves.

    Sweeps (pooling the centre) until the offset is shown within or beyond the tolerance
    with 95 % confidence, at most ``procedure.max_iterations`` sweeps.
    """
    return _Run(rig, cfg, "check", progress, abort, recorder, tools, run_id,
                frames_per_step, systematic_um).execute()


def within(m: Measurement) -> bool:
    """Within tolerance with confidence: P(|offset| <= tolerance) >= 95 %."""
    return m.p_within is not None and m.p_within >= CONFORMANCE


def beyond(m: Measurement) -> bool:
    """Out of tolerance with confidence: P(|offset| <= tolerance) <= 5 %."""
    return m.p_within is not None and m.p_within <= 1.0 - CONFORMANCE


class _Run:
    def __init__(self, rig: Rig, cfg: AligndConfig, mode: Literal["align", "check"],
                 progress: ProgressCallback | None, abort: threading.Event | None,
                 recorder: RunRecorder | None, tools: Tools | None,
                 run_id: str | None, frames_per_step: int | None = None,
                 systematic_um: float | None = None) -> None:
        self.rig = rig
        self.cfg = cfg
        self.mode = mode
        self.progress = progress or no_progress
        self.abort = abort
        self.recorder = recorder or NullRecorder()
        self.tools = tools
        self.run_id = run_id or getattr(recorder, "run_id", None) or uuid.uuid4().hex[:12]
        self.st = _State()
        self.p = cfg.procedure
        self.tol = self.p.tolerance_um
        # explicit arguments (benchmarks) override the config
        self.frames_per_step = frames_per_step or cfg.procedure.frames_per_step
        self.systematic_um = (cfg.procedure.systematic_um if systematic_um is None
                              else systematic_um)
        self.pool = CentrePool()

    # ---- top level -------------------------------------------------------------------
    def execute(self) -> RunResult:
        t_start = time.time()
        verdict, reason, config_error = "fault", "", False
        final: Measurement | None = None
        try:
            with self.rig.abort_guard(self.abort):
                self._prepare()
                self._prechecks()
                verdict, reason, final = self._align() if self.mode == "align" else \
                    self._check()
                self._park()
        except _Stop as stop:
            verdict, reason, final = stop.verdict, stop.reason, stop.measurement
            self._emit("done", reason)
            try:
                with self.rig.abort_guard(self.abort):
                    self._park()
            except AligndError as exc:  # parking is a courtesy; say why it failed
                self._warn(f"could not park the turntable: {exc}")
        except AbortRequested as exc:
            errs = self.rig.stop_all()
            verdict, reason = "aborted", f"aborted: {exc}" + (
                f" (stop failed: {'; '.join(errs)})" if errs else "")
        except (ConfigError, StateError) as exc:
            self.rig.stop_all()
            verdict, reason, config_error = "fault", f"refused: {exc}", True
        except DeviceError as exc:
            errs = self.rig.stop_all()
            verdict, reason = "fault", f"device error: {exc}" + (
                f" (stop failed: {'; '.join(errs)})" if errs else "")
        except AligndError as exc:  # vision, solve, calibration: measurement failed
            self.rig.stop_all()
            verdict, reason = "fault", f"measurement failed: {exc}"
        except Exception as exc:  # a run must always end in a verdict
            log.exception("internal error during %s run %s", self.mode, self.run_id)
            self.rig.stop_all()
            verdict, reason = "fault", f"internal error: {type(exc).__name__}: {exc}"
        if final is None and verdict in ("not_converged", "out_of_tolerance"):
            final = self.st.last
        result = RunResult(
            run_id=self.run_id, mode=self.mode, verdict=verdict,  # type: ignore[arg-type]
            reason=reason,
            offset_um=None if final is None else (float(final.offset_um[0]),
                                                  float(final.offset_um[1])),
            U_um=None if final is None else final.U_um,
            iterations=self.st.iterations, tilt_deg=self.st.tilt_deg,
            yaw_deg=None if final is None else final.yaw_deg, config_error=config_error)
        if self.rig.truth is not None:
            try:
                result.truth = dict(self.rig.truth())
            except Exception:  # truth is a report extra, never essential
                log.exception("reading the simulator truth failed")
        result.details = {
            "mode": self.mode, "started": t_start, "finished": time.time(),
            "tolerance_um": self.tol,
            "devices": {r: vars(i) for r, i in self.rig.identities.items()},
            "calibration": None if self.st.calibration is None
            else self.st.calibration.to_dict(),
            "history": self.st.history, "warnings": self.st.warnings,
            "final": None if final is None else final.to_dict(),
            "compute_s": self.st.compute_s, "motion_s": self.st.motion_s,
            "tools": (self.tools.names if self.tools else None),
        }
        level = logging.INFO if result.ok else logging.WARNING
        log.log(level, "%s run %s: %s %s", self.mode, self.run_id, verdict, reason)
        self.recorder.event(f"{self.mode} finished: {verdict}: {reason}")
        self._emit("done", f"{verdict}: {reason}", m=final)
        return result

    # ---- helpers ---------------------------------------------------------------------
    def _emit(self, phase: str, message: str, *, m: Measurement | None = None,
              iteration: int | None = None) -> None:
        ev = ProgressEvent(phase, message, iteration=iteration,
                           offset_um=None if m is None else (float(m.offset_um[0]),
                                                             float(m.offset_um[1])),
                           offset_norm_um=None if m is None else m.norm_um,
                           U_um=None if m is None else m.U_um)
        try:
            self.progress(ev)
        except Exception:  # an observer must not break the run
            log.exception("progress callback failed")

    def _progress_safe(self, ev: ProgressEvent) -> None:
        try:
            self.progress(ev)
        except Exception:  # an observer must not break the run
            log.exception("progress callback failed")

    def _warn(self, msg: str) -> None:
        log.warning("%s", msg)
        self.st.warnings.append(msg)
        self.recorder.event(f"warning: {msg}")

    def _measure(self, kind: str, iteration: int) -> Measurement:
        assert self.tools is not None
        px = (self.st.calibration.pixel_size_um if self.st.calibration is not None
              else configured_pixel_size_um(self.cfg))
        _data, m, warning = measure(
            self.rig, self.cfg, self.tools, kind=kind, iteration=iteration, abort=self.abort,
            progress=self._progress_safe, recorder=self.recorder, pixel_size_um=px,
            pool=self.pool, frames_per_step=self.frames_per_step,
            floor_um=self.systematic_um)
        if warning:
            self._warn(warning)
        self.st.compute_s += m.compute_s
        self.st.motion_s += m.timings.get("motion_s", 0.0)
        self.st.last = m
        self._emit("solve", f"{kind} {iteration}: offset {m.norm_um:.1f} ± {m.U_um:.1f} um "
                   f"(centre sigma {m.sigma_centre_um:.1f} um over {m.n_sweeps} sweep(s), "
                   f"P(within) {m.p_within:.2f})", m=m, iteration=iteration)
        return m

    def _record(self, n: int, kind: str, m: Measurement, **extra: Any) -> dict[str, Any]:
        rec = {"iteration": n, "kind": kind, **m.to_dict(), "timings": m.timings, **extra}
        self.st.history.append(rec)
        self.recorder.iteration(n, rec)
        return rec

    # ---- phases ----------------------------------------------------------------------
    def _prepare(self) -> None:
        corr = tuple(self.p.correction_axes)
        validate_rig(self.rig, corr)
        self._emit("connect", "connecting and identifying devices")
        self.rig.connect()
        for role, ident in self.rig.identities.items():
            self.recorder.event(f"{role}: {ident.vendor} {ident.model} s/n {ident.serial} "
                                f"fw {ident.firmware}")
        if self.tools is None:
            self.tools = default_tools(self.cfg)
        # before anything moves: a sweep the soft limits forbid is a config error
        tt = self.rig.axis("turntable").config.soft_limits
        if not (tt.min <= -self.p.sweep_deg and self.p.sweep_deg <= tt.max):
            raise ConfigError(f"procedure.sweep_deg {self.p.sweep_deg:g} exceeds the "
                              f"turntable soft limits [{tt.min:g}, {tt.max:g}]")
        # check moves no translation stage: home only the turntable there
        roles = list(self.rig.axes) if self.mode == "align" else ["turntable"]
        self._emit("home", "homing where required")
        homed = self.rig.home_where_required(roles, abort=self.abort)
        if homed:
            self.recorder.event(f"homed: {', '.join(homed)}")

    def _prechecks(self) -> None:
        pc = self.p.precheck
        assert self.tools is not None
        problems: list[tuple[str, str]] = []  # (verdict if refused, message)
        top = self.rig.camera("top")
        assert top is not None
        self._emit("precheck", "looking for the holder")
        for attempt in range(HOLDER_LOOK_FRAMES):
            check_abort(self.abort)
            det = self.tools.track(grab_fresh(top, time.monotonic()))
            if det.ok:
                break
            log.info("holder not found in top frame %d: %s", attempt + 1, det.reason)
        else:
            raise VisionError(f"holder not found in {HOLDER_LOOK_FRAMES} top-camera frames "
                              f"({det.reason or 'no detection'}); nothing moved")
        if self.tools.eccentricity is not None:
            check_abort(self.abort)
            self._emit("precheck", "top-camera eccentricity")
            try:
                e = self.tools.eccentricity(top.grab(after=time.monotonic()))
                self.recorder.event(f"pre-check: top-camera rim eccentricity {e:.4f}")
                if e > pc.max_eccentricity:
                    problems.append(("fault", f"top-camera eccentricity {e:.3f} exceeds "
                                     f"{pc.max_eccentricity:g} (camera not on the axis)"))
            except AligndError as exc:
                problems.append(("fault", f"top-camera eccentricity not measurable: {exc}"))
        side = self.rig.camera("side")
        if self.tools.tilt is not None and side is not None:
            check_abort(self.abort)
            self._emit("precheck", "side-camera tilt")
            try:
                self.st.tilt_deg = float(self.tools.tilt(side.grab(after=time.monotonic())))
                self.recorder.event(f"pre-check: sample tilt {self.st.tilt_deg:+.4f} deg")
                if abs(self.st.tilt_deg) > pc.max_tilt_deg:
                    problems.append(("out_of_tolerance",
                                     f"sample tilt {self.st.tilt_deg:+.3f} deg exceeds "
                                     f"{pc.max_tilt_deg:g} deg"))
            except AligndError as exc:
                problems.append(("fault", f"side-camera tilt not measurable: {exc}"))
        for verdict, msg in problems:
            if pc.action == "refuse":
                raise _Stop(verdict, f"pre-check refused: {msg}")
            self._warn(f"pre-check: {msg}")

    def _check(self) -> tuple[str, str, Measurement]:
        n = 0
        while True:
            n += 1
            self.st.iterations = n
            m = self._measure("check", n)
            self._record(n, "check", m)
            if m.sigma_centre_um > self.p.max_center_sigma_um:
                return ("out_of_tolerance", f"centre uncertainty {m.sigma_centre_um:.1f} um "
                        f"exceeds max_center_sigma_um {self.p.max_center_sigma_um:g}: cannot "
                        "show the offset is within tolerance", m)
            if within(m):
                return ("within_tolerance", f"offset {m.norm_um:.1f} ± {m.U_um:.1f} um (k=2) "
                        f"within {self.tol:g} um", m)
            if beyond(m) or n >= self.p.max_iterations:
                return ("out_of_tolerance", f"offset {m.norm_um:.1f} ± {m.U_um:.1f} um (k=2) "
                        f"not shown within {self.tol:g} um (P(within) {m.p_within:.2f})", m)

    def _calibrate(self, refreshes: int = 0) -> Calibration:
        assert self.tools is not None
        self._emit("calibrate", "calibrating the stage-to-image mapping"
                   + (" (refresh)" if refreshes else ""))
        cal = calibrate(self.rig, self.cfg, self.tools, abort=self.abort,
                        progress=self._progress_safe, recorder=self.recorder,
                        refreshes=refreshes)
        self.st.calibration = cal
        return cal

    def _align(self) -> tuple[str, str, Measurement]:
        cal = self._calibrate()
        it = 1
        self.st.iterations = 1
        m = self._measure("align", it)
        prev: Measurement | None = None
        ds_prev: np.ndarray | None = None
        extra: dict[str, Any] = {}
        while True:
            if prev is not None and ds_prev is not None:
                cal, extra = self._consistency(cal, prev, m, ds_prev)
            if m.sigma_centre_um > self.p.max_center_sigma_um:
                self._record(it, "align", m, **extra, action="refused")
                raise _Stop("not_converged", f"centre uncertainty {m.sigma_centre_um:.1f} um "
                            f"exceeds max_center_sigma_um {self.p.max_center_sigma_um:g}; "
                            "no move made", m)
            if within(m) and m.norm_um <= max(RESIDUAL_FRACTION * self.tol,
                                              2.0 * m.sigma_random_um):
                self._record(it, "align", m, **extra, action="verify")
                self._emit("verify", "within tolerance; verification sweep", m=m,
                           iteration=it)
                mv = self._measure("verify", it)
                if within(mv):
                    self._record(it, "verify", mv, action="done")
                    return ("aligned", f"offset {mv.norm_um:.1f} ± {mv.U_um:.1f} um (k=2) "
                            f"within {self.tol:g} um after {it} iteration(s)", mv)
                self._warn(f"verification sweep shows {mv.norm_um:.1f} ± {mv.U_um:.1f} um, "
                           "not within tolerance")
                if it >= self.p.max_iterations:
                    self._record(it, "verify", mv, action="stop")
                    raise _Stop("out_of_tolerance", f"verification: offset {mv.norm_um:.1f} ± "
                                f"{mv.U_um:.1f} um not within {self.tol:g} um and the "
                                f"iteration cap ({self.p.max_iterations}) is reached", mv)
                it += 1
                self.st.iterations = it
                prev, ds_prev, m, extra = None, None, mv, {}
                continue
            reason = self._divergence(prev, m, ds_prev)
            if reason:
                if cal.refreshes < MAX_CAL_REFRESHES:
                    self._warn(f"{reason}; refreshing the calibration")
                    cal = self._calibrate(cal.refreshes + 1)
                else:
                    self._record(it, "align", m, **extra, action="stop")
                    raise _Stop("not_converged", f"{reason} (offset {m.norm_um:.1f} um)", m)
            if it >= self.p.max_iterations:
                self._record(it, "align", m, **extra, action="stop")
                raise _Stop("not_converged", f"offset {m.norm_um:.1f} ± {m.U_um:.1f} um not "
                            f"within {self.tol:g} um after {it} iterations (cap)", m)
            ds_actual, move_rec = self._correct(cal, m, it)
            self._record(it, "align", m, **extra, action="move", **move_rec)
            prev, ds_prev = m, ds_actual
            it += 1
            self.st.iterations = it
            m = self._measure("align", it)
            extra = {}

    def _consistency(self, cal: Calibration, prev: Measurement, m: Measurement,
                     ds: np.ndarray) -> tuple[Calibration, dict[str, Any]]:
        """Compare the offset change a move caused with the calibration's prediction."""
        obs = m.offset_px - prev.offset_px
        pred = cal.predict(ds)
        noise = math.sqrt(float(np.trace(prev.cov_offset_px2 + m.cov_offset_px2)))
        err = float(np.hypot(*(obs - pred)))
        size = float(np.hypot(*pred))
        rec = {"calibration_check": {"predicted_px": pred.tolist(), "observed_px": obs.tolist(),
                                     "error_px": err, "noise_px": noise}}
        if size > 5 * noise and err > CAL_DISAGREE_REL * size + 3 * noise \
                and cal.refreshes < MAX_CAL_REFRESHES:
            self._warn(f"the last move disagrees with the calibration ({err:.2f} px off a "
                       f"predicted {size:.2f} px); refreshing the calibration")
            rec["calibration_check"]["action"] = "refresh"
            return self._calibrate(cal.refreshes + 1), rec
        if size > BROYDEN_MIN_SNR * noise:
            cal.update(ds, obs)
            rec["calibration_check"]["action"] = "update"
        return cal, rec

    def _divergence(self, prev: Measurement | None, m: Measurement,
                    ds_prev: np.ndarray | None) -> str:
        if prev is None or ds_prev is None or m.norm_um <= self.tol:
            return ""
        if m.norm_um > DIVERGE_RATIO * prev.norm_um + m.U_um:
            return (f"diverging: offset grew from {prev.norm_um:.1f} to {m.norm_um:.1f} um "
                    "after a correction")
        cos = float(m.offset_um @ prev.offset_um) / (m.norm_um * prev.norm_um + 1e-12)
        if cos < -0.5 and m.norm_um > 0.7 * prev.norm_um and m.norm_um > m.U_um:
            return (f"oscillating: offset flipped from {prev.norm_um:.1f} to "
                    f"{m.norm_um:.1f} um")
        return ""

    def _correct(self, cal: Calibration, m: Measurement,
                 it: int) -> tuple[np.ndarray, dict[str, Any]]:
        """Move the correction axes by the calibrated step, clamped; return the actual move."""
        ds = cal.step_for(m.offset_px)
        rec: dict[str, Any] = {"step_mm": dict(zip(cal.roles, ds.tolist(), strict=True))}
        biggest = float(np.max(np.abs(ds)))
        if biggest > self.p.max_step_mm:
            ds = ds * (self.p.max_step_mm / biggest)
            self._warn(f"iteration {it}: correction step {biggest:.3f} mm clamped to "
                       f"max_step_mm {self.p.max_step_mm:g}")
            rec["clamped"] = True
        axes = [self.rig.axis(r) for r in cal.roles]
        before = np.array([ax.position() for ax in axes])
        targets = before + ds
        limited = []
        for k, ax in enumerate(axes):
            lim = ax.config.soft_limits
            t = min(max(float(targets[k]), lim.min), lim.max)
            if t != targets[k]:
                limited.append(cal.roles[k])
                targets[k] = t
        if limited:
            self._warn(f"iteration {it}: correction limited by the soft limits of "
                       f"{', '.join(limited)}")
            rec["limited"] = limited
            if np.allclose(targets, before, atol=1e-6):
                raise _Stop("not_converged", "the correction needs travel beyond the soft "
                            f"limits of {', '.join(limited)}", m)
        rec["before_mm"] = dict(zip(cal.roles, before.tolist(), strict=True))
        rec["targets_mm"] = dict(zip(cal.roles, targets.tolist(), strict=True))
        after = []
        t0 = time.perf_counter()
        for k, ax in enumerate(axes):
            check_abort(self.abort)
            self._emit("move", f"moving {cal.roles[k]} by {targets[k] - before[k]:+.4f} mm",
                       iteration=it)
            after.append(ax.move_to(float(targets[k])))
        self.st.motion_s += time.perf_counter() - t0
        actual = np.asarray(after) - before
        rec["readback_mm"] = dict(zip(cal.roles, after, strict=True))
        return actual, rec

    def _park(self) -> None:
        """Leave the turntable at zero, where the operator expects the sample."""
        tt = self.rig.axis("turntable")
        if tt.position_known or tt.status().homed:
            tt.move_to(0.0)
