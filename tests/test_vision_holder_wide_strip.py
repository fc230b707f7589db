"""A sample strip wider than the inner-step look (holder_steps.FAR_PX, 24 px) along a side
of a nearly square holder (alignd.vision.holder._wide_strip).

Holder and strip make a rectangle within the size tolerance with its sides' roles swapped:
200 x 182 px with a 26-40 px strip along its long side reads 200 x 208-222, each side under
12 % off the other expected size (corpus seed 91100 #438: a dark holder, a grey sample
41.6 px wide, returned whole, 41.6 px wrong). Before the deeper look, 9 of these 18 frames
were returned ok and 26-40 px wrong; the side whose length is one expected size is now
looked inside as deep as the other puts the holder's side, and the holder measured there.
"""

from __future__ import annotations

import numpy as np
import pytest

from alignd.vision import order_corners, track_holder
from drivers.sim.scenes import sample_beside_scene

SIZE = (200.0, 182.0)


@pytest.mark.parametrize("angle", [12.0, 37.0])
@pytest.mark.parametrize("width", [26.0, 32.0, 40.0])
@pytest.mark.parametrize("levels", [(170.0, 45.0, 80.0), (60.0, 200.0, 150.0),
                                    (60.0, 150.0, 240.0)],
                         ids=["dark holder, grey sample", "light holder, grey sample",
                              "grey holder, white sample on a dark disc"])
def test_a_holder_with_a_wide_strip_along_it_is_found_without_the_strip(
        levels: tuple[float, float, float], width: float, angle: float) -> None:
    img, held = sample_beside_scene(width, angle, levels, seed=int(width + angle),
                                    blur_px=0.6, size_px=SIZE)
    det = track_holder(img, expected_size_px=SIZE)
    assert det.ok, det.reason
    truth = order_corners(held)
    err = np.linalg.norm(order_corners(det.corners_px, truth) - truth, axis=1)
    assert err.max() < 0.1, f"corners {err.round(2)} px off (the strip taken with it?)"
