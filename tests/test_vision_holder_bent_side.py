"""A rectangle larger than the holder, cut to the holder's size by a curved cable, is not
the holder: its side along the cable bends (new corpora returned two such cuts as holders,
298 and 570 px from the holder)."""

from __future__ import annotations

import numpy as np
import pytest

from alignd.errors import VisionError
from alignd.vision.holder import order_corners, track_holder
from drivers.sim.scenes import cable_cut_scene

SIZE = (190.0, 130.0)  # the holder's, which the cut part shares


def test_tracking_seeded_on_the_cut_finds_the_holder_instead() -> None:
    """Seeded on the cut part (a tracker that had followed it), the bent side refuses it
    and the full search that follows returns the holder."""
    img, held, cut = cable_cut_scene(sag_px=2.0)
    det = track_holder(img, expected_size_px=SIZE, hint=cut)
    assert det.ok
    truth = order_corners(held)
    assert np.max(np.linalg.norm(order_corners(det.corners_px, truth) - truth, axis=1)) < 0.05


@pytest.mark.parametrize("sag_px", [1.0, 3.0])
def test_the_cut_alone_is_refused_for_its_bent_side(sag_px: float) -> None:
    """Without the holder in the frame nothing is returned: the cut part's side along the
    cable bends away from a line by 0.2-0.7 px, which the reason names."""
    img, _held, cut = cable_cut_scene(sag_px=sag_px, with_holder=False)
    try:
        det = track_holder(img, expected_size_px=SIZE, hint=cut)
    except VisionError as exc:
        pytest.fail(f"the cut was not measured at all: {exc}")
    assert not det.ok
    assert "bends away from a straight line" in det.reason
