"""The daemon's tracker over a wide sweep's steps (+-45 deg in 4.5 deg steps, as a wide
sweep turns): the previous frame's corners are then some 12 px from the holder, beyond the
+-10 px side search's comfort. Its corners must still be the full search's: a side
measured in windows off-centre once straddled the sample strip's edge and skewed a corner
by up to 2 px, which made ``make demo`` end "the centre moved between sweeps"."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from alignd.config import load_config
from alignd.procedures.tools import SIZE_TOLERANCE, default_tools, expected_holder_px
from alignd.simulated import build_direct_rig
from alignd.vision import order_corners, track_holder

REPO = Path(__file__).resolve().parents[1]


def test_tracked_corners_over_wide_steps_are_the_full_searchs() -> None:
    cfg = load_config(REPO / "configs" / "sim.yaml")
    rig, _world = build_direct_rig(cfg, seed=1)
    rig.connect()
    tt, top = rig.axis("turntable"), rig.camera("top")
    assert top is not None
    tools = default_tools(cfg)
    worst = 0.0
    for angle in np.linspace(-45.0, 45.0, 21):
        tt.move_to(float(angle))
        frame = top.grab()
        got = tools.track(frame)
        free = track_holder(frame.gray, expected_size_px=expected_holder_px(cfg),
                            size_tolerance=SIZE_TOLERANCE)
        assert got.ok and free.ok, (got.reason, free.reason)
        full = order_corners(free.corners_px)
        worst = max(worst, max(float(np.min(np.hypot(*(full - p).T)))
                               for p in np.asarray(got.corners_px)))
    assert worst < 0.05, f"tracked corners {worst:.2f} px from the full search's"
