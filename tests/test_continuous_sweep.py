"""The continuous (on-the-fly) sweep: velocity on the wire, exposure-true simulated frames,
the blur limit, and a continuous measurement on the direct simulated rig (manual clock)."""

from __future__ import annotations

import math
import struct
import threading
from typing import Any

import numpy as np
import pytest
import test_apt
import test_zaber
from procedures_support import scene_rig, sim_config, standin_tools
from test_smc100 import CONNECT, home, make_emu, scripted_axis

from alignd.config import HolderConfig, continuous_speed, parse_config
from alignd.errors import ConfigError
from alignd.procedures import MemoryRecorder, ProgressEvent
from alignd.procedures.holder_geometry import holder_pose, holder_poses
from alignd.procedures.rig import AbortRequested
from alignd.procedures.sweep import Measurement, SweepData, measure
from alignd.simulated import build_direct_rig
from drivers.errors import LimitError
from drivers.sim.sim_camera import SimCamera


def test_smc100_set_speed_sends_va_and_the_emulator_turns_at_it() -> None:
    axis, port = scripted_axis([*CONNECT, (b"1VA5\r\n", b""), (b"1TE\r\n", b"1TE@\r\n")])
    with axis:
        axis.set_speed(5.0)
        assert axis.speed == 5.0
        with pytest.raises(LimitError, match=r"outside \(0, 20\]"):
            axis.set_speed(25.0)  # above the configured speed: refused before a byte
    assert port.written == b"1TS\r\n1VA5\r\n1TE\r\n" and not port.script
    # the emulator's kinematics honour VA: 2 s after PA at 5 deg/s (accel 80) the stage
    # has covered 2 * 5 - 5^2 / (2 * 80) deg
    emu, axes, clock = make_emu(start=0.0)
    home(emu, clock)
    assert emu.handle(b"1VA5\r\n1TE\r\n1PA20\r\n1TE\r\n") == b"1TE@\r\n1TE@\r\n"
    clock.advance(2.0)
    assert axes[1].motor_position() == pytest.approx(10.0 - 25.0 / 160.0, abs=1e-9)


def test_direct_axis_moves_at_the_set_speed_and_restores_it() -> None:
    rig, _world = scene_rig(sim_config(), 1)
    rig.connect()
    tt = rig.axis("turntable")
    with tt.speed_limited(2.0):
        t0 = tt.clock.now()
        tt.start_move(4.0)
        reached = tt.end_move(4.0, 0.0)
        took = tt.clock.now() - t0
    assert reached == pytest.approx(4.0, abs=tt.config.deadband)
    assert took >= 2.0  # 4 deg at 2 deg/s, not at the configured 20 deg/s
    assert tt.speed == tt.config.speed


def test_sim_camera_frame_is_stamped_mid_exposure_and_smeared() -> None:
    cfg = sim_config()
    rig, world = build_direct_rig(cfg, 2)
    rig.connect()
    tt = rig.axis("turntable")
    cam = rig.camera("top")
    assert isinstance(cam, SimCamera)
    sharp = cam.grab().image.astype(float)
    cam.exposure_s = 0.1
    tt.start_move(10.0)  # 20 deg/s: 2 deg, about 6 px at the far corner, in 0.1 s
    tt.clock.sleep(0.3)  # at constant speed by now
    f = cam.grab()
    assert f.timestamp == pytest.approx(tt.clock.now() - 0.05)
    assert f.metadata["turntable_deg_true"] == pytest.approx(
        world.turntable_deg(world.now() - 0.05), abs=1e-9)
    # the smear flattens the holder's edges near its corners (the rim does not move):
    # the steepest step there is much smaller than in a sharp frame
    def steepest(img: np.ndarray, at: float) -> float:
        corners = world.top_camera.project(world.top_scene(at).holder_corners_mm)
        x, y = np.round(corners[np.argmax(np.hypot(*(corners - corners.mean(0)).T))]).astype(int)
        win = img[y - 12:y + 12, x - 12:x + 12].astype(float)
        return float(max(np.abs(np.diff(win, axis=a)).max() for a in (0, 1)))

    assert steepest(f.image, world.now() - 0.05) < 0.6 * steepest(sharp, 0.0)


def continuous_config(**cont: object) -> dict[str, Any]:
    cfg = sim_config()
    data = cfg.model_dump(mode="json")
    data["procedure"]["sweep_mode"] = "continuous"
    data["procedure"]["continuous"].update(cont)
    return data


def test_blur_beyond_the_limit_is_refused_naming_the_keys() -> None:
    with pytest.raises(ConfigError) as err:
        parse_config(continuous_config(speed_deg_s=20.0, exposure_s=0.02), "rig.yaml")
    msg = str(err.value)
    for key in ("procedure.continuous.speed_deg_s", "procedure.continuous.exposure_s",
                "procedure.continuous.max_blur_px", "cameras.top.pixel_size_um",
                "on_blur: cap"):
        assert key in msg
    # 20 deg/s x 0.02 s x (hypot(40, 25) / 2 + 5 mm) / the top camera's pixel size
    top = sim_config().camera("top")
    assert top is not None and top.pixel_size_um is not None
    blur = math.radians(20) * 0.02 * (math.hypot(40, 25) / 2 + 5) * 1000 / top.pixel_size_um
    assert f"{blur:.2f} px" in msg
    capped = parse_config(continuous_config(speed_deg_s=20.0, exposure_s=0.02,
                                            on_blur="cap"), "rig.yaml")
    speed, blur = continuous_speed(capped)
    assert blur == pytest.approx(0.5) and speed < 20.0
    assert continuous_speed(capped, frames_per_step=2)[0] == pytest.approx(speed)
    with pytest.raises(ConfigError, match="does not fit in a frame period"):
        parse_config(continuous_config(exposure_s=0.05), "rig.yaml")


def run_continuous(seed: int) -> tuple[SweepData, Measurement, dict[str, Any], float]:
    """One continuous measurement on a world without bearing error motion (no runout map
    here to correct it) through the stand-in tracker (true corners + 0.01 px noise)."""
    raw_cfg = continuous_config()
    raw_cfg["sim"]["world"]["wobble_um"] = 0.0
    cfg = parse_config(raw_cfg, "sim")
    rig, world = scene_rig(cfg, seed)
    rig.connect()
    t0 = rig.axis("turntable").clock.now()
    data, m, _warning = measure(rig, cfg, standin_tools(seed, sigma_px=0.01), kind="measure",
                                iteration=0, abort=None, progress=lambda _e: None,
                                recorder=MemoryRecorder(), pixel_size_um=160.0,
                                floor_um=0.0)
    return data, m, world.truth(), rig.axis("turntable").clock.now() - t0


def test_continuous_sweep_recovers_the_offset_deterministically() -> None:
    data, m, truth, took = run_continuous(4)
    # 20 deg at 5 deg/s at 30 fps: over 110 frames, all tracked, in about 4 s of motion
    assert len(data.readback_deg) >= 110 and data.tracked.all()
    assert took < 10.0
    err = np.hypot(*(np.asarray(m.offset_um) - np.asarray(truth["offset_um"])))
    assert err <= 1.5  # um (0.6 um seen; stop-and-go's 21 frames: about 3 um)
    assert err <= m.U_um <= 3.0
    again, m2, _t, took2 = run_continuous(4)
    assert np.array_equal(m.offset_um, m2.offset_um) and took == took2
    assert again.readback_deg == data.readback_deg


def test_a_continuous_sweep_counts_the_frames_the_tracker_warned_of() -> None:
    """The tracker's warning (a holder clipped all round) on some frames reaches the
    sweep's data, counted, as in a stop-and-go sweep."""
    from dataclasses import replace

    raw_cfg = continuous_config()
    raw_cfg["sim"]["world"]["wobble_um"] = 0.0
    cfg = parse_config(raw_cfg, "sim")
    rig, _world = scene_rig(cfg, 3)
    rig.connect()
    base = standin_tools(3, sigma_px=0.01)
    calls = [0]

    def track(frame: Any) -> Any:
        calls[0] += 1
        c = base.track(frame)
        return replace(c, warning="clipped all round") if calls[0] % 10 == 0 else c

    data, _m, _w = measure(rig, cfg, replace(base, track=track), kind="measure", iteration=0,
                           abort=None, progress=lambda _e: None, recorder=MemoryRecorder(),
                           pixel_size_um=160.0, floor_um=0.0)
    assert data.mode == "continuous"
    assert data.warned_frames == calls[0] // 10 > 0 and data.warning == "clipped all round"


def test_abort_mid_sweep_stops_the_table_and_restores_its_speed() -> None:
    cfg = parse_config(continuous_config(), "sim")
    rig, _world = scene_rig(cfg, 5)
    rig.connect()
    tt = rig.axis("turntable")
    abort = threading.Event()

    def progress(ev: ProgressEvent) -> None:
        abort.set()  # the first progress event comes from the stream's first frame

    with pytest.raises(AbortRequested):
        measure(rig, cfg, standin_tools(5), kind="measure", iteration=0, abort=abort,
                progress=progress, recorder=MemoryRecorder(), pixel_size_um=160.0)
    pos = tt.position()
    assert -10.5 < pos < 0.0  # stopped early in the sweep
    tt.clock.sleep(1.0)
    assert not tt.status().moving and tt.position() == pos
    assert tt.speed == tt.config.speed


def test_vectorised_holder_poses_match_the_per_frame_pose() -> None:
    rng = np.random.default_rng(1)
    holder = HolderConfig(size_mm=(40.0, 25.0), target_mm=(0.0, -17.5))
    corners = rng.normal(0, 30, (30, 4, 2)) + np.array([[0, 0], [250, 0], [250, 156],
                                                        [0, 156]])
    poses = holder_poses(corners, holder)
    for i, c in enumerate(corners):
        one = holder_pose(c, holder)
        assert np.allclose(one.target_px, poses.target_px[i], rtol=0, atol=1e-9)
        assert one.scale_px_per_mm == pytest.approx(poses.scale_px_per_mm[i], abs=1e-12)
        assert one.angle_deg == pytest.approx(poses.angle_deg[i], abs=1e-9)


def test_apt_set_speed_writes_velparams_and_reads_them_back() -> None:
    # 0.5 mm/s on an MTS25-Z8 under a KDC101: 0.5 x 34304 counts/mm x T x 65536, T = 2048/6e6
    reg = round(0.5 * 34304 * 2048 / 6e6 * 65536)
    assert reg == 383684
    payload = test_apt.H("01 00 00 00 00 00") + struct.pack("<ii", 1048, reg)
    axis, fake = test_apt.connected([(test_apt.H("13 04 0e 00 d0 01") + payload, b""),
                                     (test_apt.REQ_VEL, test_apt.H("15 04 0e 00 81 50")
                                      + payload)])
    axis.set_speed(0.5)
    assert axis.speed == 0.5 and not fake.script


def test_zaber_set_speed_writes_maxspeed_in_the_manuals_units() -> None:
    # 2.5 mm/s at 0.047625 um per microstep: 52493.4 microsteps/s x 1.6384 = 86005
    axis, tr = test_zaber.scripted_axis([
        (test_zaber.manual_ck("/1 1 6 set maxspeed 86005"),
         test_zaber.manual_ck("@01 1 06 OK IDLE -- 0"))])
    axis.set_speed(2.5)
    assert axis.speed == 2.5 and not tr.script
