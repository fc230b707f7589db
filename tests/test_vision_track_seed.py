"""Tracking from the previous corners: when the fine windows placed on the previous sides
catch every side whole, the coarse side search is skipped and the corners are those a full
search gives; a holder that moved by pixels, or a lens, still gets the coarse search."""

from __future__ import annotations

import numpy as np
import pytest

import alignd.vision.holder as holder
from alignd.vision.edges import Line
from alignd.vision.holder import order_corners, track_holder
from alignd.vision.lens import Lens
from drivers.sim.scenes import TopSceneSample, random_top_scene


@pytest.fixture(scope="module")
def scene() -> TopSceneSample:
    return random_top_scene(np.random.default_rng(21), "plain")


def _count_coarse(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    calls = [0]
    real = holder.coarse_edges_many

    def counted(gray: np.ndarray, segments: list[tuple[np.ndarray, np.ndarray]], *,
                search_px: int = 10, margin_px: float = 12.0, min_step: float = 10.0
                ) -> list[Line | None]:
        calls[0] += 1
        return real(gray, segments, search_px=search_px, margin_px=margin_px,
                    min_step=min_step)

    monkeypatch.setattr(holder, "coarse_edges_many", counted)
    return calls


def test_seeded_tracking_skips_the_coarse_search_and_keeps_the_corners(
        scene: TopSceneSample, monkeypatch: pytest.MonkeyPatch) -> None:
    full = track_holder(scene.image, expected_size_px=scene.expected_size_px)
    assert full.ok
    truth = order_corners(scene.corners_px)
    assert np.max(np.linalg.norm(order_corners(full.corners_px, truth) - truth, axis=1)) < 0.2
    calls = _count_coarse(monkeypatch)
    tracked = track_holder(scene.image, expected_size_px=scene.expected_size_px,
                           hint=full.corners_px)
    assert tracked.ok and calls[0] == 0
    np.testing.assert_allclose(tracked.corners_px, full.corners_px, atol=0.05)


def test_a_holder_that_moved_gets_the_coarse_search(
        scene: TopSceneSample, monkeypatch: pytest.MonkeyPatch) -> None:
    full = track_holder(scene.image, expected_size_px=scene.expected_size_px)
    calls = _count_coarse(monkeypatch)
    moved = track_holder(scene.image, expected_size_px=scene.expected_size_px,
                         hint=full.corners_px + np.array([3.0, -2.0]))
    assert moved.ok and calls[0] >= 1
    np.testing.assert_allclose(order_corners(moved.corners_px, full.corners_px),
                               full.corners_px, atol=0.05)


def test_with_a_lens_the_coarse_search_always_runs(
        scene: TopSceneSample, monkeypatch: pytest.MonkeyPatch) -> None:
    """A distorted side is curved in the frame: windows along the straight segment between
    its corners would sit off it in the middle."""
    full = track_holder(scene.image, expected_size_px=scene.expected_size_px)
    calls = _count_coarse(monkeypatch)
    h, w = scene.image.shape[:2]
    lens = Lens(1.2 * w, (w / 2, h / 2), 1e-9)  # a lens, however slight
    tracked = track_holder(scene.image, expected_size_px=scene.expected_size_px,
                           hint=full.corners_px, lens=lens)
    assert tracked.ok and calls[0] >= 1
