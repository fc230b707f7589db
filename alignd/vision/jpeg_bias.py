"""JPEG's bias on a near-vertical edge's angle, measured by coding the fitted edge again.

JPEG/MJPEG quantises each 8 x 8 block's DCT coefficients. An edge's coding error depends on
where the edge sits in its block column (its phase, x mod 8) and on its levels and blur, so
along a near-vertical edge, which drifts slowly across the block columns, the error in the
edge's position drifts with it: a bias in the angle. A static view repeats that error in
every frame (the sensor noise dithers it only partly), so averaging frames keeps it.

It is measured here by simulation (a parametric bootstrap): the frames' libjpeg quality
is found by coding a frame again at each quality (a decoded frame is the fixed point of
its own quality), the edge as fitted (its per-row levels and slopes, blur and line) is
drawn into the mean frame, sensor noise like the frames' is added, the result is coded at
that quality and the edge fitted again. The angle's shift from the same noisy image
uncoded (paired, so that the noise's own part of the fit cancels) is the bias. Frames
coded with tables other than libjpeg's scaled standard ones are not recognised (no
correction: the tilt is as before).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from alignd.vision.edge_profile import (
    ProfileFit,
    Spread,
    fit_vertical_edge,
    solve_rows,
    step_basis,
)

__all__ = ["EdgeBias", "edge_angle_bias", "jpeg_quality"]

_N = 8  # JPEG's block size
BLUR_STEPS = 2  # corrections of the blur the edge is drawn at (see edge_angle_bias)
BLUR_DRAWS = 4  # simulated coded frames per correction


def jpeg_quality(gray: np.ndarray, qualities: range = range(40, 100)) -> int | None:
    """The libjpeg quality ``gray`` (8-bit DN, the block grid at the origin) was coded at,
    or None when it does not look coded at any of ``qualities``. A decoded frame coded
    again at its own quality comes back almost unchanged (the coefficients are already on
    its lattice); at any other quality it moves. A raw frame moves at every quality, less
    the higher it is."""
    img = np.clip(np.round(np.asarray(gray, np.float64)), 0, 255).astype(np.uint8)
    h, w = img.shape
    img = img[: h - h % _N, : w - w % _N]
    if img.size == 0:
        return None
    d = np.array([float(np.mean(np.abs(_code(img, k).astype(np.float64) - img)))
                  for k in qualities])
    k = int(np.argmin(d))
    near = [d[j] for j in (k - 1, k + 1) if 0 <= j < d.size]
    # coded at quality k: within 0.05 DN of itself and under 0.4 of its neighbours' change
    if d[k] > 0.05 or d[k] > 0.4 * min(near):
        return None
    return int(qualities[k])


def _code(img: np.ndarray, quality: int) -> np.ndarray:
    """``img`` (uint8) through libjpeg at ``quality``."""
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    out = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    if out is None:
        raise RuntimeError("JPEG decoding failed")
    return np.asarray(out)


def _noisy(base: np.ndarray, sd: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return np.clip(np.round(base + sd * rng.standard_normal(base.shape)), 0, 255).astype(
        np.uint8)


@dataclass(frozen=True)
class EdgeBias:
    """The angle's bias from the coding (deg, to subtract) and its standard uncertainty."""

    bias_deg: float
    u_deg: float
    drawn_blur_px: float | None = None  # the blur the edge was drawn at (see edge_angle_bias)


def edge_angle_bias(frames: list[np.ndarray], quality: int, a: float, b: float, y_mid: float,
                    rows: np.ndarray, blur_px: float, spread: Spread, half_width: int,
                    x_limits: tuple[int, int], rng: np.random.Generator,
                    draws: int = 8) -> EdgeBias | None:
    """The coding's bias on the angle of the edge x = a + b (y - y_mid) over ``rows`` of
    ``frames`` (grey, full-frame coordinates, the block grid at the origin), coded at
    libjpeg ``quality``. None when the edge cannot be drawn or fitted again."""
    h, w = np.asarray(frames[0]).shape
    m = 2 * half_width + 1
    rows = np.asarray(rows, int)
    yc = (rows - y_mid).astype(np.float64)
    start = np.round(a + b * yc).astype(int) - half_width
    cols = start[:, None] + np.arange(m)[None, :]
    # the block-aligned region around the windows
    y0, y1 = int(rows.min()) // _N * _N, min(-(-(int(rows.max()) + 1) // _N) * _N, h - h % _N)
    x0 = max(int(cols.min()) - _N, 0) // _N * _N
    x1 = min(-(-(int(cols.max()) + 1 + _N) // _N) * _N, w - w % _N)
    if y1 - y0 < 4 * _N or x1 - x0 < 2 * _N or cols.min() < x0 or cols.max() >= x1:
        return None
    keep = (rows >= y0) & (rows < y1)
    rows, yc, cols = rows[keep] - y0, yc[keep], cols[keep] - x0  # in the region from here
    stack = np.stack([np.asarray(f, np.float64)[y0:y1, x0:x1] for f in frames])
    mean = stack.mean(axis=0)
    # the edge as fitted, its per-row levels and slopes smoothed along it (the mean frame's
    # noise and coding error would otherwise be drawn in)
    u = cols - (a - x0 + b * yc)[:, None]

    def drawn(blur: float) -> np.ndarray:
        """The mean frame with the edge as fitted drawn in at ``blur``."""
        B = step_basis(u, blur, spread)[3]
        coef = solve_rows(B, mean[rows[:, None], cols][..., None])[..., 0]
        k = np.ones(9) / 9.0
        sm = np.stack([np.convolve(np.pad(coef[:, i], 4, mode="edge"), k, mode="valid")
                       for i in range(4)], axis=1)
        out = mean.copy()
        out[rows[:, None], cols] = (B @ sm[..., None])[..., 0]
        return out

    base = drawn(blur_px)
    # the sensor's noise, before the coding: a variance linear in the level, scaled until
    # the simulated frames, coded, vary from draw to draw as much as the real frames do
    # from frame to frame (the coding removes part of the noise, the more the lower the
    # quality; the noise dithers the coding error, so its level sets the bias's size)
    var = stack.var(axis=0, ddof=1)
    lv = mean
    A = np.stack([np.ones(lv.size), lv.ravel()], axis=1)
    cv, *_ = np.linalg.lstsq(A, var.ravel(), rcond=None)
    sd = np.sqrt(np.clip(cv[0] + cv[1] * base, 0.05, None))
    target = float(var.mean())
    if target < 0.01:  # frames that do not differ (one frame sent again) hold no noise level
        return None
    for _ in range(3):
        sim = np.stack([_code(_noisy(base, sd, rng), quality) for _ in range(len(frames))])
        seen = float(sim.astype(np.float64).var(axis=0, ddof=1).mean())
        if seen <= 0.0:
            break
        sd = sd * float(np.clip(math.sqrt(target / seen), 0.5, 3.0))
    lim = (max(x_limits[0], x0) - x0, min(x_limits[1], x1) - x0)

    def fitted(img: np.ndarray, blur: float) -> ProfileFit | None:
        return fit_vertical_edge(img.astype(np.float32), a - x0, b, y_mid - y0, rows,
                                 half_width=half_width, blur0=blur, x_limits=lim,
                                 spread=spread)

    # the coding blurs a faint sharp edge (its fitted blur on the frames was 0.54-0.58 px
    # where the lens gave 0.47): drawn at the blur fitted, the simulated edge is too soft
    # and its coding bias too small. The blur drawn is corrected until the simulated
    # frames, coded, fit to the blur the real ones did
    draw_blur = blur_px
    for _ in range(BLUR_STEPS):
        got = [f.blur_px for _ in range(BLUR_DRAWS)
               if (f := fitted(_code(_noisy(base, sd, rng), quality), draw_blur)) is not None]
        if not got:
            break
        draw_blur = float(np.clip(draw_blur - (np.mean(got) - blur_px), 0.5 * blur_px,
                                  blur_px))
        base = drawn(draw_blur)
    diffs = []
    for _ in range(draws):
        raw = _noisy(base, sd, rng)
        coded = _code(raw, quality)
        fits: list[float] = []
        for img in (coded, raw):
            f = fitted(img, blur_px)
            if f is None:
                break
            fits.append(f.angle_deg)
        if len(fits) == 2:
            diffs.append(fits[0] - fits[1])
    if len(diffs) < max(2, draws // 2):
        return None
    d = np.asarray(diffs)
    return EdgeBias(float(d.mean()), float(d.std(ddof=1) / math.sqrt(d.size)), draw_blur)
