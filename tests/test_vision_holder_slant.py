"""A side taken on another straight edge beyond the holder, at a slant (corpus seed 7100
#477: a dark holder's side on a bright rim ring 13-27 px beyond it, 4.8 deg from parallel
to its opposite, returned 27 px off). The rectangle it makes is straight, of the right
polarity and inside the size tolerance; a label on the holder hides it from the shadow
check, which read the holder's level as the median of its middle: the label's. Opposite
sides that far from parallel are more than a camera passing the rim pre-check makes: the
slanted side is looked for again parallel to its opposite, where the holder's own edge is.
At a slant under 2 deg (a ring 8-16 px beyond) the shadow check finds the holder's edge
inside the side, now that the holder's level is read near its sides, clear of a label."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from alignd.vision.holder import order_corners, track_holder
from drivers.sim.render import Polygon, Raster, coverage

_L, _S = 273.1, 160.9
_FLOOR, _RING, _HOLDER, _LABEL = 95.0, 200.0, 42.0, 110.0


def _scene(angle_deg: float, near: float, far: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, holder corners, the rectangle with one long side on the ring): a dark
    holder with a large light label on a grey floor; a bright ring 4 px wide beyond one
    long side, ``near`` px from it at one end and ``far`` at the other; blur 0.9 px, noise
    1.5 DN."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    region = (0, 0, w, h)
    t = math.radians(angle_deg)
    u, v = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
    ctr = np.array([640.3, 360.2])

    def rect(half_l: float, half_s: float) -> np.ndarray:
        return np.array([ctr - half_l * u - half_s * v, ctr + half_l * u - half_s * v,
                         ctr + half_l * u + half_s * v, ctr - half_l * u + half_s * v])

    held = rect(_L / 2, _S / 2)
    reach = 60.0  # the ring's overhang beyond the corners
    slope = (far - near) / _L
    a, b = held[3] - reach * u, held[2] + reach * u
    da, db = near - slope * reach, far + slope * reach
    ring = np.array([a + da * v, b + db * v, b + (db + 4) * v, a + (da + 4) * v])
    img = np.full((h, w), _FLOOR, np.float32)
    img += (_RING - img) * coverage(Polygon(ring), ras, region)
    img += (_HOLDER - img) * coverage(Polygon(held), ras, region)
    img += (_LABEL - img) * coverage(Polygon(rect(0.3 * _L, 0.25 * _S)), ras, region)
    img = cv2.GaussianBlur(img, (0, 0), 0.9)
    img += np.random.default_rng(1).normal(0.0, 1.5, img.shape).astype(np.float32)
    on_ring = held.copy()
    on_ring[3] += near * v
    on_ring[2] += far * v
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), held, on_ring


def _corner_error(found: np.ndarray, truth: np.ndarray) -> float:
    t = order_corners(truth)
    return float(np.linalg.norm(order_corners(found, t) - t, axis=1).max())


@pytest.mark.parametrize("angle_deg", [9.3, -30.0, 90.0])
@pytest.mark.parametrize(("near", "far"), [(10.0, 22.0), (8.0, 16.0)])  # 2.5, 1.7 deg
def test_a_side_on_a_slanted_edge_beyond_is_not_returned(angle_deg: float, near: float,
                                                         far: float) -> None:
    img, held, on_ring = _scene(angle_deg, near, far)
    # seeded on the rectangle with a side on the ring (as a candidate box was, #477): the
    # fine fit takes the ring's edge; the holder must come back instead
    det = track_holder(img, expected_size_px=(_L, _S), hint=on_ring)
    assert det.ok, det.reason
    assert _corner_error(det.corners_px, held) < 0.1

