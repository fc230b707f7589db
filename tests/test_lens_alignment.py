"""A top camera's lens distortion through the whole alignment (``cameras[].lens``).

A webcam's wide lens bends the holder's straight sides and the turntable's circles: the
tracker, fitting straight lines, and the solver, fitting a rigid turn, then place the
target against the centre of rotation by tens of um off, and the run still reports
"aligned" within the tolerance. The simulated world's lens (``sim.world.top_lens_k1``)
draws it: k1 = 2 at the world camera's 5000 px focal length bends the holder as a k1 of
0.08 would at a webcam's 1000 px. Configured, the corners are measured through the lens and
every sweep in the undistorted image; not configured, the corners' paths disagree with one
rigid turn, and the run says it cannot decide.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from alignd.config import AligndConfig, load_config
from alignd.procedures import run_alignment
from alignd.procedures.tools import default_tools
from alignd.report import _in_frame
from alignd.simulated import build_direct_rig
from alignd.vision import Lens
from drivers.config import LensConfig

REPO = Path(__file__).resolve().parents[1]
K1 = 2.0
# the world camera: 800 mm above the turntable at 160 um/px; its principal point is axis_px
WORLD_LENS = LensConfig(focal_px=5000.0, principal_px=(652.3, 347.8), k1=K1)


def _config(lens: LensConfig | None) -> AligndConfig:
    cfg = load_config(REPO / "configs" / "sim.yaml")
    assert cfg.sim is not None
    world = cfg.sim.world.model_copy(update={"top_lens_k1": K1})
    cams = [c.model_copy(update={"lens": lens}) if c.role == "top" else c for c in cfg.cameras]
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"world": world}),
                                  "cameras": cams})


def _aligned_truth_um(cfg: AligndConfig, seed: int) -> float:
    rig, world = build_direct_rig(cfg, seed=seed)
    res = run_alignment(rig, cfg, tools=default_tools(cfg))
    assert res.verdict == "aligned", res.reason
    return float(world.truth()["offset_norm_um"])


@pytest.mark.parametrize("seed", [1, 2])
def test_a_configured_lens_puts_the_target_on_the_axis(seed: int) -> None:
    cfg = _config(WORLD_LENS)
    assert _aligned_truth_um(cfg, seed) <= cfg.procedure.tolerance_um


def test_an_unmodelled_lens_is_not_called_aligned() -> None:
    # what the config key is for: without it the target stays 40-60 um off. The corners'
    # paths then disagree with one rigid turn (each corner bent its own way), the centre
    # fit's uncertainty widens with that (alignd.solve.rigid), and the run, which used to
    # end "aligned" at an offset of 0.7 um, cannot decide and names the likely causes
    cfg = _config(None)
    # (4 sweeps, not 8, to keep the test short: more would not decide either)
    cfg = cfg.model_copy(update={"procedure": cfg.procedure.model_copy(update={"max_sweeps": 4})})
    rig, world = build_direct_rig(cfg, seed=1)
    res = run_alignment(rig, cfg, tools=default_tools(cfg))
    assert world.truth()["offset_norm_um"] > 3 * cfg.procedure.tolerance_um
    assert res.verdict != "aligned", res.reason
    assert "cannot decide" in res.reason
    assert any("a lens not modelled (cameras[].lens)" in w for w in res.details["warnings"])


def test_the_report_draws_undistorted_points_where_the_frame_shows_them() -> None:
    run = {"config": {"cameras": [{"role": "top", "lens": WORLD_LENS.model_dump()},
                                  {"role": "side"}]}}
    p = np.array([[100.0, 80.0], [1200.0, 650.0]])
    want = Lens(5000.0, (652.3, 347.8), K1).distort(p)
    np.testing.assert_allclose(_in_frame(run)(p), want)
    assert float(np.max(np.abs(want - p))) > 1.0  # (the lens moves them visibly there)
    np.testing.assert_allclose(_in_frame({"config": {"cameras": [{"role": "top"}]}})(p), p)


def test_check_config_names_the_lens(capsys: pytest.CaptureFixture[str]) -> None:
    from alignd import daemon as daemon_mod

    assert daemon_mod.main(["--check-config",
                            str(REPO / "configs" / "examples" / "usb-serial-uvc.yaml")]) == 0
    out = capsys.readouterr().out
    assert "(lens: k1 -0.081 at 1012.4 px focal length, straightened)" in out
