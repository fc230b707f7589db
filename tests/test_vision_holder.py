"""Holder tracking against the renderer's ground truth (corners, order, pose, yaw, failures)."""

from __future__ import annotations

import numpy as np
import pytest

from alignd.errors import VisionError
from alignd.vision.holder import measure_yaw, order_corners, track_holder
from alignd.vision.lens import Lens
from drivers.config import SimWorldConfig
from drivers.sim.render import PartialShadow, RenderOptions, posed_world, render_top, top_truth

GRAD = (0.2, 0.1)
DARK = RenderOptions(gradient=GRAD)
LIGHT = RenderOptions(gradient=GRAD, holder_dn=200.0, disc_dn=70.0, sample_dn=20.0,
                      background_dn=40.0, rim_dn=150.0)


def _frame(angle: float, opts: RenderOptions, seed: int = 1, yaw: float = 1.3):
    w = posed_world(SimWorldConfig(yaw_deg=yaw), seed=seed, turntable_deg=angle)
    sc, cam = w.top_scene(), w.top_camera
    img = render_top(sc, cam, opts, np.random.default_rng(seed))
    return img, top_truth(sc, cam, opts), w


@pytest.mark.parametrize("opts", [DARK, LIGHT], ids=["dark", "light"])
@pytest.mark.parametrize("angle", [-10.0, 0.0, 6.5, 10.0])
def test_corners_subpixel_both_polarities(opts: RenderOptions, angle: float) -> None:
    img, truth, _ = _frame(angle, opts, yaw=0.0 if angle == 0 else 1.3)
    det = track_holder(img)
    assert det.ok, det.reason
    assert det.polarity == ("dark" if opts is DARK else "light")
    # same order as the scene (TL, TR, BR, BL on screen): consistent over the sweep
    err = det.corners_px - np.asarray(truth["corners_px"])
    assert np.max(np.abs(err)) < 0.06
    assert np.sqrt(np.mean(np.sum(err ** 2, axis=1))) < 0.035
    assert det.center_px == pytest.approx(truth["center_px"], abs=0.03)
    assert det.angle_deg == pytest.approx(truth["angle_deg"], abs=0.01)
    assert 0.8 < det.quality <= 1.0
    assert 0.0 < det.corner_sigma_px < 0.05


def test_partial_shadow_across_the_holder() -> None:
    opts = RenderOptions(gradient=GRAD, shadow=PartialShadow(point_px=(650, 500),
                                                             angle_deg=65, depth=0.35))
    img, truth, _ = _frame(3.0, opts)
    det = track_holder(img)
    assert det.ok
    assert np.max(np.abs(det.corners_px - np.asarray(truth["corners_px"]))) < 0.15


def test_tilted_camera_perspective_quadrilateral() -> None:
    cfg = SimWorldConfig(yaw_deg=1.0, top_camera_zenith_deg=8.0)
    w = posed_world(cfg, seed=3, turntable_deg=-4.0)
    sc, cam = w.top_scene(), w.top_camera
    img = render_top(sc, cam, DARK, np.random.default_rng(3))
    det = track_holder(img)
    assert det.ok
    err = det.corners_px - np.asarray(top_truth(sc, cam, DARK)["corners_px"])
    assert np.max(np.abs(err)) < 0.06


def test_hint_keeps_order_and_result() -> None:
    img, _truth, _ = _frame(2.0, DARK)
    d1 = track_holder(img)
    rolled = np.roll(d1.corners_px, 1, axis=0)
    d2 = track_holder(img, hint=rolled)
    assert d2.ok
    np.testing.assert_allclose(d2.corners_px, rolled, atol=0.02)
    np.testing.assert_allclose(order_corners(rolled[::-1] + 3.0, hint=rolled), rolled + 3.0)
    # a stale hint (the holder moved away from it) falls back to a full search
    d3 = track_holder(img, hint=rolled + 150.0)
    assert d3.ok and d3.polarity == "dark"
    np.testing.assert_allclose(d3.corners_px, rolled, atol=0.02)


def test_expected_size_rejects_a_wrong_target() -> None:
    img, _, _ = _frame(0.0, DARK)
    # 60 x 40 mm at 160 um/px, 30 mm nearer the camera than the turntable (800 mm)
    ok = track_holder(img, expected_size_px=(389.6, 259.7))
    assert ok.ok and ok.size_px[0] == pytest.approx(389.6, abs=0.5)
    with pytest.raises(VisionError, match="no holder found"):
        track_holder(img, expected_size_px=(200.0, 120.0))


@pytest.mark.parametrize("kind", ["blank", "saturated", "noise", "disc_only"])
def test_failures_are_flagged_not_guessed(kind: str) -> None:
    rng = np.random.default_rng(0)
    if kind == "blank":
        img = np.full((720, 1280), 128, np.uint8)
    elif kind == "saturated":
        img = np.full((720, 1280), 255, np.uint8)
        img[:100, :100] = 0
    elif kind == "noise":
        img = np.clip(128 + 40 * rng.standard_normal((720, 1280)), 0, 255).astype(np.uint8)
    else:  # a round target only (no rectangle)
        yy, xx = np.mgrid[0:720, 0:1280]
        img = np.where((xx - 640) ** 2 + (yy - 360) ** 2 < 150 ** 2, 50, 200).astype(np.uint8)
    with pytest.raises(VisionError):
        det = track_holder(img)
        assert not det.ok  # if it returns at all, it must say it failed
        raise VisionError("flagged")


def test_half_hidden_holder_is_not_returned_as_a_point() -> None:
    img, _, _ = _frame(0.0, DARK)
    img = img.copy()
    img[:, 660:] = 190  # the right half of the holder is gone
    try:
        det = track_holder(img, expected_size_px=(389.6, 259.7))
    except VisionError:
        return
    assert not det.ok
    assert np.all(np.isnan(det.corners_px))


@pytest.mark.parametrize("angle", [-8.0, 5.0])
def test_sample_yaw(angle: float) -> None:
    img, _, w = _frame(angle, DARK, seed=5, yaw=1.7)
    det = track_holder(img)
    y = measure_yaw(img, det, turntable_deg=w.turntable_deg())
    assert y.ok and y.side == 0
    # the face is parallel to the holder's front edge; the truth is the world's yaw plus the
    # small mount angle of the stage stack, seen through a 0.5 deg tilted camera
    assert y.yaw_deg == pytest.approx(w.yaw_deg, abs=0.03)
    assert y.offset_px == pytest.approx(5.0 / 0.16, abs=2.0)


def test_lens_distortion_is_straightened() -> None:
    """k1 bends the sides; without the lens model the corners are off by tenths of a pixel."""
    opts = RenderOptions(gradient=GRAD, k1=1.0)
    w = posed_world(SimWorldConfig(yaw_deg=1.0), seed=1, turntable_deg=3.0)
    sc, cam = w.top_scene(), w.top_camera
    img = render_top(sc, cam, opts, np.random.default_rng(1))
    truth = np.asarray(top_truth(sc, cam, opts)["corners_px"])
    plain = track_holder(img)
    assert np.max(np.abs(plain.corners_px - truth)) > 0.15
    det = track_holder(img, lens=Lens(cam.focal_px, cam.principal_px, 1.0))
    assert det.ok
    assert np.max(np.abs(det.corners_px - truth)) < 0.04
    lens = Lens(cam.focal_px, cam.principal_px, 1.0)
    np.testing.assert_allclose(lens.undistort(lens.distort(truth)), truth, atol=1e-8)
