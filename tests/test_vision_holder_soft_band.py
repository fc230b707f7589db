"""A soft shadow band beside one side (:func:`drivers.sim.scenes.soft_band_scene`).

A defocused camera (blur 2.2 px) sees a holder's cast shadow as a band 3-5 px wide whose
outer step, blurred by the penumbra as well, is softer than the holder's edge. The band
check (:func:`alignd.vision.holder_bands.side_bands`) fits two steps to such a side, and
before taking the inner one for the holder's edge it asks that the face inside be flat.
It read that face from 1.5 px inside the inner step, where a 2.2 px blur still has a third
of the step to climb: the face read as rough, the band was refused, and the side stayed
between the two steps, 0.86-1.26 px off: three of these four holders had a corner 1.0-1.3
px wrong. The face is now read from beyond the step's blur, and the inner step is placed
again with the outer one's own blur: their corners are 0.33-0.36 px off, what is left
being the long sides' own penumbra (the shadow's edge along them, blurred across them)."""

from __future__ import annotations

import numpy as np
import pytest

from alignd.vision.holder import order_corners, track_holder
from drivers.sim.scenes import soft_band_scene


def _outward_offset(found: np.ndarray, truth: np.ndarray, k: int) -> float:
    """How far outside side ``k`` (corner k to k + 1) of ``truth`` the found side lies,
    the mean over its two corners (px)."""
    t = np.asarray(truth, float)
    f = order_corners(found, t)
    a, b = t[k], t[(k + 1) % 4]
    d = (b - a) / np.linalg.norm(b - a)
    n = np.array([-d[1], d[0]])
    if float(np.dot((a + b) / 2 - t.mean(axis=0), n)) < 0:
        n = -n
    return float((np.dot(f[k] - a, n) + np.dot(f[(k + 1) % 4] - b, n)) / 2)


@pytest.mark.parametrize(("width_px", "angle_deg"),
                         [(5.0, 8.0), (3.0, 8.0), (3.0, 33.0), (4.0, 20.0)])
def test_a_soft_band_moves_the_side_to_the_holders_edge(width_px: float,
                                                        angle_deg: float) -> None:
    """The band side is taken in to the holder's edge: -0.11, 0.09, 0.18 and -0.14 px
    outside it (before 1.26, 0.97, 0.86 and 0.95 px; with the face read deeper but one
    blur for both steps, 0.40, 0.46, 0.47 and 0.41), and the side opposite stays on its
    edge. The first two by the band check; the last two (0.17 and -0.06 px so) by the
    profile fit's penumbra since its fit that crawled along the width's bound is fitted
    again (``profile_fit._CRAWL``), the band check then finding the side on its edge."""
    img, corners = soft_band_scene(width_px, 2.0, angle_deg)
    det = track_holder(img, expected_size_px=(260.0, 160.0))
    assert det.ok, det.reason
    assert abs(_outward_offset(det.corners_px, corners, 1)) < 0.25
    assert abs(_outward_offset(det.corners_px, corners, 3)) < 0.1


@pytest.mark.parametrize("angle_deg", [20.0, -15.0])
def test_a_sharper_shadows_band_is_resolved_at_1_4_blurs(angle_deg: float) -> None:
    """A 3 px band whose shadow is blurred by 1 px only: its two steps lie 1.45 and 1.49
    of their fitted blur apart, under the band check's old 1.5 (``holder_bands._RESOLVED``),
    and the side stayed between them, 1.33-1.34 px off at a stated corner sigma of
    0.03 px (a wrong holder returned as right). Now the band is taken: the side is
    within half a pixel of the holder's edge (0.20 and -0.33 px) and the corners' stated
    sigma grows with the inner step's (0.07 and 0.40 px)."""
    img, corners = soft_band_scene(3.0, 1.0, angle_deg)
    det = track_holder(img, expected_size_px=(260.0, 160.0))
    assert det.ok, det.reason
    assert det.banded_sides == 1
    assert abs(_outward_offset(det.corners_px, corners, 1)) < 0.5
    assert abs(_outward_offset(det.corners_px, corners, 3)) < 0.1
    truth = order_corners(corners)
    err = np.linalg.norm(order_corners(det.corners_px, truth) - truth, axis=1)
    assert float(err.max()) < 1.0


@pytest.mark.parametrize(("angle_deg", "seed"), [(8.0, 0), (33.0, 1)])
def test_a_2_px_band_is_told_by_the_other_sides_blur(angle_deg: float, seed: int) -> None:
    """A 2 px band whose shadow is blurred by 1 px: its steps lie about one blur apart,
    which no fit of two steps of one blur resolves, and the side stayed between them,
    0.93-0.95 px outside the holder's edge at a stated corner sigma of 0.03 px. The other
    three sides give the camera's blur: the band side's inner step held at it and the
    outer one softer (``holder_bands._soft_bands``), the side is 0.12-0.29 px off over 4
    angles and 2 noise seeds (0.29 and 0.12 here), and the stated sigma covers it
    (0.19-0.29 px)."""
    img, corners = soft_band_scene(2.0, 1.0, angle_deg, seed=seed)
    det = track_holder(img, expected_size_px=(260.0, 160.0))
    assert det.ok, det.reason
    assert det.banded_sides == 1
    off = _outward_offset(det.corners_px, corners, 1)
    assert abs(off) < 0.35
    assert det.corner_sigma_px >= abs(off) / 2
    assert abs(_outward_offset(det.corners_px, corners, 3)) < 0.1
