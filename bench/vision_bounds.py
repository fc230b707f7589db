"""Cramer-Rao bounds of what the vision measures: how well any unbiased estimator could
do from the pixels, given the sensor's noise, on the bench's corpus.

    python bench/vision_bounds.py                 # top corners and side tilt
    python bench/vision_bounds.py --only top      # the top corpus (1001 scenes)
    python bench/vision_bounds.py --only side --side-scenes 60
    python bench/vision_bounds.py --quick         # CI-sized (42 top scenes, 10 side views)

Top: a frame's holder corners. The model is the one the profile fit assumes, with the
nuisances it leaves free: four straight sides (a camera that may look obliquely), each
column across a side with its own level and step height (textures, gradients), the blur
and the illumination slopes known, white noise of the scene's own variance (read noise and
shot noise). Columns reach to the corners, the neighbouring side's blurred step modelled,
so the bound is what an estimator that also used the corner regions could reach. Beside
it, the bound of a rectangle: the four sides turned as one, which the fit uses where their
directions agree with it (:mod:`alignd.vision.holder_square`). It covers the corpus's
uncompressed frames without lens distortion (a curved side has no straight-line bound in
frame pixels) and compares
the corner RMS error of :func:`alignd.vision.holder.track_holder` on the same frames
(noise and bias) with the bound (noise only).

Side: one frame's tilt (sample edge against the pole's two edges), each row's level and
step height free, and either each row's illumination slopes free as well (what the side
fit leaves free, :mod:`alignd.vision.edge_profile`) or known; against the scatter of one
frame's tilt over the frames of each raw (not JPEG) view, with regions. docs/vision.md,
"How far from the bound", reads both.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Literal  # noqa: E402

import numpy as np  # noqa: E402
from scipy.special import ndtr  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from alignd.errors import VisionError  # noqa: E402
from alignd.vision.edges import as_gray  # noqa: E402
from alignd.vision.holder import order_corners, track_holder  # noqa: E402
from alignd.vision.side import SideEdge, SideMeasurement, measure_tilt_frames  # noqa: E402
from drivers.sim.scenes import (  # noqa: E402
    SIDE_CATEGORIES,
    TOP_CATEGORIES,
    random_side_scene,
    random_top_scene,
)

_SQRT_2PI = math.sqrt(2.0 * math.pi)


def pixel_variance(gray: np.ndarray, read_noise_dn: float, electrons_per_dn: float,
                   full_scale: float = 255.0) -> np.ndarray:
    """Each pixel's noise variance (8-bit DN^2): read noise, shot noise (the frame's own
    value stands for its mean: the shot term is linear in it, so the sum over a window is
    unbiased) and the quantisation of a ``full_scale`` sensor."""
    q = 255.0 / full_scale
    return read_noise_dn ** 2 + np.clip(gray, 0.0, None) / electrons_per_dn + q * q / 12.0


def _spread(blur_px: float) -> float:
    """A blurred step's width across a pixel grid: the blur and the pixel's footprint."""
    return math.sqrt(blur_px ** 2 + 1.0 / 12.0)


def _crossing_information(d: np.ndarray, values: np.ndarray, var: np.ndarray, se: float,
                          factor: np.ndarray | float = 1.0, free_slopes: bool = False
                          ) -> float:
    """The Fisher information on an edge's crossing from one window across it: the
    pixels at signed distances ``d`` (px, positive on the edge's far side), their values
    and noise variances, a step of width ``se`` (times ``factor``: a neighbouring edge's
    step); the window's level and step height (with ``free_slopes`` also a slope on
    either side) profiled out. The step height is read from the tails' medians; 0 where
    the window has no tail on a side or its model is degenerate."""
    step = ndtr(d / se) * factor
    d_step = -np.exp(-0.5 * (d / se) ** 2) / (se * _SQRT_2PI) * factor
    far, near = d > 2.5 * se + 1.0, d < -2.5 * se - 1.0
    if not far.any() or not near.any():
        return 0.0
    contrast = float(np.median(values[far]) - np.median(values[near]))
    cols = [np.ones(d.size), step] + ([d, d * step] if free_slopes else [])
    g = np.column_stack([*cols, contrast * d_step])
    fisher = (g / var[:, None]).T @ g
    k = fisher.shape[0] - 1
    try:
        return float(fisher[k, k]
                     - fisher[k, :k] @ np.linalg.solve(fisher[:k, :k], fisher[:k, k]))
    except np.linalg.LinAlgError:
        return 0.0


def _side_information(gray: np.ndarray, var: np.ndarray, sides: list[tuple], k: int,
                      blur_px: float) -> np.ndarray:
    """The 2 x 2 Fisher information of side k's (normal offset, rotation about its
    middle), summed over its columns; each column's level and step height free (profiled
    out) and the neighbouring side's step modelled near the corners."""
    a, _b, length, t, n = sides[k]
    prev, nxt = sides[(k - 1) % 4], sides[(k + 1) % 4]
    horizontal = abs(t[0]) >= abs(t[1])
    nu = abs(n[1]) if horizontal else abs(n[0])  # |normal . minor axis|
    se = _spread(blur_px)
    hw = math.ceil((3.0 * se + 0.5) / nu) + 3
    h, w = gray.shape
    j = np.arange(-hw, hw + 1)
    ends = sorted((a[0], a[0] + length * t[0]) if horizontal else (a[1], a[1] + length * t[1]))
    info = np.zeros((2, 2))
    for col in range(math.ceil(ends[0]), math.floor(ends[1]) + 1):
        if horizontal:
            m = a[1] + (col - a[0]) * t[1] / t[0]
            xs, ys = np.full(j.size, col), np.rint(m).astype(int) + j
        else:
            m = a[0] + (col - a[1]) * t[0] / t[1]
            xs, ys = np.rint(m).astype(int) + j, np.full(j.size, col)
        if xs.min() < 0 or ys.min() < 0 or xs.max() >= w or ys.max() >= h:
            continue
        p = np.column_stack([xs, ys]).astype(float)
        d1 = (p - a) @ n
        along = float((p[hw] - a) @ t)
        if min(along, length - along) < 1.0:
            continue
        nb = prev if along < length / 2 else nxt
        f = ndtr(((p - nb[0]) @ nb[4]) / se)  # the neighbour's step (1 inside the holder)
        i_off = _crossing_information(d1, gray[ys, xs], var[ys, xs], se, f)
        r = along - length / 2
        info += i_off * np.array([[1.0, r], [r, r * r]])
    return info


def corner_bound(gray: np.ndarray, corners_px: np.ndarray, blur_px: float,
                 var: np.ndarray, model: Literal["quadrilateral", "rectangle"] = "quadrilateral"
                 ) -> np.ndarray:
    """The Cramer-Rao bound of each corner's position error (px, RMS of the 2-D error) of
    the quadrilateral ``corners_px`` (in order round it) in ``gray`` (8-bit DN), for a
    Gaussian blur of ``blur_px`` and pixel noise variances ``var``; inf where a side has
    too few columns to be placed. ``model``: "quadrilateral", four free sides (what a
    tilted camera's perspective needs), or "rectangle", the four sides turned as one
    (what :mod:`alignd.vision.holder_square` fits where their directions agree)."""
    c = order_corners(np.asarray(corners_px, float))
    centre = c.mean(axis=0)
    sides = []
    for k in range(4):
        a, b = c[k], c[(k + 1) % 4]
        length = float(np.linalg.norm(b - a))
        t = (b - a) / length
        n = np.array([-t[1], t[0]])
        if n @ (centre - a) < 0:
            n = -n  # inward
        sides.append((a, b, length, t, n))
    # the joint information of (side 0-3's offsets, side 0-3's rotations about their
    # middles); a rectangle's four rotations are one (its turn about its centre moves
    # each side along itself, not across)
    info = np.zeros((8, 8))
    for k in range(4):
        i_k = _side_information(gray, var, sides, k, blur_px)
        if abs(np.linalg.det(i_k)) < 1e-12:
            return np.full(4, math.inf)
        idx = np.array([k, 4 + k])
        info[np.ix_(idx, idx)] = i_k
    if model == "rectangle":
        tie = np.zeros((8, 5))
        tie[:4, :4] = np.eye(4)
        tie[4:, 4] = 1.0
    else:
        tie = np.eye(8)
    cov = tie @ np.linalg.inv(tie.T @ info @ tie) @ tie.T
    out = np.empty(4)
    for k in range(4):  # corner k + 1: the end of side k and the start of side k + 1
        j = (k + 1) % 4
        s1, s2 = sides[k], sides[j]
        # the two sides' normal displacements at the corner, from (offset, rotation)
        ends = np.zeros((2, 8))
        ends[0, [k, 4 + k]] = 1.0, s1[2] / 2
        ends[1, [j, 4 + j]] = 1.0, -s2[2] / 2
        var_n = ends @ cov @ ends.T
        inv = np.linalg.inv(np.array([s1[4], s2[4]]))
        out[j] = math.sqrt(float(np.trace(inv @ var_n @ inv.T)))
    return out


def corpus_bound(n: int, seed: int
                 ) -> dict[str, tuple[list[float], list[float], list[float]]]:
    """The bench's top corpus (``seed``: bench/vision.py's seed + 100): per category, the
    squared corner errors of track_holder and the squared bounds (a quadrilateral's, a
    rectangle's), over the uncompressed
    frames without lens distortion that it finds (a wrong detection, > 1 px, left out as
    the bench leaves it out)."""
    rng = np.random.default_rng(seed)
    out: dict[str, tuple[list[float], list[float], list[float]]] = {}
    for i in range(n):
        cat = TOP_CATEGORIES[i % len(TOP_CATEGORIES)]
        sc = random_top_scene(rng, cat)
        if sc.encoding.jpeg_quality is not None or sc.lens is not None:
            continue
        try:
            det = track_holder(sc.image, expected_size_px=sc.expected_size_px)
        except VisionError:
            continue
        if not det.ok:
            continue
        truth = order_corners(sc.corners_px)
        err = np.linalg.norm(order_corners(det.corners_px, truth) - truth, axis=1)
        if err.max() > 1.0:
            continue
        gray = as_gray(sc.image, "top image")
        var = _scene_variance(gray, sc.params, sc.encoding.bits)
        bound = corner_bound(gray, truth, scene_number(sc.params, "blur_px"), var)
        rect = corner_bound(gray, truth, scene_number(sc.params, "blur_px"), var, "rectangle")
        for key in (cat, "total"):
            e2, b2, r2 = out.setdefault(key, ([], [], []))
            e2.extend((err ** 2).tolist())
            b2.extend((bound ** 2).tolist())
            r2.extend((rect ** 2).tolist())
    return out


def _row_information(gray: np.ndarray, var: np.ndarray, y: int, x: float, blur_px: float,
                     free_slopes: bool) -> float:
    """The information on a near-vertical edge's crossing x in image row y, its level and
    step height (and with ``free_slopes`` the slopes on either side) profiled out; 0
    where the window leaves the frame or has no tail."""
    se = _spread(blur_px)
    hw = math.ceil(3.0 * se + 0.5) + 3
    xs = round(x) + np.arange(-hw, hw + 1)
    if xs.min() < 0 or xs.max() >= gray.shape[1]:
        return 0.0
    return _crossing_information(xs - x, gray[y, xs], var[y, xs], se,
                                 free_slopes=free_slopes)


def edge_angle_bound(gray: np.ndarray, var: np.ndarray, x_mid: float, y_mid: float,
                     angle_deg: float, rows: tuple[int, int], blur_px: float,
                     free_slopes: bool = True) -> float:
    """The Cramer-Rao bound (deg) of a near-vertical edge's angle from ``rows`` (first,
    last) of ``gray``: the line x = x_mid - (y - y_mid) tan(angle) (the angle positive
    when the top leans toward +x) with its offset free; inf with fewer than two rows of
    information."""
    ta = math.tan(math.radians(angle_deg))
    info = np.zeros((2, 2))
    for y in range(rows[0], rows[1] + 1):
        r = y - y_mid
        info += _row_information(gray, var, y, x_mid - r * ta, blur_px, free_slopes) * (
            np.array([[1.0, r], [r, r * r]]))
    if abs(np.linalg.det(info)) < 1e-12:
        return math.inf
    return math.degrees(math.sqrt(float(np.linalg.inv(info)[1, 1])))


def scene_number(params: dict[str, object], key: str) -> float:
    """A scene's numeric parameter (the scene generator records its draws)."""
    v = params[key]
    if not isinstance(v, (int, float)):
        raise TypeError(f"scene parameter {key}: {v!r} is not a number")
    return float(v)


def _scene_variance(gray: np.ndarray, params: dict[str, object], bits: int) -> np.ndarray:
    """A corpus frame's pixel variances from the noise model its scene recorded."""
    return pixel_variance(gray, scene_number(params, "read_noise_dn"),
                          scene_number(params, "electrons_per_dn"), 255.0 if bits == 8 else 4095.0)


def _tilt_bound(gray: np.ndarray, var: np.ndarray, blur_px: float, m: SideMeasurement,
                sample_angle_deg: float, pole_angle_deg: float, free_slopes: bool) -> float:
    """The bound of one frame's tilt: its sample edge's angle against the mean of its
    pole's edges (weighted as the measurement weighs them, by inverse variance), over the
    rows each edge was fitted on (its ends trimmed as the fit trims them)."""
    def edge(e: SideEdge, angle_deg: float) -> float:
        rows = (e.rows[0] + 10, e.rows[1] - 10)
        return edge_angle_bound(gray, var, e.x_mid_px, (e.rows[0] + e.rows[1]) / 2,
                                angle_deg, rows, blur_px, free_slopes)
    sample = edge(m.sample_edges[0], sample_angle_deg)
    pole = 1.0 / math.sqrt(sum(edge(e, pole_angle_deg) ** -2 for e in m.pole_edges))
    return math.hypot(sample, pole)


def corpus_side_bound(n: int, seed: int, frames: int = 8
                      ) -> list[tuple[str, float, float, float]]:
    """The bench's side corpus (``seed``: bench/vision.py's seed + 200): for each raw view
    measured with its regions, its category, the scatter (standard deviation) of one
    frame's tilt over ``frames`` frames, and the bounds of one frame's tilt with the
    rows' slopes free and known (deg)."""
    rng = np.random.default_rng(seed)
    out: list[tuple[str, float, float, float]] = []
    for i in range(n):
        cat = SIDE_CATEGORIES[i % len(SIDE_CATEGORIES)]
        sc = random_side_scene(rng, cat, frames=frames)
        if sc.encoding.jpeg_quality is not None:
            continue
        try:
            av = measure_tilt_frames(list(sc.frames), pole_roi_px=sc.pole_roi_px,
                                     sample_roi_px=sc.sample_roi_px)
        except VisionError:
            continue
        first = av.frames[0]
        if not first.sample_edges or not first.pole_edges:
            continue
        gray = as_gray(sc.frames[0], "side image")
        var = _scene_variance(gray, sc.params, sc.encoding.bits)
        blur = scene_number(sc.params, "blur_px")
        bounds = [_tilt_bound(gray, var, blur, first, sc.sample_angle_deg,
                              sc.pole_angle_deg, free) for free in (True, False)]
        tilts = np.array([m.tilt_deg for m in av.frames])
        out.append((cat, float(np.std(tilts, ddof=1)), bounds[0], bounds[1]))
    return out


def print_top(n: int, seed: int) -> None:
    res = corpus_bound(n, seed + 100)
    print(f"top corpus (seed {seed} + 100), uncompressed, no lens distortion: corner "
          "RMS error (px) against the Cramer-Rao bound of four free sides (quad) and of "
          "a rectangle's (rect)")
    print(f"{'category':12s} {'scenes':>6s} {'ours':>8s} {'quad':>8s} {'ratio':>6s} "
          f"{'rect':>8s} {'ratio':>6s}")
    for cat in [*TOP_CATEGORIES, "total"]:
        if cat not in res:
            continue
        e2, b2, r2 = res[cat]
        ours, bound, rect = (math.sqrt(float(np.mean(v))) for v in (e2, b2, r2))
        print(f"{cat:12s} {len(e2) // 4:6d} {ours:8.4f} {bound:8.4f} {ours / bound:6.2f} "
              f"{rect:8.4f} {ours / rect:6.2f}")


def print_side(n: int, seed: int, frames: int) -> None:
    res = corpus_side_bound(n, seed + 200, frames)
    print(f"\nside corpus (seed {seed} + 200), raw views, regions: one frame's tilt scatter "
          f"over {frames} frames against its Cramer-Rao bound, rows' slopes free / known "
          "(deg, RMS over the views)")
    print(f"{'category':20s} {'views':>5s} {'ours':>8s} {'free':>8s} {'ratio':>6s} "
          f"{'known':>8s} {'ratio':>6s}")
    for cat in [*SIDE_CATEGORIES, "total"]:
        r = [x for x in res if cat in (x[0], "total")]
        if not r:
            continue
        ours, free, known = (math.sqrt(float(np.mean([float(x[k]) ** 2 for x in r])))
                             for k in (1, 2, 3))
        print(f"{cat:20s} {len(r):5d} {ours:8.5f} {free:8.5f} {ours / free:6.2f} "
              f"{known:8.5f} {ours / known:6.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", choices=("top", "side"), help="one camera's table")
    ap.add_argument("--scenes", type=int, default=1001, help="top scenes drawn (default 1001)")
    ap.add_argument("--side-scenes", type=int, default=300,
                    help="side views drawn (default 300; the JPEG ones are left out)")
    ap.add_argument("--frames", type=int, default=8, help="frames of each side view")
    ap.add_argument("--seed", type=int, default=2024,
                    help="bench/vision.py's --seed (its top corpus is drawn from seed + 100, "
                         "the side's from seed + 200)")
    ap.add_argument("--quick", action="store_true", help="few scenes (CI)")
    args = ap.parse_args()
    if args.quick:
        args.scenes, args.side_scenes = 42, 10
    if args.only in (None, "top"):
        print_top(args.scenes, args.seed)
    if args.only in (None, "side"):
        print_side(args.side_scenes, args.seed, args.frames)


if __name__ == "__main__":
    main()
