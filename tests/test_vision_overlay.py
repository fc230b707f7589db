"""Overlays draw where the measurements are (BGR copies, input untouched)."""

from __future__ import annotations

import numpy as np

from alignd.vision.overlay import draw_centre, draw_paths, draw_rim, draw_side
from alignd.vision.rim import fit_rim
from alignd.vision.side import measure_tilt
from drivers.config import SimWorldConfig
from drivers.sim.render import RenderOptions, posed_world, render_side, render_top


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.any(a != b, axis=2)


def test_paths_and_centre_are_drawn_at_their_positions() -> None:
    img = np.full((200, 300), 128, np.uint8)
    paths = np.array([[[50.0, 50.0], [np.nan, np.nan]], [[60.0, 55.0], [200.0, 150.0]]])
    out = draw_paths(img, paths)
    assert out.shape == (200, 300, 3) and out.dtype == np.uint8
    assert (img == 128).all()  # the input is not drawn on
    ch = _changed(out, np.full_like(out, 128))
    assert ch[48:53, 48:53].any() and ch[148:153, 198:203].any() and not ch[100, 20]
    out = draw_centre(img, (150.25, 100.5), np.diag([0.04, 0.01]), magnify=200.0,
                      bisectors=[((150.0, 100.0), (1.0, 1.0))])
    ch = _changed(out, np.full_like(out, 128))
    assert ch[100, 150] and ch[100, 150 + 70:150 + 90].any()  # 2 sigma x 200 = 80 px
    assert ch[10, 60]  # the bisector through (150, 100) at 45 deg


def test_rim_and_side_overlays() -> None:
    cfg = SimWorldConfig(pixel_size_um=500.0, top_camera_zenith_deg=5.0, axis_px=(640, 360))
    w = posed_world(cfg)
    img = render_top(w.top_scene(), w.top_camera, RenderOptions(), np.random.default_rng(1))
    fit = fit_rim(img)
    out = draw_rim(img, fit)
    x = round(fit.center_px[0] + fit.axes_px[0] * np.cos(np.radians(fit.angle_deg)))
    y = round(fit.center_px[1] + fit.axes_px[0] * np.sin(np.radians(fit.angle_deg)))
    assert _changed(out, np.dstack([img] * 3))[y - 1:y + 2, x - 1:x + 2].any()
    side = render_side(posed_world().side_scene(), RenderOptions(), np.random.default_rng(1))
    m = measure_tilt(side)
    out = draw_side(side, m)
    xs = round(m.pole_edges[0].x_mid_px)
    assert _changed(out, np.dstack([side] * 3))[360, xs - 1:xs + 2].any()
