"""Commissioning on the direct simulated rig: each way a rig can differ from its config is
found and named, and a rig that matches its config passes."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from procedures_support import scene_rig, sim_config

from alignd.config import AligndConfig
from alignd.procedures.commission import CommissionRecord, run_commission
from alignd.procedures.tools import CameraInfo, RimInfo, Tools
from alignd.simulated import standin_tools
from drivers.camera import Frame
from drivers.sim.world import World


def image_order_tools(seed: int, sigma_px: float = 0.01) -> Tools:
    """The world's projected corners + noise, in the real tracker's image order (top-left,
    top-right, bottom-right, bottom-left), and a side view from the scene's geometry."""
    return standin_tools(np.random.default_rng(seed + 1000), sigma_px)


def with_world(cfg: AligndConfig, **world: object) -> AligndConfig:
    assert cfg.sim is not None
    sim = cfg.sim.model_copy(update={"world": cfg.sim.world.model_copy(update=world)})
    return cfg.model_copy(update={"sim": sim})


def commission(cfg: AligndConfig, seed: int = 2) -> CommissionRecord:
    return commission_world(cfg, seed)[0]


def commission_world(cfg: AligndConfig, seed: int = 2) -> tuple[CommissionRecord, World]:
    rig, world = scene_rig(cfg, seed)
    rec = run_commission(rig, cfg, tools=image_order_tools(seed), abort=threading.Event())
    return rec, world


def verdicts(rec: CommissionRecord) -> dict[str, str]:
    return {f.item: f.verdict for f in rec.findings}


def test_a_rig_that_matches_its_config_is_commissioned() -> None:
    cfg = with_world(sim_config(), wobble_um=6.0)
    rec, world = commission_world(cfg)
    assert rec.verdict == "commissioned", rec.reason
    v = verdicts(rec)
    for item in ("turntable.direction", "turntable.angle_scale", "top.pixel_size",
                 "holder.size", "axis.x.direction", "axis.y.direction", "top.exposure"):
        assert v[item] == "pass", (item, rec.finding(item))
    assert rec.turntable_sign == 1
    assert rec.angle_scale == pytest.approx(1.0, abs=0.002)
    # the holder face is 30 mm nearer the camera than the turntable plane: 160 * 770 / 800
    assert rec.pixel_size_um == pytest.approx(154.0, rel=0.01)
    assert rec.holder_size_mm == pytest.approx((40.0, 25.0), rel=0.01)
    # the cable wrap allows 338 deg: enough to separate the bearing's harmonics from the
    # axis and the arm; the map is its error motion
    m = rec.runout
    assert m is not None and not m.full_turn and np.ptp(m.angles_deg) > 330
    w = np.array([world.wobble_mm(a) for a in m.angles_deg])
    # noise (0.8 um per frame) and the encoder's periodic error (1 um at the holder) remain
    err = np.hypot(*(m.offset_mm - w).T) * 1000
    assert np.sqrt(np.mean(err ** 2)) < 1.0 and err.max() < 2.5, err
    assert m.amplitude_um > 4.0
    out = rec.to_json()
    assert out["verdict"] == "commissioned" and out["config_hash"] == rec.config_hash
    back = CommissionRecord.from_json(out)
    assert back.turntable_sign == 1 and back.runout is not None
    assert back.valid_for(rec.config_hash, rec.devices) == ""
    assert "config changed" in back.valid_for("0" * 64, rec.devices)


@pytest.mark.parametrize(("world", "config", "item", "name"), [
    ({"turntable_direction": -1}, {}, "turntable.direction", "reversed"),
    ({"camera_mirror": True}, {}, "turntable.direction", "reversed"),
    ({}, {"holder": {"size_mm": (44.0, 27.5)}}, "holder.size", "holder size wrong"),
    ({}, {"cameras": "pixel+20"}, "top.pixel_size", "pixel size wrong"),
    ({"swap_xy": True}, {}, "axis.x.direction", "swapped"),
    ({"invert_y": True}, {}, "axis.y.direction", "inverted"),
    ({"turntable_scale": 1.02}, {}, "turntable.angle_scale", "mis-scaled"),
])
def test_each_deliberate_difference_is_found_and_named(world: dict[str, object],
                                                       config: dict[str, object], item: str,
                                                       name: str) -> None:
    cfg = with_world(sim_config(), **world)
    if "holder" in config:
        cfg = cfg.model_copy(update={"holder": cfg.holder.model_copy(
            update=config["holder"])})  # type: ignore[arg-type]
    if config.get("cameras") == "pixel+20":
        cams = [c.model_copy(update={"pixel_size_um": 192.0}) if c.role == "top" else c
                for c in cfg.cameras]
        cfg = cfg.model_copy(update={"cameras": cams})
    rec = commission(cfg)
    f = rec.finding(item)
    assert f is not None, rec.reason
    assert f.name == name, f.message
    assert f.verdict in ("fail", "warn")
    if f.verdict == "fail":
        assert rec.verdict == "failed" and item in rec.reason
    # everything else still measured: one finding per item, no fault
    assert rec.verdict != "fault", rec.reason


def test_daemon_commission_record_is_used_by_align(capsys: pytest.CaptureFixture[str]) -> None:
    """The daemon on a rig whose turntable turns the other way round: align stops naming it;
    commission records the direction; status shows the record; align then uses it."""
    import json
    from functools import partial

    from daemon_fakes import make_env, wait_until

    from alignd.cli import main as alignctl
    from alignd.procedures import run_alignment

    world_cfg = with_world(sim_config(), turntable_direction=-1)
    rig, _world = scene_rig(world_cfg, 4)
    tools = image_order_tools(4)
    procs = {"align": partial(run_alignment, tools=tools),
             "commission": partial(run_commission, tools=tools)}
    for env in make_env(procs, rig_factory=lambda _cfg: rig):
        wait_until(lambda env=env: env.daemon.state == "idle")
        assert alignctl(["--socket", env.sock, "align", "--json", "-q"]) == 2
        out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert "turntable reversed" in out["reason"]
        assert alignctl(["--socket", env.sock, "commission", "-q"]) == 0
        text = capsys.readouterr().out
        assert "run 2: commissioned" in text
        assert "WARN  turntable.direction" in text and "reversed" in text
        out_dir = Path(env.sock).parent / "report"
        assert alignctl(["--socket", env.sock, "report", "2", "--out", str(out_dir)]) == 0
        capsys.readouterr()
        png = cv2.imread(str(out_dir / "run-2.png"))
        assert png is not None and png.shape[1] == 1100 and png.shape[0] > 900
        record = json.loads((out_dir / "run-2.json").read_text())
        assert record["kind"] == "commission" and record["result"]["runout"]["amplitude_um"] > 0
        assert alignctl(["--socket", env.sock, "status"]) == 0
        assert "commission: using commission run 2" in capsys.readouterr().out
        assert alignctl(["--socket", env.sock, "align", "--json", "-q"]) == 0
        out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert out["verdict"] == "aligned"
        assert out["truth"]["offset_norm_um"] <= 10.0
        run = env.client.run(3)
        assert any("using commission run 2" in e["msg"] for e in run["events"])
        assert run["details"]["conventions"]["turntable_direction"] == -1


def test_soft_limits_beyond_the_controllers_travel_fail() -> None:
    """A controller that reports its travel (SMC100 SL?/SR?) is held to it."""
    from drivers.sim.direct import DirectSimAxis

    class NarrowTravel(DirectSimAxis):
        def software_limits(self) -> tuple[float, float]:
            return (-100.0, 100.0)

    cfg = sim_config()
    rig, _ = scene_rig(cfg, 2)
    rig.axes["turntable"].__class__ = NarrowTravel  # same axis, now reporting its travel
    rec = run_commission(rig, cfg, tools=image_order_tools(2), abort=threading.Event())
    f = rec.finding("device.turntable")
    assert f is not None and f.verdict == "fail" and f.name == "soft limits beyond travel"
    assert "[-100, 100]" in f.message
    other = rec.finding("device.x")
    assert other is not None and other.verdict == "pass"  # the Zaber axis reports no travel


@pytest.mark.parametrize(("said", "faint", "name"), [
    ("the holder's edges clip along all four sides; lower the exposure or the light",
     False, "clipped"),
    ("the holder was found only by a second search at a lower contrast: its sides step "
     "less than 15 DN against what surrounds them (about 13 DN)", True, "faint")])
def test_a_holder_clipped_all_round_or_faint_is_a_warning_that_names_the_exposure(
        said: str, faint: bool, name: str) -> None:
    """Where the tracker says the holder's edges clip along every side, or that it found
    the holder only at a lower contrast, commissioning warns under top.exposure (what to
    do, named "clipped" or "faint") and still commissions: the corners are measured, only
    less surely than their sigma says, or with more noise."""
    import dataclasses

    from alignd.procedures.tools import Corners

    cfg = sim_config()
    rig, _world = scene_rig(cfg, 2)
    base = image_order_tools(2)

    def track(frame: Frame) -> Corners:
        return dataclasses.replace(base.track(frame), warning=said, faint=faint)

    rec = run_commission(rig, cfg, tools=dataclasses.replace(base, track=track),
                         abort=threading.Event())
    f = rec.finding("top.exposure")
    assert f is not None and f.verdict == "warn" and f.name == name
    assert said in f.message
    assert rec.verdict == "commissioned", rec.reason


def _camera_tool(gamma: float | None, gamma_u: float | None, act: list[str]
                 ) -> Callable[[list[Frame]], CameraInfo]:
    """A stand-in for alignd.vision.camera_check: what it would read, whatever the frames."""
    def camera(frames: list[Frame]) -> CameraInfo:
        assert len(frames) == 8 and len({f.seq for f in frames}) == 8  # 8 distinct frames
        allowed = None if gamma is None or gamma_u is None else (gamma - 3 * gamma_u,
                                                                 gamma + 3 * gamma_u)
        text = "gamma not measured" if gamma is None else f"gamma {gamma:.2f} +- {gamma_u:.2f}"
        return CameraInfo(gamma, gamma_u, allowed, text, act, {"gamma": gamma, "findings": []})
    return camera


@pytest.mark.parametrize("configured", [1.0, 2.2])
def test_commissioning_checks_the_top_cameras_tone_curve_against_its_config(
        configured: float) -> None:
    """A camera whose frames' noise says gamma 2.2 +- 0.06: with the config at 1 a warning
    under top.frames that names the key and the value to set; at 2.2 a pass. Either way
    the rig is commissioned and the check's numbers are in the record."""
    import dataclasses

    cfg = sim_config()
    top = next(c for c in cfg.cameras if c.role == "top")
    cfg.cameras[cfg.cameras.index(top)] = top.model_copy(update={"gamma": configured})
    rig, _world = scene_rig(cfg, 2)
    tools = dataclasses.replace(image_order_tools(2), camera=_camera_tool(2.2, 0.06, []))
    rec = run_commission(rig, cfg, tools=tools, abort=threading.Event())
    assert rec.verdict == "commissioned", rec.reason
    f = rec.finding("top.frames")
    assert f is not None and f.value["gamma"] == 2.2 and f.expected == {"gamma": configured}
    if configured == 1.0:
        assert f.verdict == "warn" and f.name == "camera settings"
        assert "gamma 2.20 +- 0.06, the config says gamma 1" in f.message
        assert f.config_fix == {"cameras.top.gamma": 2.2}
    else:
        assert f.verdict == "pass" and f.config_fix is None, f.message
    # the side camera's frames too, against its own config (gamma 1)
    side = rec.finding("side.frames")
    assert side is not None and side.verdict == "warn"
    assert side.config_fix == {"cameras.side.gamma": 2.2}


def test_commissioning_names_a_camera_setting_to_change() -> None:
    """Settings the check says to change (sharpening, here) warn, the tone curve unknown."""
    import dataclasses

    cfg = sim_config()
    rig, _world = scene_rig(cfg, 2)
    said = "the camera sharpens its frames (neighbouring pixels' noise correlates -0.09): " \
           "set its sharpness to the lowest value"
    tools = dataclasses.replace(image_order_tools(2), camera=_camera_tool(None, None, [said]))
    rec = run_commission(rig, cfg, tools=tools, abort=threading.Event())
    f = rec.finding("top.frames")
    assert f is not None and f.verdict == "warn" and said in f.message
    assert f.config_fix is None
    assert rec.verdict == "commissioned", rec.reason


def test_the_daemons_camera_tool_reads_a_simulated_cameras_curve() -> None:
    """default_tools' camera check on our simulated top camera's frames (8 of a still
    view), drawn linear and through gamma 2.2: the curve within 3 u, a curve named where
    there is one, and no camera setting to change (the simulated camera neither sharpens
    nor clips)."""
    from alignd.config import load_config
    from alignd.procedures.tools import default_tools
    from drivers.config import SimWorldConfig
    from drivers.sim.sim_camera import SimCamera
    from drivers.sim.world import World

    tools = default_tools(load_config("configs/sim.yaml"))
    assert tools.camera is not None
    world = World(SimWorldConfig(), {}, np.random.default_rng(0))
    for gamma in (1.0, 2.2):
        cam = SimCamera(world, "top", seed=4, gamma=gamma)
        info = tools.camera([cam.grab() for _ in range(8)])
        assert info.gamma is not None and info.gamma_u is not None
        assert abs(info.gamma - gamma) <= 3 * info.gamma_u, (gamma, info.gamma, info.gamma_u)
        assert info.act == []
        findings = info.record["findings"]
        assert isinstance(findings, list)
        curve = [f for f in findings if f["key"] == "gamma"]
        assert (curve[0]["level"] == "act") == (gamma > 1)


def test_an_abort_during_the_camera_check_aborts_the_commission() -> None:
    """The operator's abort while the camera check runs ends the run as aborted (it is
    not taken for a camera that could not be checked)."""
    import dataclasses

    from alignd.procedures.rig import AbortRequested

    cfg = sim_config()
    rig, _world = scene_rig(cfg, 2)
    abort = threading.Event()

    def camera(frames: list[Frame]) -> CameraInfo:
        abort.set()
        raise AbortRequested("abort requested")

    tools = dataclasses.replace(image_order_tools(2), camera=camera)
    rec = run_commission(rig, cfg, tools=tools, abort=abort)
    assert rec.verdict == "aborted", rec.reason
    assert rec.finding("top.frames") is None


def _rim_tool(u_still: float, u_turned: float
              ) -> Callable[[list[Frame], float | None, float | None], RimInfo]:
    """A rim fit that reads e = 0.02 +- ``u_still`` from frames taken where the
    turntable stood and +- ``u_turned`` from frames turned apart."""
    def rim(frames: list[Frame], radius: float | None, height: float | None) -> RimInfo:
        angles = [float(f.metadata["turntable_deg_true"]) for f in frames]
        return RimInfo((640.0, 360.0), 0.02, None,
                       u_turned if np.ptp(angles) > 1.0 else u_still)

    return rim


@pytest.mark.parametrize(("u", "turn", "verdict", "fix"), [
    ((0.0004, 0.0004), 0.0, "pass", None),
    ((0.0030, 0.0006), 0.0, "warn", {"procedure.precheck.rim_turn_deg": 22.5}),
    ((0.0030, 0.0028), 0.0, "warn", None),
    ((0.0030, 0.0030), 22.5, "warn", None),
])
def test_an_uncertain_rim_warns_and_names_what_makes_it_certain(
        u: tuple[float, float], turn: float, verdict: str, fix: dict[str, float] | None
        ) -> None:
    """e less certain than 0.001 (a third of the 0.003 the vision holds it to) is a
    warning. From still frames the rim is measured again with the disc turned 180 /
    rim_frames deg between the frames, and that turn is the fix where it made e clearly
    more certain (a disc's texture); where it did not, or the frames were turned already,
    the warning says what is left to the lab. A certain e passes with no fix and no
    turn."""
    import dataclasses

    base = sim_config()
    cfg = sim_config(precheck=base.procedure.precheck.model_copy(update={"rim_turn_deg": turn}))
    rig, _world = scene_rig(cfg, 2)
    tools = dataclasses.replace(image_order_tools(2), rim=_rim_tool(*u))
    rec = run_commission(rig, cfg, tools=tools, abort=threading.Event())
    assert rec.verdict == "commissioned", rec.reason
    f = rec.finding("top.rim")
    assert f is not None and f.verdict == verdict and f.config_fix == fix, f.message
    retried = verdict == "warn" and not turn
    assert f.sigma == {"eccentricity": u[0]} | (
        {"eccentricity_turned": u[1]} if retried else {}), f.sigma
    if verdict == "warn":
        assert f.name == "uncertain" and "uncertain to more than 0.001" in f.message
    if retried:
        assert f"turned 22.5 deg apart here, e reads 0.0200 +- {u[1]:.4f}" in f.message
        assert ("no more certain" in f.message) == (fix is None)
    if turn:
        assert "averages its texture" in f.message and "more rim_frames" in f.message


def test_rim_advice_keeps_the_turn_inside_the_soft_limits() -> None:
    from alignd.procedures.commission import rim_advice

    # 8 frames in +-40 deg: 80 / 7 = 11.4 deg a step, not 22.5
    text, fix = rim_advice(8, 0.0, -40.0, 40.0)
    assert fix == {"procedure.precheck.rim_turn_deg": 11.4} and "about 79.8 deg" in text
    # +-10 deg leaves 2.8 deg a step: too little to average a texture, no turn offered
    text, fix = rim_advice(8, 0.0, -10.0, 10.0)
    assert fix is None and "soft limits [-10, 10] leave too little turn" in text
    # one frame: more frames first
    assert rim_advice(1, 0.0, -169.0, 169.0)[1] == {"procedure.precheck.rim_frames": 8}
    # 4 frames: 45 deg, the config's largest step
    assert rim_advice(4, 0.0, -169.0, 169.0)[1] == {"procedure.precheck.rim_turn_deg": 45.0}
