"""The daemon's tracker never takes a rectangle of another size for the holder, and keeps
the image's own corner order whatever frame seeded its search."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_the_seeded_search_keeps_the_images_corner_order(monkeypatch: pytest.MonkeyPatch) -> None:
    """The vision orders corners nearest to its seed; a seed from the end of the previous
    sweep (far away in angle) would rotate every label of the next one, so the daemon's
    tracker returns the image's own order (top-left first)."""
    from dataclasses import dataclass

    import alignd.vision as vision
    from alignd.config import load_config
    from alignd.procedures.tools import default_tools
    from drivers.camera import Frame

    box = np.array([[100.0, 50.0], [350.0, 50.0], [350.0, 206.0], [100.0, 206.0]])

    @dataclass
    class Det:
        corners_px: np.ndarray
        ok: bool = True
        quality: float = 1.0
        reason: str = ""
        warning: str = ""
        faint: bool = False

    seeds = []

    def track_holder(gray: np.ndarray, hint: np.ndarray | None = None, **_: object) -> Det:
        seeds.append(hint)
        return Det(np.roll(box, len(seeds), axis=0))  # a different labelling each call

    monkeypatch.setattr(vision, "track_holder", track_holder)
    tools = default_tools(load_config("configs/sim.yaml"))
    frame = Frame(np.zeros((300, 400), np.uint8), 0.0, 1)
    first, second = tools.track(frame), tools.track(frame)
    assert first.ok and second.ok
    assert np.array_equal(first.corners_px, vision.order_corners(box))
    assert np.array_equal(second.corners_px, first.corners_px)
    assert seeds[0] is None and seeds[1] is not None  # the first frame seeded the second
