"""Opt-in checks against a real rig: ``pytest tests/test_hardware.py --hardware-config F``.

Without ``--hardware-move`` nothing moves: each axis is connected, identified and its
status and position read. With it, each homed axis moves by a small step inside its soft
limits and back, verified by read-back.
"""

from __future__ import annotations

import pytest

from alignd.config import load_config
from alignd.hardware import open_rig

pytestmark = pytest.mark.hardware


@pytest.fixture(scope="module")
def rig(request: pytest.FixtureRequest):
    cfg = load_config(request.config.getoption("--hardware-config"))
    r = open_rig(cfg)
    try:
        r.connect()
        yield r
    finally:
        r.stop_all()
        r.close()


def test_every_axis_identifies_and_reports(rig) -> None:
    for role, ax in rig.axes.items():
        ident = rig.identities[role]
        assert ident.model, f"{role}: empty model"
        st = ax.status()
        assert not st.fault, f"{role}: controller reports a fault: {st.messages}"
        lim = ax.config.soft_limits
        if st.homed:
            assert lim.min - 1 <= ax.position() <= lim.max + 1


def test_cameras_deliver_frames(rig) -> None:
    import time

    for role, cam in rig.cameras.items():
        frame = cam.grab(after=time.monotonic())
        assert frame.image.size > 0, f"{role} camera: empty frame"


def test_small_moves_are_verified(rig, request: pytest.FixtureRequest) -> None:
    if not request.config.getoption("--hardware-move"):
        pytest.skip("pass --hardware-move to let the test move the axes")
    for ax in rig.axes.values():
        if not ax.status().homed:
            continue
        here = ax.position()
        lim = ax.config.soft_limits
        step = 0.1 if ax.config.units == "mm" else 0.5
        target = here + step if here + step <= lim.max else here - step
        assert ax.move_to(target) == pytest.approx(target, abs=ax.config.deadband)
        assert ax.move_to(here) == pytest.approx(here, abs=ax.config.deadband)
