"""Config loading: the reference config is valid; bad configs name the file and key."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from alignd.config import config_hash, load_config, parse_config
from alignd.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent
SIM = ROOT / "configs" / "sim.yaml"


def sim_data() -> dict:
    return yaml.safe_load(SIM.read_text())


def test_reference_config_loads() -> None:
    cfg = load_config(SIM)
    assert {a.role for c in cfg.controllers for a in c.axes} == {
        "turntable", "translator", "x", "y", "z"}
    ctl, idx = cfg.axis("turntable")
    assert ctl.protocol == "smc100" and ctl.axes[idx].units == "deg"
    assert cfg.sim is not None and cfg.camera("top").pixel_size_um == 154.0
    assert len(config_hash(cfg)) == 64


def test_hash_changes_with_content() -> None:
    a = parse_config(sim_data())
    data = sim_data()
    data["procedure"]["tolerance_um"] = 5.0
    assert config_hash(a) != config_hash(parse_config(data))


@pytest.mark.parametrize(("mutate", "needle"), [
    (lambda d: d["controllers"][0]["axes"][0].pop("soft_limits"),
     "controllers.0.axes.0.soft_limits: Field required"),
    (lambda d: d["controllers"][0]["axes"][0].update(soft_limits={}),
     "controllers.0.axes.0.soft_limits.min: Field required"),
    (lambda d: d["controllers"][1]["axes"][0].update(soft_limits={"min": 5, "max": 1}),
     "must be below max"),
    (lambda d: d.update(bogus=1), "bogus: Extra inputs are not permitted"),
    (lambda d: d["procedure"].update(tolerance_um=-1), "procedure.tolerance_um"),
    (lambda d: d.pop("sim"), "needs a 'sim:' section"),
    (lambda d: d["controllers"].pop(2), "no axis with role 'x'"),
    (lambda d: d.update(version=2), "version"),
])
def test_bad_config_names_key(tmp_path: Path, mutate, needle: str) -> None:
    data = sim_data()
    mutate(data)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(path) in str(err.value)
    assert needle in str(err.value)


def test_unreadable_and_invalid_yaml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="cannot read config"):
        load_config(tmp_path / "missing.yaml")
    bad = tmp_path / "x.yaml"
    bad.write_text("controllers: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    bad.write_text("- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_config(bad)


# ---- limits the hardware holds us to (issue 9) -------------------------------------------
def _write(tmp_path: Path, data: dict, text_patch: tuple[str, str] | None = None) -> Path:
    text = yaml.safe_dump(data, sort_keys=False)
    if text_patch is not None:
        assert text_patch[0] in text
        text = text.replace(*text_patch)
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    return path


@pytest.mark.parametrize(("mutate", "needles"), [
    # a translator configured 10..70 mm on a 25 mm stage would drive into its limit switch
    (lambda d: d["controllers"][1]["axes"][0].update(soft_limits={"min": 10, "max": 70}),
     ["controllers.1", "translator", "[10, 70] mm", "MTS25-Z8 [0, 25] mm"]),
    (lambda d: d["controllers"][2]["axes"][0].update(soft_limits={"min": -1, "max": 48}),
     ["controllers.2", "(x)", "X-LSM050A [0, 50.8]"]),
    (lambda d: d["controllers"][2]["axes"][1].update(stage="X-LSM9000"),
     ["unknown zaber stage model 'X-LSM9000'", "known: X-LSM025A, X-LSM050A"]),
    (lambda d: d["controllers"][0]["axes"][0].update(stage="URS76BCC"),
     ["unknown smc100 stage model 'URS76BCC'", "known: URS100BCC, URS150BCC, URS75BCC"]),
    (lambda d: d["controllers"][1]["axes"][0].update(stage="X-LSM050A"),
     ["unknown apt stage model 'X-LSM050A' (X-LSM050A is a zaber stage)", "MTS25-Z8"]),
    (lambda d: d["controllers"][1]["axes"][0].update(stage="PRM1-Z8"),
     ["stage PRM1-Z8 moves in deg, the axis is configured in mm"]),
    (lambda d: d["procedure"].update(correction_axes=["x", "x"]),
     ["procedure.correction_axes", "names 'x' twice"]),
])
def test_stage_travel_and_axes_checked_at_load(tmp_path: Path, mutate, needles) -> None:
    data = sim_data()
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    for needle in [str(path), *needles]:
        assert needle in str(err.value)


@pytest.mark.parametrize(("old", "new", "needle"), [
    ("max: 24.5", "max: .inf", "controllers.1.axes.0.soft_limits.max"),
    ("min: 0.5", "min: .nan", "controllers.1.axes.0.soft_limits.min"),
    ("min: -169.0", "min: -.inf", "controllers.0.axes.0.soft_limits.min"),
    ("tolerance_um: 10.0", "tolerance_um: .inf", "procedure.tolerance_um"),
    ("deadband: 0.0005", "deadband: .nan", "controllers.1.axes.0.deadband"),
])
def test_non_finite_limits_and_tolerances_are_rejected(tmp_path: Path, old: str, new: str,
                                                      needle: str) -> None:
    path = _write(tmp_path, sim_data(), (old, new))
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert needle in str(err.value) and "finite" in str(err.value)


def test_unknown_stage_at_daemon_start_is_exit_2_without_traceback(tmp_path: Path) -> None:
    data = sim_data()
    data["controllers"][2]["axes"][2]["stage"] = "X-LSM075A"
    path = _write(tmp_path, data)
    # a subprocess, so that a daemon which wrongly starts is killed by the timeout
    proc = subprocess.run([sys.executable, "-m", "alignd.daemon", "--config", str(path),
                           "--state-dir", str(tmp_path / "state"),
                           "--socket", str(tmp_path / "s.sock")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert "unknown zaber stage model 'X-LSM075A'" in proc.stderr
    assert "X-LSM200A" in proc.stderr
    assert "Traceback" not in proc.stderr and not (tmp_path / "state").exists()
