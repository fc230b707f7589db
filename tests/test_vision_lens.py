"""Radial lens distortion (alignd.vision.lens): undistort inverts distort over the whole
frame, for either sign of k1, and the principal point stays where it is (undistort solves
the radius by Newton's method, which divides by it)."""

from __future__ import annotations

import numpy as np
import pytest

from alignd.vision.lens import Lens


@pytest.mark.parametrize("k1", [-0.12, 0.03, 0.12, 1.0])
def test_undistort_inverts_distort_over_the_frame(k1: float) -> None:
    lens = Lens(1000.0, (640.0, 360.0), k1)
    yy, xx = np.mgrid[0:721:16, 0:1281:16]
    ideal = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    frame = lens.distort(ideal)
    assert np.max(np.abs(frame - ideal)) > 1.0  # the lens does bend the frame
    np.testing.assert_allclose(lens.undistort(frame), ideal, atol=1e-9)


def test_the_principal_point_and_an_empty_set() -> None:
    lens = Lens(1000.0, (640.0, 360.0), 0.12)
    np.testing.assert_array_equal(lens.undistort(np.array([[640.0, 360.0]])), [[640.0, 360.0]])
    assert lens.undistort(np.empty((0, 2))).shape == (0, 2)


def test_the_holders_remembered_undistortions_are_never_another_sets() -> None:
    """The top camera undistorts a frame's sides once each and remembers them by identity
    (alignd.vision.holder._ideal): the same crossings through another lens, other crossings
    (many more than it keeps, every one a new object), and each set again after the memo
    has moved on are undistorted as if for the first time."""
    from alignd.vision.edges import EdgePoints
    from alignd.vision.holder import _IDEAL_KEPT, _ideal

    rng = np.random.default_rng(5)
    a, b = Lens(1000.0, (640.0, 360.0), 0.12), Lens(1000.0, (640.0, 360.0), -0.12)
    sets = [EdgePoints(rng.uniform(0, 720, (50, 2)), np.ones(50), False)
            for _ in range(3 * _IDEAL_KEPT)]
    for pts in sets:
        for lens in (a, b):
            np.testing.assert_array_equal(_ideal(pts, lens).xy, lens.undistort(pts.xy))
    first = sets[0]
    assert _ideal(first, a) is _ideal(first, a)  # remembered while it is among the last
    np.testing.assert_array_equal(_ideal(sets[1], a).xy, a.undistort(sets[1].xy))
    assert _ideal(first, None) is first
