"""A lens out of focus blurs by a disc, not a Gaussian (:func:`disc_defocus_scene`).

A disc's edge ends abruptly a radius out on either side, where a Gaussian's tails go on.
Two Gaussian steps a radius apart fit it far better than one: the neighbour look took
every side for a step with a second one 3.2 px beside it and measured the sides again
1.5 px off; the band check took a side for one between two steps and moved it in. Both
now ask whether one edge defocused by a disc fits nearly as well
(:func:`alignd.vision.holder_bands.one_disc_edge`)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from alignd.vision.holder import order_corners, track_holder
from alignd.vision.profile_fit import disc_edge
from drivers.sim.scenes import disc_defocus_scene, disc_kernel, random_top_scene


def test_a_disc_edge_is_what_the_disc_kernel_draws() -> None:
    """The model against the scenes' own kernel: a vertical edge at x = 100.3 px covering
    the pixels right of it, blurred by a 3 px disc; each pixel (its centre 0.5 px in)
    within 1 % of the step of :func:`disc_edge` with a pixel's footprint, and flat a
    radius and a pixel beyond the edge (a Gaussian of the same spread is not)."""
    x = np.arange(200, dtype=float) + 0.5
    row = np.clip(x + 0.5 - 100.3, 0.0, 1.0).astype(np.float32)
    img = cv2.filter2D(np.repeat(row[None, :], 40, axis=0), -1, disc_kernel(3.0))[20]
    model = disc_edge(x - 100.3, 3.0, np.array([1.0, 0.0]))
    assert float(np.max(np.abs(img - model))) < 0.01
    assert float(model[int(100.3 + 4.5)]) == pytest.approx(1.0, abs=1e-9)
    assert float(model[int(100.3 - 4.5)]) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(("radius_px", "angle_deg", "levels", "gauss_px", "seed"), [
    (4.0, 8.0, (200.0, 60.0), 0.0, 3),
    (4.0, 33.0, (200.0, 60.0), 0.0, 3),
    (5.0, 3.0, (60.0, 180.0), 0.0, 3),
    (5.0, 33.0, (200.0, 60.0), 0.5, 3),
])
def test_a_holder_through_a_lens_out_of_focus(radius_px: float, angle_deg: float,
                                              levels: tuple[float, float],
                                              gauss_px: float, seed: int) -> None:
    """Found within 0.1 px (measured 0.007, 0.012, 0.030 and 0.014 px; before 2.1, 2.2 and
    2.8 px wrong at a stated sigma of 0.03 px, and refused: "a second step")."""
    img, corners = disc_defocus_scene(radius_px, angle_deg, seed=seed, levels=levels,
                                      gauss_px=gauss_px)
    det = track_holder(img, expected_size_px=(260.0, 160.0))
    assert det.ok, det.reason
    t = order_corners(corners)
    assert float(np.max(np.linalg.norm(order_corners(det.corners_px, t) - t, axis=1))) < 0.1


@pytest.mark.parametrize(("levels", "gauss_px", "seed"), [
    ((60.0, 180.0), 0.0, 31),
    ((200.0, 60.0), 0.5, 30),
])
def test_a_disc_edge_is_not_a_penumbra(levels: tuple[float, float], gauss_px: float,
                                       seed: int) -> None:
    """A 5 px disc at 45 deg (the bench's "lens out of focus" frames 31 and 30): a
    penumbra fitted with the edge, held at its least width, took up the disc edge's
    shoulders and moved a side 0.58 and 0.67 px at a stated corner sigma of 0.03 px
    (on one machine; on another the fit did not converge there). Now a fit that stays at
    the least width is refused (``profile_fit._CRAWL``): within 0.1 px."""
    img, corners = disc_defocus_scene(5.0, 45.0, seed=seed, levels=levels, gauss_px=gauss_px)
    det = track_holder(img, expected_size_px=(260.0, 160.0))
    assert det.ok, det.reason
    t = order_corners(corners)
    assert float(np.max(np.linalg.norm(order_corners(det.corners_px, t) - t, axis=1))) < 0.1


# the random generator's state just before corpus scenes #90 and #846 of seed 2124 (the
# bench's; "everything", JPEG q 63 and 60), so that each is drawn alone
_SCENES_2124 = {
    90: {"bit_generator": "PCG64",
         "state": {"state": 89400527125577535804558165491398507867,
                   "inc": 274125618534547784574732873802860556589},
         "has_uint32": 0, "uinteger": 3082717886},
    846: {"bit_generator": "PCG64",
          "state": {"state": 301216331106076794964491110504441000303,
                    "inc": 274125618534547784574732873802860556589},
          "has_uint32": 0, "uinteger": 3795401661},
}


@pytest.mark.parametrize("index", sorted(_SCENES_2124))
def test_a_corpus_scene_through_a_lens_out_of_focus(index: int) -> None:
    """The bench corpus's scenes #90 and #846 blurred by a disc (``defocus="disc"``): the
    band check read a side's edge as two steps 2-3 px apart and moved it in to the inner
    one, 1.09 and 1.52 px wrong at a stated sigma of 0.07-0.09 px; now within 0.2 px."""
    rng = np.random.default_rng()
    rng.bit_generator.state = _SCENES_2124[index]
    sc = random_top_scene(rng, "everything", (1280, 720), defocus="disc")
    det = track_holder(sc.image, expected_size_px=sc.expected_size_px)
    assert det.ok, det.reason
    t = order_corners(sc.corners_px)
    assert float(np.max(np.linalg.norm(order_corners(det.corners_px, t) - t, axis=1))) < 0.2
