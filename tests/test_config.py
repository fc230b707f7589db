"""Config loading: the reference config is valid; bad configs name the file and key."""

from __future__ import annotations

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
    assert cfg.sim is not None and cfg.camera("top").pixel_size_um == 160.0
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
