"""Test options: hardware tests run only with ``--hardware-config FILE``."""

from __future__ import annotations

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--hardware-config", default=None, metavar="FILE",
                     help="instrument config of a real rig: enables the hardware tests")
    parser.addoption("--hardware-move", action="store_true",
                     help="hardware tests may also move each axis by a small step")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--hardware-config"):
        return
    skip = pytest.mark.skip(reason="hardware test: pass --hardware-config FILE to run")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def noise_free_scenes(monkeypatch: pytest.MonkeyPatch) -> None:
    """drivers.sim.scenes draws evenly lit, untextured scenes with no noise or compression:
    what is left of an error is the method's own."""
    import numpy as np

    from drivers.sim import scenes

    monkeypatch.setattr(scenes, "_light",
                        lambda rng, shape, **kw: (np.ones(shape, np.float32), {}))
    monkeypatch.setattr(scenes, "_texture",
                        lambda rng, shape, scale, amp: np.zeros(shape, np.float32))
    monkeypatch.setattr(scenes, "_finish", lambda img, rng, **kw: img)
