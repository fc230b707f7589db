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
