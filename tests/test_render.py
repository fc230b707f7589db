"""Renderer: exact pixel-area coverage, truth geometry, the camera model and the sensor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from alignd.vision.rim import eccentricity_from_zenith
from drivers.config import SimWorldConfig
from drivers.sim.render import (
    RenderOptions,
    distort_points,
    posed_world,
    render_side,
    render_top,
    side_truth,
    top_truth,
    undistort_points,
)

EXACT = dict(read_noise_dn=0.0, blur_sigma_px=0.0, quantize=False, gradient=(0.0, 0.0))


def _shoelace(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


@pytest.mark.parametrize("angle", [0.0, 3.7, -10.0])
def test_holder_coverage_sums_to_its_area(angle: float) -> None:
    """Sum of coverage = polygon area to 1e-3 px^2: edges are drawn exactly, not aliased."""
    w = posed_world(SimWorldConfig(yaw_deg=0.0 if angle == 0 else 1.3), seed=2,
                    turntable_deg=angle)
    sc, cam = w.top_scene(), w.top_camera
    opts = RenderOptions(**EXACT, background_dn=100.0, disc_dn=100.0, rim_dn=100.0,
                         holder_dn=200.0, sample_dn=100.0)
    img = render_top(sc, cam, opts)
    assert img.dtype == np.float32
    area = float((img.astype(np.float64) - 100.0).sum() / 100.0)
    truth = top_truth(sc, cam, opts)
    assert area == pytest.approx(_shoelace(np.asarray(truth["corners_px"])), abs=2e-3)


def test_column_sums_locate_a_horizontal_edge_exactly() -> None:
    """Per column, the summed coverage equals the edge's crossing (to 1e-4 px)."""
    w = posed_world(SimWorldConfig(yaw_deg=0.0), seed=4, turntable_deg=2.0)
    sc, cam = w.top_scene(), w.top_camera
    opts = RenderOptions(**EXACT, background_dn=0.0, disc_dn=0.0, rim_dn=0.0, holder_dn=1.0,
                         sample_dn=1.0)
    img = render_top(sc, cam, opts).astype(np.float64)
    c = np.asarray(top_truth(sc, cam, opts)["corners_px"])
    # bottom edge (corners 3 -> 2): in a middle column the filled part ends at the edge
    x = round((c[2, 0] + c[3, 0]) / 2)
    y_edge = c[3, 1] + (x - c[3, 0]) * (c[2, 1] - c[3, 1]) / (c[2, 0] - c[3, 0])
    col = img[:, x]
    top = math.floor(y_edge) - 40
    # from a row well inside the holder down: sum of coverage = y_edge - (top - 0.5)
    assert col[top:].sum() == pytest.approx(y_edge - (top - 0.5), abs=1e-4)


def test_rim_ellipse_matches_the_derived_eccentricity() -> None:
    """The renderer's projected rim and the closed-form eq. 3.7 agree (independent paths)."""
    for zen in (0.5, 4.0, 11.0):
        cfg = SimWorldConfig(pixel_size_um=500.0, top_camera_zenith_deg=zen, axis_px=(640, 360),
                             wobble_um=0.0)
        w = posed_world(cfg)
        t = top_truth(w.top_scene(), w.top_camera)
        e = t["rim"]["eccentricity"]  # type: ignore[index]
        assert e == pytest.approx(eccentricity_from_zenith(zen, 150.0, 800.0), rel=1e-6)


def test_distortion_round_trip_and_direction() -> None:
    cam = posed_world().top_camera
    pts = np.array([[100.0, 50.0], [652.3, 347.8], [1200.0, 700.0]])
    d = distort_points(pts, cam, k1=0.5)
    np.testing.assert_allclose(undistort_points(d, cam, 0.5), pts, atol=1e-6)
    # barrel/pincushion moves points radially, the principal point stays put
    np.testing.assert_allclose(d[1], pts[1], atol=1e-9)
    r0 = np.linalg.norm(pts[0] - pts[1])
    assert np.linalg.norm(d[0] - d[1]) > r0


def test_truth_corners_follow_distortion() -> None:
    w = posed_world(seed=1, turntable_deg=5.0)
    sc, cam = w.top_scene(), w.top_camera
    plain = np.asarray(top_truth(sc, cam, RenderOptions())["corners_px"])
    bent = np.asarray(top_truth(sc, cam, RenderOptions(k1=1.0))["corners_px"])
    np.testing.assert_allclose(bent, distort_points(plain, cam, 1.0), atol=1e-9)
    assert np.max(np.abs(bent - plain)) > 0.5


def test_noise_level_and_quantisation() -> None:
    w = posed_world(seed=1)
    img = render_top(w.top_scene(), w.top_camera, RenderOptions(read_noise_dn=2.0),
                     np.random.default_rng(3))
    assert img.dtype == np.uint8 and img.shape == (720, 1280)
    patch = img[20:120, 20:220].astype(float)  # flat turntable, far from the holder
    assert patch.std() == pytest.approx(2.0, abs=0.15)
    assert patch.mean() == pytest.approx(190.0, abs=0.5)


def test_gradient_and_shadow_change_the_light() -> None:
    w = posed_world(seed=1)
    sc, cam = w.top_scene(), w.top_camera
    flat = render_top(sc, cam, RenderOptions(**EXACT))
    grad = render_top(sc, cam, RenderOptions(**{**EXACT, "gradient": (0.2, 0.0)}))
    # +-10 % at the left and right borders
    assert grad[10, 2] / flat[10, 2] == pytest.approx(0.9, abs=0.005)
    assert grad[10, 1277] / flat[10, 1277] == pytest.approx(1.1, abs=0.005)


def test_side_view_truth_and_pole_width() -> None:
    w = posed_world(SimWorldConfig(tilt_deg=0.4), seed=1)
    sc = w.side_scene()
    opts = RenderOptions(**EXACT, side_roll_deg=0.5, side_background_dn=0.0, pole_dn=1.0,
                         side_sample_dn=0.0)
    img = render_side(sc, opts).astype(np.float64)
    t = side_truth(sc, opts)
    assert t["tilt_deg"] == pytest.approx(0.4)
    assert t["pole_angle_deg"] == pytest.approx(0.5)
    # a row crosses the rolled pole over diameter / cos(roll) px of coverage
    width = opts.pole_diameter_mm / (opts.side_pixel_size_um / 1000.0)
    assert img[360].sum() == pytest.approx(width / math.cos(math.radians(0.5)), abs=1e-3)
