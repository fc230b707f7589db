"""The simulated rig as a whole: alignd-sim serves every device; drivers talk to them."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from alignd.config import load_config
from alignd.hardware import open_rig
from drivers.newport_smc100 import make_axes as smc100_axes

ROOT = Path(__file__).resolve().parent.parent
SIM = ROOT / "configs" / "sim.yaml"


def test_alignd_sim_prints_endpoints_serves_and_stops_on_sigterm() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "drivers.sim.cli", "--config", str(SIM), "--seed", "3",
         "--time-scale", "50"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        lines = [json.loads(proc.stdout.readline()) for _ in range(3)]
        assert [ep["device"] for ep in lines] == ["turntable", "translator", "platform"]
        assert [ep["protocol"] for ep in lines] == ["smc100", "apt", "zaber"]
        assert all(ep["url"].startswith("socket://127.0.0.1:") for ep in lines)
        assert all(ep["pty"].startswith("/dev/pts/") for ep in lines)  # both, by default
        ctl = load_config(SIM).controllers[0].model_copy(update={"port": lines[0]["pty"]})
        (tt,) = smc100_axes(ctl, time_scale=50)
        with tt:
            assert tt.identify().model.startswith("SMC100")
            tt.home()
            assert tt.move_to(5.0) == pytest.approx(5.0, abs=0.001)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=5) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_alignd_sim_bad_config_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("controllers:\n  - name: t\n    protocol: smc100\n    port: sim\n")
    res = subprocess.run([sys.executable, "-m", "drivers.sim.cli", "--config", str(bad)],
                         capture_output=True, text=True, cwd=ROOT, timeout=30)
    assert res.returncode != 0
    assert "controllers.0.axes" in res.stderr


@pytest.mark.parametrize("transport", ["tcp", "pty"])
def test_open_rig_connects_every_simulated_device(transport: str) -> None:
    cfg = load_config(SIM)
    rig = open_rig(cfg, seed=5, transport=transport)
    try:
        ids = rig.connect()
        assert {r: i.model for r, i in ids.items()} == {
            "turntable": "SMC100CC", "translator": "KDC101", "x": ids["x"].model,
            "y": ids["y"].model, "z": ids["z"].model}
        assert "X-LSM" in ids["x"].model or "LSM" in ids["x"].stage
        assert ids["translator"].stage == "MTS25-Z8"
        truth = rig.truth()
        assert 1000 < truth["offset_norm_um"] < 4100  # a few mm of initial misalignment
        frame = rig.cameras["top"].grab(after=time.monotonic())
        assert frame.image.shape == (720, 1280)
    finally:
        rig.close()
