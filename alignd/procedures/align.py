"""The closed loop: measure the target's offset from the rotation axis, move, repeat, verify.

``run_alignment``: connect, identify and home; pre-checks (top-camera eccentricity,
side-camera tilt); calibrate the stage-to-image mapping; then iterate: sweep (corrected for
the turntable's error motion when a runout map is given) -> centre pooled over the run's
sweeps -> target offset from the mean axis with its uncertainty budget -> the decision rule
(``procedure.decision_rule``) -> either a verdict, a better measurement (wider sweep, more
frames per step) when the measurement cannot decide and a move cannot help, or a stage move
in the rotating frame (clamped to the maximum step and the soft limits). No move is made
when it would gain less than the stages' repeatability. The sweep after the last move is
the verdict's measurement. ``run_check`` measures without moving any translation stage and
answers from the first sweep that decides.

``iterations`` in the result counts correction moves (0 for a check); ``sweeps`` counts
measurements.

Nothing moves on data that failed a check (tracking lost, centre too uncertain); an abort
or a device error stops every axis. The simulator's truth is read only after the run.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.stats import chi2 as chi2_dist

from alignd.config import RIM_FRAME_PREFIX, SIDE_FRAME_PREFIX, AligndConfig
from alignd.errors import (
    AligndError,
    ConfigError,
    DeviceError,
    HolderFrameError,
    StateError,
    VisionError,
)
from alignd.procedures.angles import AngleMap
from alignd.procedures.budget import Contribution
from alignd.procedures.calibrate import Calibration, calibrate, configured_pixel_size_um
from alignd.procedures.commission import CommissionRecord
from alignd.procedures.decision import Decision, decide
from alignd.procedures.events import Phase, ProgressCallback, ProgressEvent, no_progress
from alignd.procedures.recorder import NullRecorder, RunRecorder
from alignd.procedures.result import RunResult, Verdict
from alignd.procedures.rig import AbortRequested, Rig, check_abort, validate_rig
from alignd.procedures.runout import WELL_SEPARATED_DEG, RunoutMap
from alignd.procedures.sweep import (
    CentrePool,
    Measurement,
    SweepPlan,
    grab_frames,
    grab_fresh,
    grab_rim_frames,
    measure,
    rim_turn_angles,
    sweep_runout,
)
from alignd.procedures.tools import (
    RimReading,
    TiltReading,
    Tools,
    default_tools,
    expected_holder_px,
)
from alignd.textfmt import identity_text
from drivers.camera import Camera, Frame

log = logging.getLogger(__name__)

MAX_CAL_REFRESHES = 2
CAL_DISAGREE_REL = 0.15  # observed vs predicted change of offset, beyond noise
BROYDEN_MIN_SNR = 30.0  # update J only from moves this far above the noise
DIVERGE_RATIO = 1.5
HOLDER_LOOK_FRAMES = 3
# the turntable's error motion, when no runout map is given, stands in as
# ``procedure.systematic_um`` (1 sigma per axis): over a +-10 deg sweep a radial error motion
# that changes with the angle is indistinguishable from a shifted centre (a 2 um
# third-harmonic wobble shifts it by up to 6 um), and every sweep sees the same one. With a
# map (``alignctl commission``) each sweep is corrected and the floor is measured.
SOFT_LIMIT_MARGIN_DEG = 0.1
MAX_CENTRE_JUMPS = 2  # a centre that jumps once may be a bump; twice, something is loose
WIDENED_WARN = 2.0  # a centre fit widened past this for correlated corner errors is named
# the sweeps disagree with the runout map: a wide sweep's centre against the narrower
# sweeps' beyond this chi-square quantile in MAP_DISAGREE_SWEEPS consecutive sweeps (or one
# centre jump with a map)
MAP_DISAGREE_P = 0.99
MAP_DISAGREE_SWEEPS = 2
MAP_DISAGREE_P_ONCE = 0.999  # ... or beyond this quantile once
# a refresh maps the error motion in the run: over at least this span (the harmonics
# separate from the axis and the arm, runout.WELL_SEPARATED_DEG), in these steps
REFRESH_STEP_DEG = 10.0
REFRESH_MAX_HALF_DEG = 165.0


class _Stop(AligndError):
    """Ends the loop with a verdict that is not an error (refusal, not converged)."""

    def __init__(self, verdict: Verdict, reason: str,
                 measurement: Measurement | None = None) -> None:
        super().__init__(reason)
        self.verdict = verdict
        self.reason = reason
        self.measurement = measurement


@dataclass
class _State:
    iterations: int = 0  # correction moves made
    sweeps: int = 0
    last: Measurement | None = None
    decision: Decision | None = None
    tilt_deg: float | None = None
    tilt_u_deg: float | None = None  # its standard uncertainty (k = 1)
    eccentricity: float | None = None  # the top camera's rim pre-check
    eccentricity_u: float | None = None  # its standard uncertainty (k = 1)
    warnings: list[str] = field(default_factory=list)
    history: list[dict[str, Any]] = field(default_factory=list)
    calibration: Calibration | None = None
    compute_s: float = 0.0
    motion_s: float = 0.0
    centre_jumps: int = 0  # sweeps whose centre disagreed with the pool (axis cannot move)
    map_disagree: int = 0  # consecutive sweeps whose centres disagreed with the runout map
    runout_refresh: dict[str, Any] | None = None  # what a refresh (or its refusal) found
    sweep_warned: bool = False  # a sweep's frames carried the tracker's warning (said once)
    widened_warned: bool = False  # a sweep's centre fit was widened past WIDENED_WARN (once)


def run_alignment(rig: Rig, cfg: AligndConfig, *, progress: ProgressCallback | None = None,
                  abort: threading.Event | None = None, recorder: RunRecorder | None = None,
                  tools: Tools | None = None, run_id: str | None = None,
                  frames_per_step: int | None = None, systematic_um: float | None = None,
                  runout: RunoutMap | None = None,
                  commission: CommissionRecord | None = None) -> RunResult:
    """Align the sample's target point onto the mean rotation axis (see the module
    docstring). ``commission``: a valid commission record (the daemon passes the latest
    one): its measured turntable direction and angle scale replace the config's, its runout
    map is subtracted from every sweep. ``runout``: a map given directly (it wins over the
    record's)."""
    return _Run(rig, cfg, "align", progress, abort, recorder, tools, run_id,
                frames_per_step, systematic_um, runout, commission).execute()


def run_check(rig: Rig, cfg: AligndConfig, *, progress: ProgressCallback | None = None,
              abort: threading.Event | None = None, recorder: RunRecorder | None = None,
              tools: Tools | None = None, run_id: str | None = None,
              frames_per_step: int | None = None, systematic_um: float | None = None,
              runout: RunoutMap | None = None,
              commission: CommissionRecord | None = None) -> RunResult:
    """Measure the offset against the tolerance; no translation stage moves.

    Answers from the first sweep the decision rule can decide on; when it cannot, measures
    better (pooling the centre) up to ``procedure.max_sweeps`` sweeps. ``runout`` and
    ``commission`` as for ``run_alignment``.
    """
    return _Run(rig, cfg, "check", progress, abort, recorder, tools, run_id,
                frames_per_step, systematic_um, runout, commission).execute()


class _Run:
    def __init__(self, rig: Rig, cfg: AligndConfig, mode: Literal["align", "check"],
                 progress: ProgressCallback | None, abort: threading.Event | None,
                 recorder: RunRecorder | None, tools: Tools | None,
                 run_id: str | None, frames_per_step: int | None = None,
                 systematic_um: float | None = None, runout: RunoutMap | None = None,
                 commission: CommissionRecord | None = None) -> None:
        self.rig = rig
        self.cfg = cfg
        self.mode = mode
        self.progress = progress or no_progress
        self.abort = abort
        self.recorder = recorder or NullRecorder()
        self.tools = tools
        self.run_id = run_id or uuid.uuid4().hex[:12]
        self.st = _State()
        self.p = cfg.procedure
        self.tol = self.p.tolerance_um
        # explicit arguments (benchmarks) override the config
        self.frames_per_step = frames_per_step or cfg.procedure.frames_per_step
        self.systematic_um = (cfg.procedure.systematic_um if systematic_um is None
                              else systematic_um)
        self.pool = CentrePool()
        # the pool holds sweeps of one width: the runout map's residual biases the centres
        # of different widths differently (more the narrower), so a wider sweep starts a
        # new pool, and the narrower sweeps' centre is kept to test the map against
        self.pool_half: float | None = None
        self.narrow: tuple[np.ndarray, np.ndarray] | None = None  # centre, cov (image px)
        self.commission = commission
        if commission is not None:
            self.angle_map = commission.angle_map(f"commission run {commission.run_id}")
            if commission.runout is not None and systematic_um is None:
                # the bearing's error motion is subtracted: what stays systematic is the
                # map's own error, below its per-frame residual (1 sigma), and never taken
                # below 1 um (perspective, the encoder's periodic error)
                self.systematic_um = min(self.systematic_um,
                                         max(1.0, commission.runout.residual_um))
        else:
            self.angle_map = AngleMap(cfg.procedure.turntable_direction, 1.0, "config")
        self.runout = runout if runout is not None or commission is None else commission.runout
        self.plan = SweepPlan(self.p.sweep_deg, self.p.sweep_steps, self.frames_per_step)

    # ---- top level -------------------------------------------------------------------
    def execute(self) -> RunResult:
        t_start = time.time()
        verdict: Verdict = "fault"
        reason, config_error = "", False
        final: Measurement | None = None
        holder_frame: dict[str, object] | None = None  # a refused holder frame's evidence
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
            verdict, reason = "aborted", f"{exc}" + (
                f" (stop failed: {'; '.join(errs)})" if errs else "")
        except (ConfigError, StateError) as exc:
            self.rig.stop_all()
            verdict, reason, config_error = "fault", f"refused: {exc}", True
            if isinstance(exc, HolderFrameError):
                holder_frame = exc.evidence
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
            run_id=self.run_id, mode=self.mode, verdict=verdict, reason=reason,
            offset_um=None if final is None else (float(final.offset_um[0]),
                                                  float(final.offset_um[1])),
            U_um=None if final is None else final.U_um,
            iterations=self.st.iterations, sweeps=self.st.sweeps, tilt_deg=self.st.tilt_deg,
            tilt_u_deg=self.st.tilt_u_deg, eccentricity=self.st.eccentricity,
            eccentricity_u=self.st.eccentricity_u,
            yaw_deg=None if final is None else final.yaw_deg, config_error=config_error,
            budget=None if final is None else final.budget.to_dict(),
            decision=None if final is None else self._decision(final).to_dict())
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
            "holder_frame_refused": holder_frame,
            "final": None if final is None else final.to_dict(),
            "budget": None if final is None else final.budget.to_dict(),
            "decision": None if final is None else self._decision(final).to_dict(),
            "runout_map": None if self.runout is None else self.runout.to_json(),
            "runout_refresh": self.st.runout_refresh,
            "moves": self.st.iterations, "sweeps": self.st.sweeps,
            "compute_s": self.st.compute_s, "motion_s": self.st.motion_s,
            "tools": (self.tools.names if self.tools else None),
            "conventions": {"source": self.angle_map.source,
                            "turntable_direction": self.angle_map.sign,
                            "angle_scale": self.angle_map.scale,
                            "runout": self.commission is not None
                            and self.commission.runout is not None},
        }
        level = logging.INFO if result.ok else logging.WARNING
        log.log(level, "%s run %s: %s %s", self.mode, self.run_id, verdict, reason)
        self.recorder.event(f"{self.mode} finished: {verdict}: {reason}")
        self._emit("done", f"{verdict}: {reason}", m=final)
        return result

    # ---- helpers ---------------------------------------------------------------------
    def _emit(self, phase: Phase, message: str, *, m: Measurement | None = None,
              iteration: int | None = None, step: int | None = None,
              total: int | None = None) -> None:
        ev = ProgressEvent(phase, message, step=step, total=total, iteration=iteration,
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

    def _measure(self, kind: str) -> Measurement:
        """One sweep with the current plan; the centre pooled over the run's sweeps."""
        assert self.tools is not None
        self.st.sweeps += 1
        n = self.st.sweeps
        px = (self.st.calibration.pixel_size_um if self.st.calibration is not None
              else configured_pixel_size_um(self.cfg))
        if (self.pool_half is not None and self.plan.half_deg != self.pool_half
                and self.pool.items and self.st.last is not None):
            p = self.pool.pooled()
            self.narrow = (p.center_px, p.cov_px2 + self._floor_px2(self.st.last))
            self.pool = CentrePool()
        self.pool_half = self.plan.half_deg
        data, m, warning = measure(
            self.rig, self.cfg, self.tools, kind=kind, iteration=n, abort=self.abort,
            progress=self._progress_safe, recorder=self.recorder, pixel_size_um=px,
            pool=self.pool, floor_um=self.systematic_um, angle_map=self.angle_map,
            runout=self.runout, plan=self.plan, approach=self._approach())
        if data.warned_frames and not self.st.sweep_warned:
            # once a run: a holder clipped at some angles (a glint) says so in every sweep
            self.st.sweep_warned = True
            self._warn(f"{kind} sweep {n}: top camera, {data.warned_frames} of "
                       f"{len(data.frame_hashes)} frame(s): {data.warning}")
        if m.centre_widened > WIDENED_WARN and not self.st.widened_warned:
            self.st.widened_warned = True
            self._warn(f"{kind} sweep {n}: the holder's corners disagree with one rigid turn "
                       f"far beyond their noise (the centre fit's uncertainty widened "
                       f"x{m.centre_widened:.1f}): a lens not modelled (cameras[].lens), "
                       "clutter or a shadow at the holder's corners, or a holder that is "
                       "not rigid; the run's picture shows the corners' paths")
        if warning:
            self._warn(warning)
            if "moved between sweeps" in warning:
                self.st.centre_jumps += 1
        if self.runout is not None and self._map_disagrees(warning, m) \
                and self._refresh_runout():
            self.st.compute_s += m.compute_s
            return self._measure(kind)  # the centre again, with the refreshed map
        self.st.compute_s += m.compute_s
        self.st.motion_s += m.timings.get("motion_s", 0.0)
        self.st.last = m
        d = self._decision(m)
        self._emit("solve", f"{kind} sweep {n}: {d.text()} (centre over {m.n_sweeps} "
                   f"sweep(s))", m=m, iteration=n)
        return m

    def _predicted(self, cal: Calibration, m: Measurement,
                   ds: np.ndarray) -> Measurement | None:
        """The offset after a small move, predicted from the measurement before it, when
        that decides (else None: a sweep must measure it).

        Small: the calibration's scale error on the move is below half the stages'
        repeatability, so the stages' landing scatter is what the move adds to the
        measurement's uncertainty: the measured position holds the old landing error and
        the move replaces it by a new one, ``stage_repeatability_um`` times sqrt(2) per
        axis (the budget's "stage repeatability"). Decides: within under the decision
        rule, U at most ``target_u_fraction`` of the tolerance, and no further move would
        gain more than the repeatability."""
        rep = self.p.stage_repeatability_um
        if not self.p.predict_after_small_move or self.p.decision_rule != "guarded":
            return None
        moved_px = cal.predict(ds)
        moved_um = float(np.hypot(*moved_px)) / m.scale_px_per_mm * 1000.0
        u_scale = cal.sigma_rel * moved_um
        if u_scale > 0.5 * rep:
            return None
        off_px = m.offset_px + moved_px
        # the measured position holds the old landing error, the new one replaces it:
        # the change is off by both, rep sqrt(2) per axis
        add = (2.0 * rep**2 + u_scale**2 / 2.0) * np.eye(2)
        landing = Contribution("stage repeatability", math.sqrt(float(np.trace(add))), "B",
                               f"landing scatter of the last move ({rep:g} um x sqrt 2 per axis; "
                               f"the verdict is predicted after a {moved_um:.1f} um move)")
        items = (*(c for c in m.budget.items if c.name != "stage repeatability"), landing)
        pred = dataclasses.replace(
            m, offset_px=off_px, offset_um=off_px / m.scale_px_per_mm * 1000.0,
            cov_offset_um2=m.cov_offset_um2 + add,
            budget=dataclasses.replace(m.budget, items=items), predicted=True,
            moved_um=moved_um)
        pred.p_within = None
        d = self._decision(pred)
        if (not d.conforms or pred.U_um > self.p.target_u_fraction * self.tol
                or self._gain(pred) > rep):
            return None
        return pred

    @staticmethod
    def _floor_px2(m: Measurement) -> np.ndarray:
        """The runout map's residual on a centre (the budget's residual error motion), as
        a covariance in image px."""
        s = m.budget.get("residual error motion") / 1000.0 * m.scale_px_per_mm
        return (s * s / 2.0) * np.eye(2)

    def _map_disagrees(self, warning: str, m: Measurement) -> bool:
        """Whether the sweeps disagree with the runout map: a wide sweep's centre against
        the narrower sweeps' (a map that no longer fits the bearing biases them
        differently), beyond the ``MAP_DISAGREE_P`` quantile of chi-square with the fits'
        and the map's own uncertainties in ``MAP_DISAGREE_SWEEPS`` consecutive sweeps, or
        beyond ``MAP_DISAGREE_P_ONCE`` once; or a centre that jumped (the axis cannot
        move)."""
        beyond = far = False
        if self.narrow is not None and self.pool.items:
            c, cov, _ = self.pool.items[-1]
            d = c - self.narrow[0]
            S = self.narrow[1] + cov + self._floor_px2(m)
            chi2 = float(d @ np.linalg.solve(S, d))
            beyond = chi2 > float(chi2_dist.ppf(MAP_DISAGREE_P, 2))
            far = chi2 > float(chi2_dist.ppf(MAP_DISAGREE_P_ONCE, 2))
        jumped = "moved between sweeps" in warning
        self.st.map_disagree = self.st.map_disagree + 1 if beyond or jumped else 0
        return self.st.runout_refresh is None and (
            jumped or far or self.st.map_disagree >= MAP_DISAGREE_SWEEPS)

    def _refresh_runout(self) -> bool:
        """Map the error motion again in this run (once) with a sweep over most of a turn,
        or, where the soft limits or the conventions forbid it, drop the map (the assumed
        floor stands in) and say that the rig needs commissioning again. Either way the
        pool starts over (its centres were corrected with the old map) and the caller
        measures again."""
        assert self.tools is not None and self.runout is not None
        why = (f"the sweeps disagree with the runout map (wide and narrow sweeps' centres "
               f"apart beyond the {100 * MAP_DISAGREE_P:g} % point of chi-square in "
               f"{self.st.map_disagree} consecutive sweep(s), beyond the "
               f"{100 * MAP_DISAGREE_P_ONCE:g} % point once, or a centre jump): the "
               "turntable's error motion has changed since commissioning")
        tt = self.rig.axis("turntable").config
        lim = tt.soft_limits
        half = min(REFRESH_MAX_HALF_DEG, -lim.min - tt.backlash_approach - SOFT_LIMIT_MARGIN_DEG,
                   lim.max - tt.backlash_approach - SOFT_LIMIT_MARGIN_DEG)
        plain = self.angle_map.sign == 1 and abs(self.angle_map.scale - 1.0) < 1e-3
        if 2 * half < WELL_SEPARATED_DEG or not plain:
            cause = (f"the turntable's soft limits allow +-{half:.0f} deg, too little to map it "
                     f"here (at least {WELL_SEPARATED_DEG:g} deg)" if plain else
                     "this rig's turntable conventions are the commission record's")
            self.st.runout_refresh = {"refreshed": False, "reason": why, "note": cause}
            self._warn(f"{why}; {cause}: the map is no longer used in this run (the error "
                       f"motion is the assumed procedure.systematic_um "
                       f"{self.systematic_um:g} um); re-run alignctl commission")
            self.runout = None  # a map known to be wrong would bias every verdict
            self.pool = CentrePool()
            self.narrow = None
            return True
        self._emit("sweep", f"{why}; refreshing the runout map over +-{half:.0f} deg")
        old = self.runout
        new = sweep_runout(self.rig, self.cfg, self.tools, half_deg=half,
                           step_deg=REFRESH_STEP_DEG, frames_per_step=2, abort=self.abort,
                           progress=self._progress_safe, recorder=self.recorder)
        self.runout = new
        self.pool = CentrePool()
        self.narrow = None  # corrected with the old map
        self.st.map_disagree = 0
        self.st.runout_refresh = {"refreshed": True, "reason": why, "half_deg": half,
                                  "old_amplitude_um": old.amplitude_um,
                                  "new_amplitude_um": new.amplitude_um,
                                  "new_residual_um": new.residual_um}
        self._warn(f"{why}: refreshed the runout map from a +-{half:.0f} deg sweep (peak "
                   f"{old.amplitude_um:.1f} -> {new.amplitude_um:.1f} um) and measured the "
                   "centre again; the refreshed map serves this run only: re-run alignctl "
                   "commission to keep it")
        return True

    def _decision(self, m: Measurement) -> Decision:
        return decide(m.norm_um, m.U_um, self.tol, self.p.decision_rule)

    def _gain(self, m: Measurement) -> float:
        """What a correction move is expected to gain (um): the measured distance minus the
        expected distance after the move (the measurement's uncertainty, the stages'
        landing scatter and the calibration's scale error on the move, in quadrature)."""
        rep = self.p.stage_repeatability_um
        rel = self.st.calibration.sigma_rel if self.st.calibration is not None else 0.0
        after = math.sqrt(float(np.trace(m.cov_offset_um2)) + 2.0 * rep**2
                          + (rel * m.norm_um) ** 2)
        return m.norm_um - after

    def _widest_deg(self) -> float:
        """The widest sweep half-width allowed: ``procedure.max_sweep_deg`` inside the
        turntable's soft limits (less the backlash pre-move and a margin)."""
        tt = self.rig.axis("turntable").config
        lim = tt.soft_limits
        both = self.p.alternate_sweeps  # a pre-move past either end
        room = min(-lim.min - (tt.backlash_approach if tt.approach == "+" or both else 0.0),
                   lim.max - (tt.backlash_approach if tt.approach == "-" or both else 0.0))
        return max(min(self.p.max_sweep_deg or self.p.sweep_deg, room - SOFT_LIMIT_MARGIN_DEG),
                   self.p.sweep_deg)

    def _verdict_plan(self) -> SweepPlan:
        """The plan of a sweep that is to decide (a check's, the sweep after a correction
        move under guarded acceptance): the widest allowed, because the map's floor falls
        with the swept angle and a sweep that can decide saves the sweeps of the ladder;
        ``verdict_frames_per_step`` frames a step (a frame costs a frame period, a step a
        move). Simple acceptance does not need a small U: the configured plan."""
        fps = max(self.plan.frames_per_step,
                  min(self.p.verdict_frames_per_step, self.p.max_frames_per_step))
        if self.p.decision_rule != "guarded" or (self.plan.half_deg >= self._widest_deg()
                                                 and self.plan.frames_per_step >= fps):
            return self.plan
        steps = (self.plan.steps if self.plan.half_deg >= self._widest_deg()
                 else self.p.verdict_sweep_steps or self.plan.steps)
        return SweepPlan(max(self._widest_deg(), self.plan.half_deg), steps, fps)

    def _approach(self) -> Literal["+", "-"] | None:
        """The sweep's direction: from the end nearer the turntable (None: the axis' own)."""
        if not self.p.alternate_sweeps:
            return None
        tt = self.rig.axis("turntable")
        return "-" if tt.position() > 0.0 else "+"

    def _better_plan(self) -> SweepPlan | None:
        """The next step up in measurement quality within the limits, or None at the top:
        a wider sweep first (the centre's uncertainty falls with the swept angle), then
        more frames per step (the tracking noise falls with their root)."""
        cur = self.plan
        widest = self._widest_deg()
        if cur.half_deg < widest - 1e-6:
            return SweepPlan(min(widest, 2.0 * cur.half_deg), cur.steps, cur.frames_per_step)
        if cur.frames_per_step < self.p.max_frames_per_step:
            return SweepPlan(cur.half_deg, cur.steps,
                             min(2 * cur.frames_per_step, self.p.max_frames_per_step))
        return None

    def _measure_better(self) -> str:
        """Step the plan up (it stays up for the rest of the run); describe what changed."""
        nxt = self._better_plan()
        if nxt is None:
            return "another sweep at the same plan (the widest and finest allowed)"
        old, self.plan = self.plan, nxt
        if nxt.half_deg != old.half_deg:
            return f"widening the sweep to +-{nxt.half_deg:g} deg"
        return f"averaging {nxt.frames_per_step} frames per step"

    @staticmethod
    def _motion_floor_um(m: Measurement) -> float:
        """The residual error motion that no further sweep averages out: the budget's
        contribution less the sweeps' excess scatter, which falls with their number."""
        u = m.budget.get("residual error motion")
        excess2 = 2.0 * m.excess_um ** 2 / max(m.n_sweeps, 1)  # its part of u^2
        return math.sqrt(max(u * u - excess2, 0.0))

    def _floor_above(self, m: Measurement, u_um: float) -> bool:
        """Whether no better measurement can bring U under ``u_um``: U cannot fall below k
        times the residual error motion, which more sweeps and frames do not average out.
        With a runout map that floor falls with the swept angle, so only a sweep as wide
        as allowed is at it; without one it is ``procedure.systematic_um`` at any width."""
        return (m.budget.k * self._motion_floor_um(m) >= u_um
                and (not m.runout_corrected
                     or self.plan.half_deg >= self._widest_deg() - 1e-6))

    def _floor_blocks(self, m: Measurement) -> str:
        """Why no better measurement can decide ('' when one can)."""
        need = abs(self.tol - m.norm_um)
        if self.p.decision_rule != "guarded" or not self._floor_above(m, need):
            return ""
        fix = ("re-run alignctl commission" if self.runout is not None
               else "commission the rig (alignctl commission) for a runout map")
        return (f"the residual error motion alone gives U >= "
                f"{m.budget.k * self._motion_floor_um(m):.1f} um, more "
                f"than the {need:.1f} um between the offset and the tolerance; {fix}")

    def _record(self, kind: str, m: Measurement, **extra: Any) -> dict[str, Any]:
        n = self.st.sweeps
        d = self._decision(m)
        rec = {"iteration": n, "kind": kind, **m.to_dict(), "decision": d.to_dict(),
               "moves": self.st.iterations, "gain_um": self._gain(m),
               "timings": m.timings, **extra}
        self.st.history.append(rec)
        self.recorder.iteration(n, rec)
        return rec

    def _tally(self) -> str:
        moves, sweeps = self.st.iterations, self.st.sweeps
        return (f"{moves} move{'s' if moves != 1 else ''}, "
                f"{sweeps} sweep{'s' if sweeps != 1 else ''}")

    # ---- phases ----------------------------------------------------------------------
    def _prepare(self) -> None:
        corr = tuple(self.p.correction_axes)
        validate_rig(self.rig, corr)
        self._emit("connect", "connecting and identifying devices")
        self.rig.connect()
        for role, ident in self.rig.identities.items():
            self.recorder.event(f"{role}: {identity_text(vars(ident))}")
        if self.tools is None:
            self.tools = default_tools(self.cfg)
        # before anything moves: a sweep the soft limits forbid is a config error
        tt = self.rig.axis("turntable").config.soft_limits
        if not (tt.min <= -self.p.sweep_deg and self.p.sweep_deg <= tt.max):
            raise ConfigError(f"procedure.sweep_deg {self.p.sweep_deg:g} exceeds the "
                              f"turntable soft limits [{tt.min:g}, {tt.max:g}]")
        rim_turn_angles(0.0, self.p.precheck.rim_frames, self.p.precheck.rim_turn_deg,
                        tt.min, tt.max)
        # check moves no translation stage: home only the turntable there
        roles = list(self.rig.axes) if self.mode == "align" else ["turntable"]
        self._emit("home", "homing where required")
        homed = self.rig.home_where_required(roles, abort=self.abort)
        if homed:
            self.recorder.event(f"homed: {', '.join(homed)}")

    def _prechecks(self) -> None:
        pc = self.p.precheck
        assert self.tools is not None
        problems: list[tuple[Verdict, str]] = []  # (verdict if refused, message)
        top = self.rig.camera("top")
        assert top is not None
        self._emit("precheck", "looking for the holder")
        for attempt in range(HOLDER_LOOK_FRAMES):
            check_abort(self.abort)
            seen = grab_fresh(top, top.clock.now())
            det = self.tools.track(seen)
            if det.ok:
                break
            log.info("holder not found in top frame %d: %s", attempt + 1, det.reason)
        else:
            # the frame looked at, kept: the run's picture shows it
            self.recorder.frame(seen.image, "precheck-holder")
            size = expected_holder_px(self.cfg)
            looked = (f", {size[0]:.0f} x {size[1]:.0f} px as holder.size_mm and the top "
                      "camera's pixel_size_um give it" if size is not None else "")
            raise VisionError(
                f"holder not found in {HOLDER_LOOK_FRAMES} top-camera frames; nothing moved. "
                "Check a frame of the top camera (alignctl analyze top FRAME): the holder "
                f"whole in view{looked}, its face 15 DN or more (20 is safer) darker or "
                "lighter than what surrounds it, no part of it at full scale "
                "(docs/configure.md, the holder frame). The tracker said: "
                f"{det.reason or 'no detection'}")
        if det.warning:
            self._warn(f"pre-check: top camera: {det.warning}")
        if self.tools.eccentricity is not None or self.tools.rim is not None:
            check_abort(self.abort)
            # (tools without a rim fit read one still frame)
            turn = pc.rim_turn_deg if pc.rim_frames > 1 and self.tools.rim is not None else 0.0
            self._emit("precheck", "top-camera eccentricity" + (
                f" ({pc.rim_frames} frames, the turntable turned {turn:g} deg between them)"
                if turn else ""))
            try:
                rim = self._rim(top, pc.rim_frames)
                e = self.st.eccentricity = rim.eccentricity
                self.st.eccentricity_u = rim.u
                u = "" if rim.u is None else f" +- {rim.u:.4f}"
                turned = f", turned {turn:g} deg apart" if turn else ""
                self.recorder.event(f"pre-check: top-camera rim eccentricity {e:.4f}{u} "
                                    f"(mean of {rim.frames} top frame(s){turned}, u k = 1)")
                if e > pc.max_eccentricity:
                    problems.append(("fault", f"top-camera eccentricity {e:.3f} exceeds "
                                     f"{pc.max_eccentricity:g} (camera not on the axis)"))
            except AbortRequested:
                raise
            except AligndError as exc:
                problems.append(("fault", f"top-camera eccentricity not measurable: {exc}"))
        side = self.rig.camera("side")
        if self.tools.tilt is not None and side is not None:
            check_abort(self.abort)
            self._emit("precheck", "side-camera tilt")
            try:
                reading = self._tilt(side, pc.tilt_frames)
                self.st.tilt_deg, self.st.tilt_u_deg = reading.tilt_deg, reading.u_deg
                u = "" if reading.u_deg is None else f" +- {reading.u_deg:.4f}"
                why = f"; {reading.stop}" if reading.stop else ""
                if reading.jpeg_quality is not None:
                    why += (f"; JPEG-coded frames, quality {reading.jpeg_quality}: the "
                            f"coding's bias {reading.jpeg_bias_deg or 0.0:+.4f} deg taken off")
                self.recorder.event(f"pre-check: sample tilt {self.st.tilt_deg:+.4f}{u} deg "
                                    f"(mean of {reading.frames} side frame(s), u k = 1{why})")
                if abs(self.st.tilt_deg) > pc.max_tilt_deg:
                    problems.append(("out_of_tolerance",
                                     f"sample tilt {self.st.tilt_deg:+.3f} deg exceeds "
                                     f"{pc.max_tilt_deg:g} deg"))
            except AbortRequested:
                raise
            except AligndError as exc:
                problems.append(("fault", f"side-camera tilt not measurable: {exc}"))
        for verdict, msg in problems:
            if pc.action == "refuse":
                raise _Stop(verdict, f"pre-check refused: {msg}")
            self._warn(f"pre-check: {msg}")

    def _rim(self, top: Camera, n: int) -> RimReading:
        """The rim's eccentricity on the mean of ``n`` top frames, each exposed after the
        one before (at small e one frame's noise dominates e's uncertainty), with the
        turntable turned ``precheck.rim_turn_deg`` between them if set. Tools without
        a rim fit give ``tools.eccentricity`` of one frame, without uncertainty."""
        assert self.tools is not None
        if self.tools.rim is None:
            assert self.tools.eccentricity is not None
            return RimReading(float(self.tools.eccentricity(grab_fresh(top, top.clock.now()))),
                              None, 1)
        frames = grab_rim_frames(self.rig, top, n, self.p.precheck.rim_turn_deg, self.abort)
        self._keep(RIM_FRAME_PREFIX, frames, 0)
        info = self.tools.rim(frames, None, None)  # the ellipse alone: no zenith needed
        return RimReading(info.eccentricity, info.eccentricity_u, len(frames))

    def _keep(self, prefix: str, frames: list[Frame], first: int) -> None:
        """Record a pre-check's frames as ``<prefix>NNN`` (numbered from ``first``): the
        raw data behind its reading, kept as files as ``daemon.keep_frames`` says."""
        for k, f in enumerate(frames, start=first):
            self.recorder.frame(f.image, f"{prefix}{k:03d}")

    def _tilt(self, side: Camera, n: int) -> TiltReading:
        """The sample tilt over ``n`` side frames, each exposed after the one before (a
        real camera's frames have independent noise; one frame's fit is good to a few
        thousandths of a degree at worst); ``tools.tilt_frames`` may take more while the
        tilt is less certain than ``precheck.tilt_u_target_deg``. Tools without a
        multi-frame measurement give the mean of ``tools.tilt`` and, from 2 frames on, its
        standard error."""
        assert self.tools is not None
        frames = grab_frames(side, n, self.abort)
        self._keep(SIDE_FRAME_PREFIX, frames, 0)
        if self.tools.tilt_frames is not None:
            pc = self.p.precheck
            taken = [len(frames)]

            def more(k: int) -> list[Frame]:
                # a faint view may take several seconds of frames: the operator sees why
                target = pc.tilt_u_target_deg
                above = "its target" if target is None else f"{target:g} deg"
                self._emit("precheck", f"side-camera tilt: {k} more frame(s), its "
                           f"uncertainty still above {above}",
                           step=taken[0], total=max(pc.tilt_max_frames, n))
                got = grab_frames(side, k, self.abort)
                self._keep(SIDE_FRAME_PREFIX, got, taken[0])
                taken[0] += len(got)
                return got

            return self.tools.tilt_frames(frames, more)
        assert self.tools.tilt is not None
        t = np.array([float(self.tools.tilt(f)) for f in frames])
        u = float(np.std(t, ddof=1) / math.sqrt(n)) if n > 1 else None
        return TiltReading(float(t.mean()), u, n)

    def _check(self) -> tuple[Verdict, str, Measurement]:
        self.plan = self._verdict_plan()  # one sweep that can decide, not a ladder
        while True:
            m = self._measure("check")
            if m.sigma_centre_um > self.p.max_center_sigma_um:
                self._record("check", m, action="refused")
                return ("out_of_tolerance", f"centre uncertainty {m.sigma_centre_um:.1f} um "
                        f"exceeds max_center_sigma_um {self.p.max_center_sigma_um:g}: cannot "
                        "show the offset is within tolerance", m)
            d = self._decision(m)
            if d.conforms:
                self._record("check", m, action="done")
                return ("within_tolerance", f"{d.text()}; {self._tally()}", m)
            if d.outcome == "does_not_conform":
                self._record("check", m, action="done")
                return ("out_of_tolerance", f"{d.text()}; {self._tally()}", m)
            blocked = self._floor_blocks(m)
            if blocked or self.st.sweeps >= self.p.max_sweeps:
                self._record("check", m, action="stop")
                return ("out_of_tolerance", f"not shown within: {d.text()}; " + (
                    blocked or f"the measurement cannot decide after {self.st.sweeps} sweeps "
                    "(procedure.max_sweeps)"), m)
            what = self._measure_better()
            self._record("check", m, action="measure better", next=what)
            self._emit("sweep", f"cannot decide yet ({d.text()}); {what}", m=m)

    def _calibrate(self, refreshes: int = 0) -> Calibration:
        assert self.tools is not None
        self._emit("calibrate", "calibrating the stage-to-image mapping"
                   + (" (refresh)" if refreshes else ""))
        cal = calibrate(self.rig, self.cfg, self.tools, abort=self.abort,
                        progress=self._progress_safe, recorder=self.recorder,
                        refreshes=refreshes)
        self.st.calibration = cal
        return cal

    def _align(self) -> tuple[Verdict, str, Measurement]:
        cal = self._calibrate()
        rep = self.p.stage_repeatability_um
        m = self._measure("align")
        prev: Measurement | None = None
        ds_prev: np.ndarray | None = None
        extra: dict[str, Any] = {}
        while True:
            if prev is not None and ds_prev is not None:
                cal, extra = self._consistency(cal, prev, m, ds_prev)
            if self.st.centre_jumps >= MAX_CENTRE_JUMPS:
                self._record("align", m, **extra, action="stop")
                raise _Stop("not_converged", f"the centre of rotation moved between sweeps "
                            f"{self.st.centre_jumps} times: the rotation axis cannot move, so "
                            "the camera, the turntable mount or the tracking is not stable; "
                            "no further move made", m)
            if m.sigma_centre_um > self.p.max_center_sigma_um:
                self._record("align", m, **extra, action="refused")
                raise _Stop("not_converged", f"centre uncertainty {m.sigma_centre_um:.1f} um "
                            f"exceeds max_center_sigma_um {self.p.max_center_sigma_um:g}; "
                            "no move made", m)
            d = self._decision(m)
            gain = self._gain(m)
            moves_left = self.st.iterations < self.p.max_iterations
            sweeps_left = self.st.sweeps < self.p.max_sweeps
            helps = gain > rep and moves_left and sweeps_left
            if d.conforms and not helps:
                target_u = self.p.target_u_fraction * self.tol
                at_floor = m.U_um > target_u and self._floor_above(m, target_u)
                if at_floor:
                    self.recorder.event(
                        f"U {m.U_um:.1f} um is above {self.p.target_u_fraction:g} of the "
                        f"tolerance, but the residual error motion alone holds it above "
                        f"{target_u:g} um; more sweeps would not lower it" +
                        ("" if m.runout_corrected else
                         " (commission the rig, alignctl commission, for a runout map)"))
                if (m.U_um > target_u and sweeps_left and not at_floor
                        and self._better_plan() is not None):
                    what = self._measure_better()
                    self._record("align", m, **extra, action="measure better", next=what)
                    self._emit("sweep", f"within, but U {m.U_um:.1f} um is above "
                               f"{self.p.target_u_fraction:g} of the tolerance; {what}", m=m)
                    prev, ds_prev, extra = None, None, {}
                    m = self._measure("align")
                    continue
                self._record("align", m, **extra, action="done")
                return ("aligned", f"{d.text()}; {self._tally()}", m)
            if not helps:
                if gain > rep:  # a move would help, but the caps forbid it
                    self._record("align", m, **extra, action="stop")
                    cap = (f"the move cap (procedure.max_iterations {self.p.max_iterations})"
                           if not moves_left else
                           f"the sweep cap (procedure.max_sweeps {self.p.max_sweeps})")
                    raise _Stop("not_converged", f"{d.text()}; {cap} is reached "
                                f"after {self._tally()}", m)
                if d.outcome == "does_not_conform":
                    self._record("align", m, **extra, action="stop")
                    raise _Stop("not_converged", f"{d.text()}; a move would gain "
                                f"{max(gain, 0.0):.1f} um, less than the stages' "
                                f"repeatability {rep:g} um: the stages cannot get closer", m)
                blocked = self._floor_blocks(m)
                if blocked or not sweeps_left:
                    self._record("align", m, **extra, action="stop")
                    raise _Stop("out_of_tolerance", f"not shown within: {d.text()}; " + (
                        blocked or f"the measurement cannot decide after {self.st.sweeps} "
                        "sweeps (procedure.max_sweeps)"), m)
                what = self._measure_better()
                self._record("align", m, **extra, action="measure better", next=what)
                self._emit("sweep", f"cannot decide yet and a move would gain only "
                           f"{max(gain, 0.0):.1f} um; {what}", m=m)
                prev, ds_prev, extra = None, None, {}
                m = self._measure("align")
                continue
            reason = self._divergence(prev, m, ds_prev)
            if reason:
                if cal.refreshes < MAX_CAL_REFRESHES:
                    self._warn(f"{reason}; refreshing the calibration")
                    cal = self._calibrate(cal.refreshes + 1)
                else:
                    self._record("align", m, **extra, action="stop")
                    raise _Stop("not_converged", f"{reason} (offset {m.norm_um:.1f} um)", m)
            ds_actual, move_rec = self._correct(cal, m, self.st.iterations + 1)
            self.st.iterations += 1
            pred = self._predicted(cal, m, ds_actual)
            if pred is not None:  # the move was small and its outcome decides: no sweep
                self._record("align", m, **extra, action="move", **move_rec,
                             next="verdict predicted after the move")
                self.st.last = pred
                return ("aligned", f"{self._decision(pred).text()}; predicted after the "
                        f"last move of {pred.moved_um:.1f} um (the stages' landing scatter "
                        f"in U); {self._tally()}", pred)
            nxt = self._verdict_plan()  # the sweep after a move is the verdict's candidate
            if nxt != self.plan:
                self.plan = nxt
                move_rec["next"] = f"the sweep after the move over +-{nxt.half_deg:g} deg"
            self._record("align", m, **extra, action="move", **move_rec)
            prev, ds_prev, extra = m, ds_actual, {}
            m = self._measure("align")

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
