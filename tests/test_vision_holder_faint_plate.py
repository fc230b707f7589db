"""A sample plate beside a light holder, a little darker than it (corpus seed 9100 #291: 25
DN under the holder on a 130 DN step to the floor, 13.5 px wide): holder and plate read
as one light rectangle 5 % too wide, inside the size tolerance, and it was returned ok,
13.5 px wrong at two corners. Its band just inside the found side differs from the
holder's level by 0.18 of the side's step, under the 0.2 a shadow band needs; but the
plate's inner edge is as sharp as a side and well inside it, which shading and a side's
own transition are not. And square to the pixel grid (90 deg), the holder's two sizes
pair at different scales (the plate makes one 5 % long), its sides vote along one midline
only, and the six voted boxes, all somewhere along it, used up the candidates before the
threshold ladder's box (the outline) was tried: not found at all."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from alignd.vision.holder import order_corners, track_holder
from alignd.vision.holder_steps import inner_step
from drivers.sim.render import Polygon, Raster, coverage

_L, _S, _PLATE = 318.4, 280.0, 13.5
_FLOOR, _HOLDER = 40.0, 200.0


def _scene(angle_deg: float, plate: float, blur: float = 0.6
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image, holder corners, holder + plate corners): the plate at ``plate`` DN along a
    long side; blur ``blur`` px, noise 1.5 DN."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    region = (0, 0, w, h)
    t = math.radians(angle_deg)
    u, v = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
    ctr = np.array([640.3, 360.2])
    held = np.array([ctr - _L / 2 * u - _S / 2 * v, ctr + _L / 2 * u - _S / 2 * v,
                     ctr + _L / 2 * u + _S / 2 * v, ctr - _L / 2 * u + _S / 2 * v])
    wide = held.copy()
    wide[2:] += _PLATE * v
    strip = np.array([held[3], held[2], wide[2], wide[3]])
    ch = coverage(Polygon(held), ras, region)
    cs = coverage(Polygon(strip), ras, region)
    img = (_FLOOR * np.clip(1.0 - ch - cs, 0.0, 1.0) + _HOLDER * ch + plate * cs
           ).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), blur)
    img += np.random.default_rng(3).normal(0.0, 1.5, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), held, wide


def _corner_error(found: np.ndarray, truth: np.ndarray) -> float:
    t = order_corners(truth)
    return float(np.linalg.norm(order_corners(found, t) - t, axis=1).max())


@pytest.mark.parametrize("angle_deg", [-6.5, 20.0, 90.0])
@pytest.mark.parametrize("plate", [178.0, 184.0])
def test_a_faint_plate_beside_the_holder_is_not_taken_for_it(angle_deg: float,
                                                             plate: float) -> None:
    img, held, wide = _scene(angle_deg, plate)
    step = inner_step(img, order_corners(wide))
    assert step is not None and step.ratio < 0.2  # under the shadow band's threshold
    assert abs(step.depth_px - _PLATE) < 1.5
    for hint in (None, wide):  # a full search, and tracking seeded on holder + plate
        det = track_holder(img, expected_size_px=(_L, _S), hint=hint)
        assert det.ok, det.reason
        assert _corner_error(det.corners_px, held) < 0.1


def test_the_holder_alone_has_no_inner_edge() -> None:
    """Its own soft transition (blur 1.5 px) is 3-5 px deep and not flagged."""
    img, held, _wide = _scene(20.0, _FLOOR, blur=1.5)
    assert inner_step(img, order_corners(held)) is None
