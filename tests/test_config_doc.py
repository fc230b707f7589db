"""The config reference and JSON Schema in docs/ are generated from the models and current;
``alignd --check-config`` validates a file without touching hardware."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from alignd import daemon as daemon_mod
from alignd.config import AligndConfig
from alignd.config_doc import json_schema, reference_markdown

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"


def test_config_reference_is_current() -> None:
    assert (DOCS / "config-reference.md").read_text() == reference_markdown(), (
        "docs/config-reference.md is stale: run `alignd --config-reference > "
        "docs/config-reference.md`")


def test_json_schema_is_current_and_names_every_section() -> None:
    assert (DOCS / "alignd-config.schema.json").read_text() == json_schema(), (
        "docs/alignd-config.schema.json is stale: run `alignd --config-schema > "
        "docs/alignd-config.schema.json`")
    schema = json.loads(json_schema())
    assert set(schema["properties"]) == set(AligndConfig.model_fields)
    assert schema["additionalProperties"] is False  # unknown keys are refused


def test_reference_lists_every_key_with_a_meaning() -> None:
    text = reference_markdown()
    for key in ("`commission.sweep_deg`", "`procedure.turntable_direction`",
                "`controllers[].axes[].soft_limits.min`", "`sim.world.camera_rotation_deg`",
                "`holder.target_mm`"):
        assert key in text, key
    rows = [r for r in text.splitlines() if r.startswith("| `")]
    empty = [r.split("|")[1] for r in rows if r.rstrip().endswith("|  |")]
    assert not empty, f"keys without a meaning: {empty}"
    # bounds and defaults come from the models
    row = next(r for r in rows if r.startswith("| `commission.sweep_deg`"))
    assert "`360.0`" in row and ">= 30" in row and "<= 360" in row and "| deg |" in row


def test_check_config_accepts_the_reference_and_names_a_bad_key(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert daemon_mod.main(["--check-config", str(REPO / "configs" / "sim.yaml")]) == 0
    assert "valid (reference-sim" in capsys.readouterr().out
    for example in sorted((REPO / "configs" / "examples").glob("*.yaml")):
        assert daemon_mod.main(["--check-config", str(example)]) == 0, example
        assert "valid (" in capsys.readouterr().out
    bad = tmp_path / "bad.yaml"
    bad.write_text((REPO / "configs" / "sim.yaml").read_text().replace(
        "  step_deg: 5.0", "  step_deg: 50.0"))
    assert daemon_mod.main(["--check-config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "commission.step_deg" in err and str(bad) in err


def test_check_config_warns_about_missing_ports_without_opening_them(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = (REPO / "configs" / "sim.yaml").read_text().replace(
        "    port: sim                 # 'sim'", "    port: /dev/serial/by-id/usb-none  #", 1)
    f = tmp_path / "real.yaml"
    f.write_text(text)
    assert daemon_mod.main(["--check-config", str(f)]) == 0
    out = capsys.readouterr().out
    assert "controllers.turntable.port /dev/serial/by-id/usb-none does not exist now" in out
