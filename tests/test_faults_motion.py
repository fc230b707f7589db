"""Issue 6, scenarios 6-12 and 14: motion faults (limit switch, stall, timeout, a controller
that says done too early, a missed target), bad targets and limits, a loop that does not
converge, and corrections that are too uncertain or too big.

Daemon-level scenarios run the real ``alignd`` in a subprocess on the simulated rig with
config-driven faults (``faults_support``); driver-level ones run each real driver against
its emulator on a TCP port; loop-level ones use the direct simulated rig (ManualClock)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
import yaml
from faults_support import SIM_YAML, assert_end_state, short_tmp, sim_daemon, targets
from procedures_support import commanded, scene_rig, sim_config, standin_tools
from test_faults_link import served

from alignd import daemon as daemon_mod
from alignd.cli import main as alignctl
from alignd.procedures import MemoryRecorder, ProgressEvent, run_alignment
from alignd.procedures.tools import Corners
from drivers.config import SoftLimits
from drivers.errors import DeviceTimeoutError, LimitError, MissedTargetError
from drivers.sim.kinematics import SimAxis

NAMES = ["turntable", "translator", "platform"]


# ---- 6. hardware limit switch ------------------------------------------------------------------
def test_limit_switch_mid_run_stops_records_and_never_retries() -> None:
    faults = [{"device": "platform", "kind": "limit_switch", "axis": "x",
               "on": "move abs", "nth": 4}]
    with sim_daemon(faults=faults) as dp:
        run = dp.run_and_wait("align")
        assert_end_state(dp, run, verdicts=["fault"],
                         reason_has=["limit switch", "device x", "socket://"])
        snap = dp.snapshot()
        # the flag is still set: no move of x was commanded after the switch tripped
        assert snap["x"]["limit_high"] and not snap["x"]["moving"]
        xs = [t for t in targets(dp.target_log) if t["axis"] == "x"]
        assert len(xs) >= 2  # it tripped mid-run, after homing
        assert dp.client.status()["state"] == "fault"


# ---- 9. stall, and a move that outlasts its timeout --------------------------------------------
def test_stall_mid_sweep_stops_and_faults_and_a_timer_check_is_then_skipped(
        capsys: pytest.CaptureFixture[str]) -> None:
    """Scenario 9 (stall), and 21 (a scheduled check while the daemon is faulted)."""
    faults = [{"device": "turntable", "kind": "stall", "on": "PA", "nth": 3}]
    with sim_daemon(faults=faults) as dp:
        run = dp.run_and_wait("check")
        assert_end_state(dp, run, verdicts=["fault"], reason_has=["device turntable"])
        assert any(w in run["reason"] for w in ("stall", "following error")), run["reason"]
        assert not dp.snapshot()["turntable"]["stalled"]  # stopped, not left straining
        assert alignctl(["--socket", str(dp.sock), "check", "--started-by", "timer"]) == 75
        err = capsys.readouterr().err
        assert "skipped" in err and "faulted" in err
        assert len(dp.client.history()) == 1  # the skipped check left no run behind


def test_move_outlasting_its_timeout_is_stopped() -> None:
    cfg = sim_config()
    rig, _ = scene_rig(cfg, 2)
    sim = rig.sim_parts.sim_axes["x"]  # type: ignore[attr-defined]
    sim.p.speed = 0.05  # the stage is far slower than its config says
    ax = rig.axis("x")
    ax.connect()
    with pytest.raises(DeviceTimeoutError, match="did not finish within") as info:
        ax.move_to(sim.motor_position() + 3.0)
    assert info.value.device == ax.name and info.value.command.startswith("move to")
    assert not sim.moving and not ax.position_known


# ---- 7. bad targets are refused before any byte is sent ------------------------------------------
@pytest.mark.parametrize("name", NAMES)
def test_targets_outside_soft_limits_nan_or_inf_never_reach_the_controller(name: str) -> None:
    with served(name) as (axis, sim, srv):
        lim = axis.config.soft_limits
        seen, moves = srv.emulator.commands_seen, list(sim.targets)
        for bad in (math.nan, math.inf, -math.inf, lim.max + 1e-3, lim.min - 1.0, 1e308):
            with pytest.raises(LimitError) as info:
                axis.move_to(bad)
            assert info.value.device == axis.name and info.value.port == srv.url
        assert srv.emulator.commands_seen == seen and sim.targets == moves


# ---- 8. missing or empty limits in the config -------------------------------------------------
@pytest.mark.parametrize(("edit", "key", "why"), [
    (lambda ax: ax.pop("soft_limits"), "controllers.2.axes.0.soft_limits", "Field required"),
    (lambda ax: ax.update(soft_limits={}), "controllers.2.axes.0.soft_limits.min",
     "Field required"),
    (lambda ax: ax.update(soft_limits={"min": 5.0, "max": 5.0}),
     "controllers.2.axes.0.soft_limits", "must be below max"),
    (lambda ax: ax.update(soft_limits={"min": 2.0, "max": None}),
     "controllers.2.axes.0.soft_limits.max", "valid number"),
])
def test_missing_or_empty_limits_refuse_start_naming_the_key(
        edit: Any, key: str, why: str, capsys: pytest.CaptureFixture[str]) -> None:
    tmp = short_tmp()
    data = yaml.safe_load(SIM_YAML.read_text())
    edit(data["controllers"][2]["axes"][0])
    cfg = tmp / "bad.yaml"
    cfg.write_text(yaml.safe_dump(data))
    rc = daemon_mod.main(["--config", str(cfg), "--socket", str(tmp / "s.sock"),
                          "--state-dir", str(tmp / "state")])
    err = capsys.readouterr().err
    assert rc == 2
    assert f"{cfg}: {key}:" in err and why in err, err
    assert not (tmp / "s.sock").exists() and not (tmp / "state").exists()


def test_sweep_beyond_the_turntable_limits_is_refused_before_any_motion() -> None:
    cfg = sim_config(sweep_deg=5.0)
    ctl = cfg.controllers[0]  # the turntable: soft limits [-30, 3] deg cannot hold +-5 deg
    tt = ctl.axes[0].model_copy(update={"soft_limits": SoftLimits(min=-30.0, max=3.0)})
    cfg = cfg.model_copy(update={"controllers": [ctl.model_copy(update={"axes": [tt]}),
                                                 *cfg.controllers[1:]]})
    rig, _ = scene_rig(cfg, 4, homed=False)
    res = run_alignment(rig, cfg, tools=standin_tools(4))
    assert res.verdict == "fault" and res.config_error
    assert "procedure.sweep_deg 5 exceeds the turntable soft limits [-30, 3]" in res.reason
    sims = rig.sim_parts.sim_axes  # type: ignore[attr-defined]
    assert all(not s.targets and not s.homed for s in sims.values())  # nothing moved, homed


# ---- 10 and 11. done too early; outside the deadband after all retries -------------------------
def land_short(sim: SimAxis, by: float, times: int | None) -> list[float]:
    """Make the stage stop ``by`` short of its next ``times`` targets (None: always)."""
    orig = sim.move_to
    asked: list[float] = []

    def short(target: float, speed: float | None = None) -> None:
        asked.append(target)
        if times is None or len(asked) <= times:
            target -= by
        orig(target, speed)
        sim.targets[-1] = asked[-1]  # record what was commanded, as before

    sim.move_to = short  # type: ignore[method-assign]
    return asked


@pytest.mark.parametrize("name", NAMES)
def test_done_before_the_readback_is_in_the_deadband_is_not_done(name: str) -> None:
    with served(name) as (axis, sim, srv):
        dead = axis.config.deadband
        target = axis.config.soft_limits.min + 2.0
        axis.move_to(target - 1.0)
        start = len(targets_of(srv))
        land_short(sim, 20 * dead, times=1)  # the controller says done, 20 deadbands short
        got = axis.move_to(target)
        assert abs(got - target) <= dead
        sent = targets_of(srv)[start:]
        assert sent.count(pytest.approx(target, abs=dead / 10)) >= 2  # sent again


def targets_of(srv: Any) -> list[float]:
    return list(srv.emulator.axes[min(srv.emulator.axes)].targets)


@pytest.mark.parametrize("name", NAMES)
def test_outside_the_deadband_after_all_retries_is_a_missed_target(name: str) -> None:
    with served(name) as (axis, sim, srv):
        target = axis.config.soft_limits.min + 2.0
        land_short(sim, 20 * axis.config.deadband, times=None)
        with pytest.raises(MissedTargetError, match="missed target") as info:
            axis.move_to(target)
        assert info.value.port == srv.url
        finals = [t for t in targets_of(srv) if t == pytest.approx(target, abs=1e-4)]
        assert len(finals) == axis.config.retries + 1  # bounded
        assert not axis.position_known


def test_missed_target_in_a_run_is_a_fault_never_aligned() -> None:
    cfg = sim_config(sweep_steps=7, max_iterations=3)
    rig, _ = scene_rig(cfg, 8)
    land_short(rig.sim_parts.sim_axes["y"], 0.01, times=None)  # type: ignore[attr-defined]
    res = run_alignment(rig, cfg, tools=standin_tools(8))
    assert res.verdict == "fault" and "missed target" in res.reason
    assert not any(a.moving for a in rig.sim_parts.sim_axes.values())  # type: ignore


# ---- 12. diverging or oscillating; the iteration cap ---------------------------------------------
def test_a_loop_that_cannot_converge_ends_not_converged() -> None:
    cfg = sim_config(sweep_steps=9, max_iterations=6)
    rig, _ = scene_rig(cfg, 9)
    base = standin_tools(9).track
    solves = [0]

    def astray(frame: Any) -> Corners:
        """After the first measurement the holder seems to jump, further and further, to
        alternate sides: each correction chases a target that runs away."""
        det = base(frame)
        k = solves[0]
        shift = 0.0 if k == 0 else 12.0 * k * (-1) ** k
        return dataclasses.replace(det, corners_px=det.corners_px + np.array([shift, 0.0]))

    def progress(ev: ProgressEvent) -> None:
        if ev.phase == "solve" and ev.message.startswith("align"):
            solves[0] += 1

    rec = MemoryRecorder()
    res = run_alignment(rig, cfg, tools=standin_tools(9, track=astray), progress=progress,
                        recorder=rec)
    assert res.verdict == "not_converged", res.reason
    assert any(w in res.reason for w in ("diverging", "oscillating", "cap")), res.reason
    assert res.iterations <= cfg.procedure.max_iterations
    for r in ("x", "y"):  # whatever happened, nothing was commanded beyond the soft limits
        lim = rig.axis(r).config.soft_limits
        assert all(lim.min <= t <= lim.max for t in commanded(rig, r))
    assert not any(a.moving for a in rig.sim_parts.sim_axes.values())  # type: ignore


def test_iteration_cap_is_not_converged_and_a_big_step_is_clamped_and_logged() -> None:
    """Scenarios 12 (the cap) and 14 (a step too big) in one run on the rig."""
    proc = {"sweep_steps": 5, "sweep_deg": 5.0, "max_iterations": 2, "max_step_mm": 0.3}
    with sim_daemon(procedure=proc) as dp:
        run = dp.run_and_wait("align")
        assert_end_state(dp, run, verdicts=["not_converged"],
                         reason_has=["after 2 iterations (cap)"])
        moves = [r for r in run["iteration_records"] if r.get("action") == "move"]
        assert len(moves) == 1 and moves[0].get("clamped")
        for role, t in moves[0]["targets_mm"].items():
            assert abs(t - moves[0]["before_mm"][role]) <= 0.3 + 1e-9
        assert any("clamped to max_step_mm 0.3" in e["msg"] for e in run["events"])
        # what the stages received: the clamped targets, and no correction beyond them
        xs = [t["target"] for t in targets(dp.target_log) if t["axis"] == "x"]
        assert any(x == pytest.approx(moves[0]["targets_mm"]["x"], abs=1e-4) for x in xs)


def test_too_uncertain_a_centre_moves_nothing() -> None:
    cfg = sim_config(sweep_steps=7, max_center_sigma_um=0.5)
    rig, _ = scene_rig(cfg, 12)
    rec = MemoryRecorder()
    n_cal: dict[str, int] = {}

    def progress(ev: ProgressEvent) -> None:
        if ev.phase == "solve" and not n_cal:  # calibration done, first sweep measured
            n_cal.update({r: len(commanded(rig, r)) for r in ("x", "y", "z", "translator")})

    res = run_alignment(rig, cfg, tools=standin_tools(12, sigma_px=0.05), recorder=rec,
                        progress=progress)
    assert res.verdict == "not_converged" and "no move made" in res.reason
    assert [r.get("action") for _, r in rec.iterations] == ["refused"]
    assert {r: len(commanded(rig, r)) for r in n_cal} == n_cal


