"""A strip passing under the holder (issue 11, corpus #890 of seed 71100 at 800 x 600).

The strip's top end, its sides above the holder and a label's lower edge on the holder
framed a quadrilateral of the holder's size, returned ok 233 px off. Two of its sides
are the strip's edges, seen beside the holder only: over their other end the image does
not step across them, and what lies just inside is the holder's face, not the strip.
(A side hidden at one end by a floor hole as dark as the holder keeps the holder's face
inside all along: ``tests/test_vision_holder_hole.py`` finds those.)"""

from __future__ import annotations

import numpy as np

from alignd.vision.holder import track_holder
from drivers.sim.scenes import strip_under_scene


def test_a_strip_framed_by_a_label_is_not_the_holder() -> None:
    img, _held, quad = strip_under_scene()
    for shift in ([0.0, 0.0], [1.5, -1.0]):
        # seeded on the quadrilateral, as tracking would be after a wrong frame
        det = track_holder(img, expected_size_px=(347.0, 195.0), hint=quad + shift)
        assert not det.ok
        assert "short of a corner" in det.reason and "passing under" in det.reason


def test_the_search_returns_no_wrong_holder_there() -> None:
    img, held, _quad = strip_under_scene()
    det = track_holder(img, expected_size_px=(347.0, 195.0))
    # the holder itself has sides of both polarities (the strip above and below it)
    assert not det.ok or float(np.abs(det.center_px - held.mean(axis=0)).max()) < 1.0
