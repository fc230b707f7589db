"""Rim ellipse, eccentricity, eq. 3.7 (derived) and the plane rectification."""

from __future__ import annotations

import math

import numpy as np
import pytest

from alignd.errors import VisionError
from alignd.vision.rim import (
    PlaneRectifier,
    camera_zenith_from_eccentricity,
    eccentricity_from_zenith,
    fit_ellipse,
    fit_rim,
    fit_rim_frames,
    zenith_from_ellipse,
)
from drivers.config import SimWorldConfig
from drivers.sim.render import RenderOptions, posed_world, render_top, top_truth


def _rim_world(zen: float, seed: int = 1):
    cfg = SimWorldConfig(pixel_size_um=500.0, top_camera_zenith_deg=zen, axis_px=(640.0, 360.0),
                         rim_radius_mm=150.0)
    return posed_world(cfg, seed=seed, turntable_deg=3.0)


@pytest.mark.parametrize("zen", [0.3, 2.0, 7.0, 25.0])
def test_eq_3_7_round_trip_and_far_limit(zen: float) -> None:
    e = eccentricity_from_zenith(zen, 150.0, 800.0)
    assert camera_zenith_from_eccentricity(e, 150.0, 800.0) == pytest.approx(zen, rel=1e-9)
    # a distant camera sees e = sin(theta); nearby, perspective lowers it
    assert eccentricity_from_zenith(zen, 150.0, 1e9) == pytest.approx(
        math.sin(math.radians(zen)), rel=1e-9)
    assert e < math.sin(math.radians(zen))


def test_fit_ellipse_recovers_an_exact_conic() -> None:
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    a, b, ang = 300.0, 200.0, math.radians(25.0)
    x = 640 + a * np.cos(t) * math.cos(ang) - b * np.sin(t) * math.sin(ang)
    y = 360 + a * np.cos(t) * math.sin(ang) + b * np.sin(t) * math.cos(ang)
    k = fit_ellipse(np.column_stack([x, y]))
    f = k[0] * x * x + k[1] * x * y + k[2] * y * y + k[3] * x + k[4] * y + k[5]
    assert np.max(np.abs(f)) / np.abs(k).max() < 1e-9


@pytest.mark.parametrize("e_target", [0.02, 0.08, 0.2])
def test_fit_rim_eccentricity_and_zenith(e_target: float) -> None:
    zen = camera_zenith_from_eccentricity(e_target, 150.0, 800.0)
    w = _rim_world(zen)
    sc, cam = w.top_scene(), w.top_camera
    opts = RenderOptions(gradient=(0.2, 0.1))
    img = render_top(sc, cam, opts, np.random.default_rng(2))
    truth = top_truth(sc, cam, opts)["rim"]
    f = fit_rim(img, 150.0, 800.0)
    assert f.eccentricity == pytest.approx(truth["eccentricity"], abs=0.003)
    assert f.center_px == pytest.approx(truth["center_px"], abs=0.05)
    assert f.axes_px == pytest.approx(truth["axes_px"], abs=0.05)
    assert f.camera_zenith_deg == pytest.approx(zen, abs=0.15 if e_target < 0.05 else 0.05)
    assert f.rms_px < 0.1 and f.n_points >= 100  # edge segments of ~12 px


@pytest.mark.parametrize(("blur", "dark"), [(0.5, False), (1.0, True), (1.5, False), (1.5, True)])
def test_fit_rim_unbiased_under_blur(blur: float, dark: bool) -> None:
    """A clean (noise-free) disc, e = 0.01: the edge profile's width is fitted, so blur does
    not pull the axes (the former 9 px area windows gave +0.27 px and an e error of 0.008
    at 1.5 px); noise-free arcs are not dropped for their tiny, unequal standard errors."""
    import cv2

    from drivers.sim.render import Conic, Raster, coverage
    from drivers.sim.scenes import ellipse_conic
    w, h, a, e = 1280, 720, 200.0, 0.01
    b = a * math.sqrt(1 - e * e)
    floor, disc = (160.0, 60.0) if dark else (60.0, 160.0)
    cov = coverage(Conic(ellipse_conic((640.3, 360.7), a, b, 27.0)),
                   Raster((w, h), float(w), (w / 2, h / 2), 0.0), (0, 0, w, h))
    img = cv2.GaussianBlur((floor + (disc - floor) * cov).astype(np.float32), (0, 0), blur)
    f = fit_rim(img, None, None)
    assert f.eccentricity == pytest.approx(e, abs=0.0005)
    assert f.axes_px == pytest.approx((a, b), abs=0.01)
    assert f.center_px == pytest.approx((640.3, 360.7), abs=0.01)


def test_zenith_from_ellipse_and_rectifier() -> None:
    zen = 9.0
    w = _rim_world(zen)
    sc, cam = w.top_scene(), w.top_camera
    t = top_truth(sc, cam)["rim"]
    z, _rho = zenith_from_ellipse(t["axes_px"][0], t["axes_px"][1], cam.focal_px)
    assert z == pytest.approx(zen, abs=0.02)  # the rim centre wobbles by 2 um
    img = render_top(sc, cam, RenderOptions(), np.random.default_rng(4))
    fit = fit_rim(img, 150.0, 800.0)
    rect = PlaneRectifier.from_rim(fit, cam.focal_px, cam.principal_px, 150.0)
    assert rect.zenith_deg == pytest.approx(zen, abs=0.05)
    assert rect.height_mm == pytest.approx(800.0, rel=0.005)
    plane = np.array([[0.0, 0.0, 0.0], [60.0, 0.0, 0.0], [0.0, 90.0, 0.0], [-70.0, -50.0, 0.0],
                      [110.0, 40.0, 0.0]])
    mm = rect.to_plane_mm(cam.project(plane))
    # rigid up to a turn about the axis: all distances kept (the ellipse bias removed)
    d_true = np.linalg.norm(plane[:, None, :2] - plane[None, :, :2], axis=2)
    d_rect = np.linalg.norm(mm[:, None] - mm[None], axis=2)
    assert np.max(np.abs(d_rect - d_true)) < 0.1
    # the uncorrected image would be off by the foreshortening (several mm here)
    px = cam.project(plane)[:, :2] * 0.5
    d_img = np.linalg.norm(px[:, None] - px[None], axis=2)
    assert np.max(np.abs(d_img - d_true)) > 0.5
    np.testing.assert_allclose(rect.to_image_px(mm), cam.project(plane), atol=1e-6)
    # a raised plane (the holder's top face)
    raised = plane.copy()
    raised[:, 2] = 30.0
    mm30 = rect.to_plane_mm(cam.project(raised), plane_height_mm=30.0)
    d30 = np.linalg.norm(mm30[:, None] - mm30[None], axis=2)
    assert np.max(np.abs(d30 - d_true)) < 0.1


def test_no_rim_raises() -> None:
    with pytest.raises(VisionError):
        fit_rim(np.full((720, 1280), 30, np.uint8))
    img = np.full((720, 1280), 200, np.uint8)
    img[200:500, 300:900] = 60  # a rectangle is not a rim
    with pytest.raises(VisionError):
        fit_rim(img)


def _disc_image(a: float, e: float, centre: tuple[float, float], angle: float,
                floor: np.ndarray | float, disc: float, blur: float,
                size: tuple[int, int] = (1280, 720)) -> np.ndarray:
    """A uniform disc over ``floor`` (exact pixel coverage), defocused; no noise."""
    import cv2

    from drivers.sim.render import Conic, Raster, coverage
    from drivers.sim.scenes import ellipse_conic
    w, h = size
    b = a * math.sqrt(1 - e * e)
    cov = coverage(Conic(ellipse_conic(centre, a, b, angle)),
                   Raster((w, h), float(w), (w / 2, h / 2), 0.0), (0, 0, w, h))
    img = (floor + (disc - floor) * cov).astype(np.float32)
    return cv2.GaussianBlur(img, (0, 0), blur)


def test_fit_rim_unbiased_by_a_floor_sloping_outside_the_disc_only() -> None:
    """A floor whose shading slopes across the rim's edge on the outside only (a textured
    or shaded floor under a flat disc), the slope along the normal varying round the rim as
    cos 2 phi (a saddle): one background slope for both sides of the edge moved each arc's
    edge by ~0.03 px with that pattern, which is e's own (e off by 0.009 here); a slope of
    its own on each side follows it (what is left, 0.0005, is the floor's curvature)."""
    cx, cy, a, e = 640.3, 360.7, 220.0, 0.02
    yy, xx = np.mgrid[0:720, 0:1280].astype(np.float32)
    floor = 150.0 + 0.15 * ((xx - cx) ** 2 - (yy - cy) ** 2) / a  # +-0.3 DN/px at the rim
    img = _disc_image(a, e, (cx, cy), 0.0, floor, 90.0, 1.0)
    f = fit_rim(img, None, None)
    assert f.eccentricity == pytest.approx(e, abs=0.001)
    assert f.axes_px == pytest.approx((a, a * math.sqrt(1 - e * e)), abs=0.005)


@pytest.mark.parametrize("seed", [0, 21])
def test_fit_rim_finds_a_partly_hidden_rim(seed: int) -> None:
    """Seeded corpus scenes (occluded: a holder, cables and a shadow's edge across the
    disc) once refused with "no elliptical rim found" (the best candidate's edge ran along
    51 % and 62 % of it). Seed 0: no threshold level's region follows the rim; the chains
    of edge pixels (Canny) do. Seed 21: the rim's arc is in a contour, but an ellipse
    hugging a cable had more of its points; every arc's ellipse is now a candidate and
    the edge support picks the rim. The fit is right."""
    from drivers.sim.scenes import random_rim_scene
    sc = random_rim_scene(np.random.default_rng(seed), "occluded", size_px=(640, 400))
    f = fit_rim(sc.image, None, None)
    assert f.center_px == pytest.approx(sc.center_px, abs=0.05)
    assert f.axes_px == pytest.approx(sc.axes_px, abs=0.05)
    assert abs(f.eccentricity - sc.eccentricity) <= 3 * f.eccentricity_std


def test_eccentricity_std_matches_the_scatter_over_noisy_frames() -> None:
    """e's reported standard uncertainty agrees with the scatter of e over frames that
    differ only in their noise (small e, where e's noise is largest), and a caller's
    ``max_eccentricity_std`` refuses a frame that cannot support it."""
    rng = np.random.default_rng(3)
    a, e = 120.0, 0.04
    clean = _disc_image(a, e, (240.4, 180.2), 20.0, 140.0, 90.0, 1.0, size=(480, 360))
    errs, stds = [], []
    for _ in range(8):
        img = np.clip(np.rint(clean + rng.normal(0.0, 4.0, clean.shape)), 0, 255)
        f = fit_rim(img.astype(np.uint8), None, None)
        errs.append(f.eccentricity - e)
        stds.append(f.eccentricity_std)
    sd = float(np.sqrt(np.mean(np.square(errs))))
    assert 0.001 < float(np.median(stds)) < 0.01  # noise this high: e is uncertain
    assert 0.6 < sd / float(np.median(stds)) < 1.6
    assert max(abs(x) / s for x, s in zip(errs, stds, strict=True)) < 3.5
    with pytest.raises(VisionError, match="uncertain"):
        fit_rim(img.astype(np.uint8), None, None, max_eccentricity_std=0.1 * min(stds))
    assert fit_rim(img.astype(np.uint8), None, None).to_json()["eccentricity_std"] == (
        pytest.approx(stds[-1]))


def test_the_mean_of_frames_cuts_e_uncertainty_by_their_root_and_stays_right() -> None:
    """The rim pre-check's several frames of one view (the same noise as above): e's
    uncertainty falls by about sqrt(8) and e stays within 3 of it; frames that are not
    one view's, or none, are refused before any fit."""
    rng = np.random.default_rng(4)
    a, e = 120.0, 0.04
    clean = _disc_image(a, e, (240.4, 180.2), 20.0, 140.0, 90.0, 1.0, size=(480, 360))
    frames = [np.clip(np.rint(clean + rng.normal(0.0, 4.0, clean.shape)), 0, 255
                      ).astype(np.uint8) for _ in range(8)]
    one = [fit_rim(f, None, None).eccentricity_std for f in frames]
    mean = fit_rim_frames(frames, None, None)
    assert 2.0 < float(np.median(one)) / mean.eccentricity_std < 4.0  # sqrt(8) = 2.8
    assert abs(mean.eccentricity - e) <= 3 * mean.eccentricity_std
    assert fit_rim_frames(frames[:1], None, None).eccentricity == fit_rim(
        frames[0], None, None).eccentricity
    with pytest.raises(VisionError, match="different sizes"):
        fit_rim_frames([frames[0], frames[1][:-8]], None, None)
    with pytest.raises(VisionError, match="no frame"):
        fit_rim_frames([], None, None)


def test_default_tools_fit_the_rim_on_the_configured_frames() -> None:
    from alignd.config import parse_config
    from alignd.errors import ConfigError
    from alignd.procedures.tools import default_tools
    from drivers.camera import Frame
    from tests.test_vision_scenes import _cfg_data
    rng = np.random.default_rng(5)
    clean = _disc_image(120.0, 0.04, (240.4, 180.2), 20.0, 140.0, 90.0, 1.0, size=(480, 360))
    d = _cfg_data()
    cfg = parse_config(d)
    assert cfg.procedure.precheck.rim_frames == 8
    tools = default_tools(cfg)
    # the pre-check and commissioning's rim item both measure the mean of the frames
    assert tools.rim is not None
    info = tools.rim([Frame(image=np.clip(np.rint(clean + rng.normal(0.0, 2.0, clean.shape)),
                                          0, 255).astype(np.uint8), timestamp=float(k), seq=k)
                      for k in range(3)], None, None)
    assert info.eccentricity_u is not None and 0 < info.eccentricity_u < 0.003
    assert info.eccentricity == pytest.approx(0.04, abs=3 * info.eccentricity_u)
    assert info.zenith_deg is None  # no rim radius or camera height given
    d["procedure"] = {**d.get("procedure", {}), "precheck": {"rim_frames": 0}}
    with pytest.raises(ConfigError, match="rim_frames"):
        parse_config(d)


def test_fit_rim_recovers_from_a_start_pulled_onto_a_cable(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A cable running along the rim just outside it over a sixth of its circumference
    (inside the edge profiles' band), and a coarse ellipse pulled 3-4 px toward it: the
    arcs along the cable are left out (another contrast, a poor step fit) and the fit
    converges on the rim."""
    import cv2

    from alignd.vision import rim
    cx, cy, a, e = 640.3, 360.7, 220.0, 0.05
    b = a * math.sqrt(1 - e * e)
    img = _disc_image(a, e, (cx, cy), 10.0, 170.0, 80.0, 1.0).astype(np.float32)
    t = np.linspace(-0.5, 0.5, 60)
    r = np.deg2rad(10.0)
    u, v = (a + 9) * np.cos(t), (b + 9) * np.sin(t)
    pts = np.column_stack([cx + u * math.cos(r) - v * math.sin(r),
                           cy + u * math.sin(r) + v * math.cos(r)])
    mask = np.zeros(img.shape, np.uint8)
    cv2.polylines(mask, [np.round(pts * 16).astype(np.int32)], False, 255, 5, cv2.LINE_AA, 4)
    img += (40.0 - img) * cv2.GaussianBlur(mask.astype(np.float32) / 255, (0, 0), 0.7)
    start = np.array([cx + 3.0, cy + 0.5, a + 3.5, b, r])
    monkeypatch.setattr(rim, "_coarse_ellipses",
                        lambda gray, mc: [rim._conic_from_params(start)])
    f = fit_rim(np.clip(img, 0, 255).astype(np.uint8), None, None)
    assert f.center_px == pytest.approx((cx, cy), abs=0.05)
    assert f.axes_px == pytest.approx((a, b), abs=0.05)


def test_fit_rim_with_a_disc_that_saturates_inside_the_band() -> None:
    """A bright disc brightening inward that saturates from 7 px inside its edge (the
    corpus' scene #212 of 400 did): inside the +-8-12 px band of the edge profiles every
    arc held saturated pixels and was left out ("traced over only 57 %"); now only
    clipping within 4 px of the edge leaves an arc out, farther clipped pixels just lose
    their weight."""
    import cv2

    from drivers.sim.render import Conic, Raster, coverage
    from drivers.sim.scenes import ellipse_conic
    w, h, cx, cy, a, e = 1280, 720, 640.3, 360.7, 220.0, 0.05
    b = a * math.sqrt(1 - e * e)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    depth = a - np.hypot((xx - cx), (yy - cy) * a / b)  # ~ px inside the edge
    disc = 200.0 + 8.0 * np.clip(depth, 0, None)  # 255 from 7 px in
    cov = coverage(Conic(ellipse_conic((cx, cy), a, b, 0.0)),
                   Raster((w, h), float(w), (w / 2, h / 2), 0.0), (0, 0, w, h))
    img = cv2.GaussianBlur((90.0 + (disc - 90.0) * cov).astype(np.float32), (0, 0), 1.0)
    f = fit_rim(np.clip(np.rint(img), 0, 255).astype(np.uint8), None, None)
    assert f.axes_px == pytest.approx((a, b), abs=0.02)
    assert f.eccentricity == pytest.approx(e, abs=0.001)


def _textured_disc_frames(turn_deg: float, n: int = 8) -> tuple[list[np.ndarray], float]:
    """n frames (2 DN noise each) of a bright disc (a = 250 px, e = 0.025) with a fine
    texture (3 px, 2 DN) that turns by ``turn_deg`` per frame, and the true e."""
    import cv2

    from drivers.sim.scenes import _texture, _turned
    w, h, a, e, ctr, ang = 640, 600, 250.0, 0.025, (320.3, 300.6), 22.0
    b = a * math.sqrt(1 - e * e)
    cov = _disc_cover(ctr, a, b, ang, (w, h))
    rng = np.random.default_rng(4)  # a texture that pulls one frame's e by 3.4 u
    tex = _texture(rng, (h, w), 3.2, 2.0)
    frames = []
    for k in range(n):
        t = _turned(tex, ctr, (a, b), ang, k * turn_deg) if turn_deg else tex
        img = cv2.GaussianBlur(60.0 + (53.0 + t) * cov, (0, 0), 1.05)
        frames.append(np.clip(np.rint(img + rng.normal(0.0, 2.0, img.shape)), 0, 255
                              ).astype(np.uint8))
    return frames, e


def _disc_cover(ctr: tuple[float, float], a: float, b: float, ang: float,
                size: tuple[int, int]) -> np.ndarray:
    from drivers.sim.render import Conic, Raster, coverage
    from drivers.sim.scenes import ellipse_conic
    w, h = size
    return coverage(Conic(ellipse_conic(ctr, a, b, ang)),
                    Raster((w, h), float(w), (w / 2, h / 2), 0.0), (0, 0, w, h)
                    ).astype(np.float32)


def test_a_disc_texture_the_frames_share_stays_in_e_unless_the_turntable_turns() -> None:
    """The corpus' scene #64 in small: a fine disc texture moves each arc's edge by ~0.04
    px (its levels and its edge pixels are textured; no per-arc model separates that from
    the edge without tripling the noise's share), and frames of a still view share it, so
    their mean keeps e 0.005 off (3.4 u). Frames taken with the turntable turned 22.5 deg
    apart (180 deg / 8: the texture's second harmonic round the rim, which is what moves e,
    cancels) carry the texture elsewhere each time while the rim's ellipse stays: their
    mean averages it, and e is within 0.001 and 3 u."""
    still, e = _textured_disc_frames(0.0)
    f = fit_rim_frames(still, None, None)
    assert f.eccentricity - e > 0.004  # the texture's pull, which averaging cannot remove
    turned, _ = _textured_disc_frames(22.5)
    g = fit_rim_frames(turned, None, None)
    assert abs(g.eccentricity - e) < 0.001
    assert abs(g.eccentricity - e) <= 3 * g.eccentricity_std
    assert g.eccentricity_std < f.eccentricity_std


def test_the_robust_mean_of_frames_leaves_out_what_covers_a_pixel_in_few_frames() -> None:
    """A patch over some pixels in 2 of 8 frames (a holder turning with the turntable) is
    left out of them; frames that differ by noise alone (shot noise rising with the level)
    give exactly their plain mean."""
    from alignd.vision.rim import _robust_mean
    rng = np.random.default_rng(6)
    xx = np.mgrid[0:120, 0:160][1]
    clean = 40.0 + 180.0 * (xx / 160.0)  # dark to bright: the noise grows with the level
    frames = [(clean + rng.normal(0.0, 1.0, clean.shape) * np.sqrt(1.0 + clean / 20.0)
               ).astype(np.float32) for _ in range(8)]
    plain = np.stack(frames).mean(axis=0)
    assert np.array_equal(_robust_mean(frames), plain)
    covered = [f.copy() for f in frames]
    covered[0][20:50, 30:70] = 10.0  # a dark holder at one turntable angle ...
    covered[1][30:60, 50:90] = 10.0  # ... and at the next
    r = _robust_mean(covered)
    rest = np.stack(frames[2:]).mean(axis=0)
    assert np.abs(r - rest)[30:50, 50:70].max() < 1e-4  # covered twice: the other 6 frames
    assert np.abs(r - plain)[:, 100:].max() == 0.0  # never covered: untouched


def test_frames_with_a_holder_turning_over_the_rim_are_fitted() -> None:
    """Eight frames 22.5 deg apart of a rim a holder overlaps (it stands on the turntable
    and turns with it): their plain mean smears the holder over the rim and no rim is
    found in it; without what covers a pixel in few frames the rim is measured."""
    from drivers.sim.scenes import random_rim_scene
    sc = random_rim_scene(np.random.default_rng(37), "occluded", frames=8, turn_deg=22.5)
    assert sc.params["occluded"]
    with pytest.raises(VisionError, match="rim"):
        fit_rim(np.stack(sc.frames).mean(axis=0, dtype=np.float32), None, None)
    f = fit_rim_frames(sc.frames, None, None)
    assert abs(f.eccentricity - sc.eccentricity) <= min(0.003, 3 * f.eccentricity_std)


def test_fit_rim_finds_a_dark_disc_crossed_by_a_cable_and_a_shadow() -> None:
    """The corpus' scene #26 of bench seed 2024 (rim seed 2324; the generator's state
    before it, so the test need not draw the 26 scenes before it): a dark disc, a bright
    cable across it and a shadow's edge that makes the floor on one side about as dark.
    No outline at any level nor any Canny chain followed the rim (the best candidate's
    edge support 0.55, "no elliptical rim found") though the true ellipse's is 0.96; a
    circle voted by the gradients (Hough) lands on it."""
    from drivers.sim.scenes import random_rim_scene
    rng = np.random.default_rng()
    rng.bit_generator.state = {
        "bit_generator": "PCG64", "has_uint32": 1, "uinteger": 762999726,
        "state": {"state": 7491133373549638027148934880759949826,
                  "inc": 55807410728343984531942684752446525213}}
    sc = random_rim_scene(rng, "dark disc")
    assert sc.category == "dark disc"
    f = fit_rim(sc.image, None, None)
    assert f.center_px == pytest.approx(sc.center_px, abs=0.3)
    assert max(f.axes_px) == pytest.approx(max(sc.axes_px), abs=0.3)
    assert abs(f.eccentricity - sc.eccentricity) <= 3 * f.eccentricity_std
    assert abs(f.eccentricity - sc.eccentricity) <= 0.003
