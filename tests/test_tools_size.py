"""The daemon's tracker never takes a rectangle of another size for the holder, and keeps
the image's own corner order whatever frame seeded its search."""

from __future__ import annotations

import numpy as np

from alignd.procedures.tools import Corners, size_checked


def _rect(w: float, h: float, x0: float = 100.0, y0: float = 50.0) -> Corners:
    return Corners(np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]]), True)


def test_a_holder_of_the_expected_size_passes_either_way_round() -> None:
    assert size_checked(_rect(260, 150), (250.0, 156.0)).ok
    assert size_checked(_rect(150, 260), (250.0, 156.0)).ok


def test_a_rectangle_of_another_size_is_refused_with_the_reason() -> None:
    got = size_checked(_rect(190, 150), (250.0, 156.0))  # a sample plate, not the holder
    assert not got.ok
    assert "190 x 150 px" in got.reason and "250 x 156 px" in got.reason
    assert not size_checked(_rect(250, 200), (250.0, 156.0)).ok
