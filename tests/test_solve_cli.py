"""``alignctl solve``: contract output, table, exit codes and messages."""

from __future__ import annotations

import json

import numpy as np
import pytest

from alignd.cli import EXIT_OK, EXIT_USAGE, main
from alignd.solve import Sweep, sweep_to_json
from alignd.solve.synthetic import make_sweep


@pytest.fixture
def good(tmp_path):
    sw, tr = make_sweep(n_frames=21, miss_fraction=0.05, seed=7)
    p = tmp_path / "good.json"
    p.write_text(json.dumps(sweep_to_json(sw)))
    return p, tr


def test_json_contract(good, capsys) -> None:
    path, tr = good
    assert main(["solve", str(path), "--json"]) == EXIT_OK
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    obj = json.loads(lines[0])
    assert obj["file"] == str(path)
    assert obj["method"] == "rigid"
    assert {"center_px", "cov_px2", "rms_residual_px", "inliers", "outliers",
            "center_um"} <= set(obj)
    err = np.array(obj["center_px"]) - tr.center_px
    assert np.all(np.abs(err) < 4 * np.sqrt(np.diag(obj["cov_px2"])))
    np.testing.assert_allclose(obj["center_um"], np.array(obj["center_px"]) * 160.0)
    frames = json.loads(path.read_text())["frames"]
    detected = sum(f is not None for fr in frames for f in fr["features"])
    assert obj["inliers"] + obj["outliers"] == detected


def test_method_option_and_several_files(good, tmp_path, capsys) -> None:
    path, _ = good
    sw, _ = make_sweep(n_frames=15, seed=8)
    p2 = tmp_path / "nopix.json"
    p2.write_text(json.dumps(sweep_to_json(Sweep(sw.angles_deg, sw.points, None))))
    assert main(["solve", str(path), str(p2), "--method", "circles", "--json"]) == EXIT_OK
    objs = [json.loads(s) for s in capsys.readouterr().out.strip().splitlines()]
    assert [o["file"] for o in objs] == [str(path), str(p2)]
    assert all(o["method"] == "circles" for o in objs)
    assert "center_um" not in objs[1]


def test_table_output(good, capsys) -> None:
    path, _ = good
    assert main(["solve", str(path)]) == EXIT_OK
    out = capsys.readouterr().out
    assert str(path) in out and "rigid" in out and "centre (" in out and " um" in out


@pytest.mark.parametrize("text, fragment", [
    ("{not json", "bad JSON at line 1"),
    ('{"version": 3, "frames": []}', "unsupported version 3"),
    ('{"version": 1, "frames": [{"angle_deg": 0, "features": [[1, 2]]},'
     ' {"angle_deg": 1, "features": [[1, 2], [3, 4]]}]}', "ragged"),
    ('{"version": 1, "frames": [{"angle_deg": NaN, "features": [[1, 2]]}]}', "NaN"),
])
def test_malformed_file_exit_2(tmp_path, capsys, good, text, fragment) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    path, _ = good
    rc = main(["solve", str(bad), str(path), "--json"])
    assert rc == EXIT_USAGE
    cap = capsys.readouterr()
    assert str(bad) in cap.err and fragment in cap.err
    lines = [json.loads(s) for s in cap.out.strip().splitlines()]
    assert lines[0]["file"] == str(bad) and fragment in lines[0]["error"]
    assert lines[1]["file"] == str(path) and "center_px" in lines[1]  # others still solved


def test_degenerate_file_exit_2(tmp_path, capsys) -> None:
    obj = {"version": 1, "frames": [{"angle_deg": a, "features": [[10.0, 20.0]]}
                                    for a in (-1.0, 1.0)]}
    p = tmp_path / "two.json"
    p.write_text(json.dumps(obj))
    assert main(["solve", str(p)]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert str(p) in err and "fewer than 3 usable frames" in err


def test_missing_file_exit_2(tmp_path, capsys) -> None:
    assert main(["solve", str(tmp_path / "nope.json")]) == EXIT_USAGE
    assert "cannot read sweep file" in capsys.readouterr().err
