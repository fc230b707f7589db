"""``alignctl analyze``: JSON fields per the contract, sweep files, exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from alignd.cli import main
from alignd.solve.sweep import load_sweep
from drivers.config import SimWorldConfig
from drivers.sim.render import RenderOptions, posed_world, render_side, render_top, top_truth

OPTS = RenderOptions(gradient=(0.2, 0.1))


@pytest.fixture(scope="module")
def images(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    d = tmp_path_factory.mktemp("frames")
    rng = np.random.default_rng(7)
    tops, truths = [], []
    for a in (-10.0, -2.5, 5.0, 10.0):
        w = posed_world(SimWorldConfig(yaw_deg=1.5), seed=2, turntable_deg=a)
        sc, cam = w.top_scene(), w.top_camera
        p = d / f"top_{a:+.1f}deg.png"
        cv2.imwrite(str(p), render_top(sc, cam, OPTS, rng))
        tops.append(str(p))
        truths.append(np.asarray(top_truth(sc, cam, OPTS)["corners_px"]))
    side = d / "side.png"
    cv2.imwrite(str(side), render_side(posed_world(SimWorldConfig(tilt_deg=0.3)).side_scene(),
                                       OPTS, rng))
    w = posed_world(SimWorldConfig(pixel_size_um=500.0, top_camera_zenith_deg=4.0,
                                   axis_px=(640.0, 360.0)))
    rim = d / "rim.png"
    cv2.imwrite(str(rim), render_top(w.top_scene(), w.top_camera, OPTS, rng))
    for k in range(4):  # frames of one still view, their own noise each
        f = d / f"side_{k}.png"
        cv2.imwrite(str(f), render_side(posed_world(SimWorldConfig(tilt_deg=0.3)).side_scene(),
                                        OPTS, rng))
        f = d / f"rim_{k}.png"
        cv2.imwrite(str(f), render_top(w.top_scene(), w.top_camera, OPTS, rng))
    blank = d / "blank.png"
    cv2.imwrite(str(blank), np.full((720, 1280), 100, np.uint8))
    bad = d / "bad.png"
    bad.write_bytes(b"\x89PNG but not really")
    return {"dir": d, "tops": tops, "truths": truths, "side": str(side), "rim": str(rim),
            "blank": str(blank), "bad": str(bad)}


def _lines(out: str) -> list[dict]:
    return [json.loads(s) for s in out.splitlines() if s.strip()]


def test_top_json_fields(images, capsys) -> None:
    rc = main(["analyze", "top", *images["tops"], "--json"])
    objs = _lines(capsys.readouterr().out)
    assert rc == 0 and len(objs) == 4
    for o, f, t in zip(objs, images["tops"], images["truths"], strict=True):
        assert o["file"] == f
        assert np.max(np.abs(np.asarray(o["corners_px"]) - t)) < 0.06
        assert set(o["pose"]) == {"center_px", "angle_deg"}
        assert 0.8 < o["quality"] <= 1.0
        # the sample face's yaw from the turntable zero (angle taken from the file name)
        assert o["sample_yaw_deg"] == pytest.approx(1.5, abs=0.05)


def test_top_warns_of_a_holder_clipped_all_round(images, tmp_path, capsys) -> None:
    """A frame whose holder reads full scale along every side: measured, with a warning in
    the JSON and on the human line that says what to do; a clean frame has none."""
    from test_vision_holder_clip import _saturated_holder

    img, _ = _saturated_holder(360.0, 1.3, 0)
    sat = tmp_path / "saturated.png"
    cv2.imwrite(str(sat), img)
    assert main(["analyze", "top", str(sat), images["tops"][0], "--json"]) == 0
    got, clean = _lines(capsys.readouterr().out)
    assert "lower the exposure" in got["warning"] and "warning" not in clean
    assert main(["analyze", "top", str(sat)]) == 0
    assert "\n  warning: the holder's edges clip along all four sides" in (
        capsys.readouterr().out)


def test_top_sweep_file_round_trips_through_the_solver_reader(images, tmp_path, capsys) -> None:
    out = tmp_path / "sweep.json"
    rc = main(["analyze", "top", *images["tops"], "--sweep-out", str(out),
               "--pixel-size-um", "160"])
    assert rc == 0
    sw = load_sweep(out)
    assert list(sw.angles_deg) == [-10.0, -2.5, 5.0, 10.0]  # from the file names
    assert sw.pixel_size_um == 160.0 and sw.points.shape == (4, 4, 2)
    # the same feature in every frame (order kept through the sweep)
    for k in range(4):
        assert np.max(np.abs(sw.points[:, k] - np.asarray(images["truths"])[:, k])) < 0.06
    capsys.readouterr()


def test_sweep_needs_angles(images, tmp_path, capsys) -> None:
    img = images["dir"] / "noangle.png"
    img.write_bytes(Path(images["tops"][0]).read_bytes())
    rc = main(["analyze", "top", str(img), "--sweep-out", str(tmp_path / "s.json")])
    assert rc == 2
    assert "no turntable angle" in capsys.readouterr().err
    rc = main(["analyze", "top", str(img), "--sweep-out", str(tmp_path / "s.json"),
               "--angles", "3.5"])
    assert rc == 0 and load_sweep(tmp_path / "s.json").angles_deg[0] == 3.5


def test_side_and_rim_json(images, capsys) -> None:
    assert main(["analyze", "side", images["side"], "--json"]) == 0
    o = _lines(capsys.readouterr().out)[0]
    assert o["file"] == images["side"]
    assert o["tilt_deg"] == pytest.approx(0.3, abs=0.002)
    assert o["sample_angle_deg"] - o["pole_angle_deg"] == pytest.approx(o["tilt_deg"])
    assert main(["analyze", "rim", images["rim"], "--json", "--radius-mm", "150",
                 "--height-mm", "800"]) == 0
    o = _lines(capsys.readouterr().out)[0]
    assert set(o["ellipse"]) == {"center_px", "axes_px", "angle_deg"}
    assert o["eccentricity"] == pytest.approx(0.0688, abs=0.003)
    assert o["camera_zenith_deg"] == pytest.approx(4.0, abs=0.1)


def test_mean_of_still_frames_is_one_result(images, capsys) -> None:
    d = images["dir"]
    sides = [str(d / f"side_{k}.png") for k in range(4)]
    assert main(["analyze", "side", *sides, "--mean", "--json"]) == 0
    objs = _lines(capsys.readouterr().out)
    assert len(objs) == 1 and objs[0]["files"] == sides and objs[0]["frames"] == 4
    o = objs[0]
    assert o["tilt_deg"] == pytest.approx(0.3, abs=0.002)
    assert o["tilt_deg"] == pytest.approx(np.mean(o["frame_tilts_deg"]), abs=1e-9)  # PNG: raw
    rims = [str(d / f"rim_{k}.png") for k in range(4)]
    assert main(["analyze", "rim", rims[0], "--json"]) == 0
    one = _lines(capsys.readouterr().out)[0]
    assert main(["analyze", "rim", *rims, "--mean", "--json"]) == 0
    o = _lines(capsys.readouterr().out)[0]
    assert o["frames"] == 4 and o["files"] == rims
    assert o["eccentricity"] == pytest.approx(0.0688, abs=0.003)
    assert o["eccentricity_std"] < one["eccentricity_std"]  # four frames' noise averaged
    assert main(["analyze", "rim", *rims, "--mean"]) == 0
    assert capsys.readouterr().out.startswith("mean of 4 frames: ellipse centre")


def test_mean_refuses_what_it_cannot_average(images, capsys) -> None:
    assert main(["analyze", "top", *images["tops"], "--mean"]) == 2
    assert "--mean applies to 'analyze side' and 'analyze rim'" in capsys.readouterr().err
    assert main(["analyze", "rim", images["rim"], images["bad"], "--mean", "--json"]) == 2
    cap = capsys.readouterr()
    assert "cannot read image" in _lines(cap.out)[0]["error"]
    assert cap.err.count("alignctl analyze: error:") == 1


def test_unreadable_and_targetless_images_exit_2(images, capsys) -> None:
    rc = main(["analyze", "top", images["bad"], images["blank"], images["tops"][0],
               "missing.png", "--json"])
    cap = capsys.readouterr()
    objs = _lines(cap.out)
    assert rc == 2
    assert [o["file"] for o in objs] == [images["bad"], images["blank"], images["tops"][0],
                                         "missing.png"]
    assert "cannot read image" in objs[0]["error"]
    assert "blank" in objs[1]["error"]
    assert "corners_px" in objs[2]
    assert "no such image" in objs[3]["error"]
    assert cap.err.count("alignctl analyze: error:") == 3
    assert main(["analyze", "side", images["blank"]]) == 2
    assert main(["analyze", "rim", images["blank"]]) == 2


def test_gamma_undoes_a_cameras_tone_curve(tmp_path, capsys) -> None:
    """``--gamma``: a frame from a camera that encodes (light)^(1/2.2) is measured as
    linear light; read as it is, its corners are tenths of a px off."""
    w = posed_world(seed=1)
    opts = RenderOptions(gamma=2.2, blur_sigma_px=1.2)
    p = tmp_path / "top_gamma.png"
    cv2.imwrite(str(p), render_top(w.top_scene(), w.top_camera, opts,
                                   np.random.default_rng(3)))
    truth = np.asarray(top_truth(w.top_scene(), w.top_camera, opts)["corners_px"])
    off = {}
    for gamma in ("1", "2.2"):
        assert main(["analyze", "top", str(p), "--json", "--gamma", gamma]) == 0
        got = np.asarray(_lines(capsys.readouterr().out)[0]["corners_px"])
        off[gamma] = float(np.max(np.abs(got - truth)))
    assert off["1"] > 0.15 and off["2.2"] < 0.03
    assert main(["analyze", "top", str(p), "--gamma", "0.45"]) == 2
    assert "--gamma 0.45: the camera's tone curve is within 1-3" in capsys.readouterr().err


def test_gamma_takes_a_named_curve(tmp_path, capsys) -> None:
    """``--gamma bt709``: a BT.709 camera's frame measured by its curve's name; a name
    that is not a curve is a usage error naming the choices."""
    w = posed_world(seed=1)
    opts = RenderOptions(gamma="bt709", blur_sigma_px=1.2)
    p = tmp_path / "top_bt709.png"
    cv2.imwrite(str(p), render_top(w.top_scene(), w.top_camera, opts,
                                   np.random.default_rng(3)))
    truth = np.asarray(top_truth(w.top_scene(), w.top_camera, opts)["corners_px"])
    assert main(["analyze", "top", str(p), "--json", "--gamma", "BT709"]) == 0
    got = np.asarray(_lines(capsys.readouterr().out)[0]["corners_px"])
    assert float(np.max(np.abs(got - truth))) < 0.03
    with pytest.raises(SystemExit) as exc:
        main(["analyze", "top", str(p), "--gamma", "rec709"])
    assert exc.value.code == 2
    assert "a number (1-3) or srgb or bt709" in capsys.readouterr().err
