"""The batched edge measurements (alignd.vision.edges *_many, adaptive_slopes) that make
holder tracking fast: several edges in one batch give exactly what each edge gives alone,
and one edge's data never leaks into another's (an edge with no usable column used to
turn the running sums of every later edge into NaN)."""

from __future__ import annotations

import numpy as np
import pytest

from alignd.vision.edges import (
    adaptive_slope,
    adaptive_slopes,
    area_crossings,
    area_crossings_many,
    coarse_edge,
    coarse_edges_many,
    edge_points,
    edge_points_many,
    edge_rows,
    segment_median,
)
from drivers.sim.scenes import random_top_scene


def _segments(rng: np.random.Generator) -> list[np.ndarray]:
    parts = []
    for _ in range(int(rng.integers(1, 6))):
        v = rng.normal(0.0, 1.0, int(rng.integers(1, 80)))
        if v.size > 10 and rng.random() < 0.5:
            v[v.size // 2:] += rng.uniform(3.0, 12.0)  # a penumbra along the edge
        if v.size > 5 and rng.random() < 0.3:
            v[2] = 40.0  # an outlier
        parts.append(v)
    return parts


@pytest.mark.parametrize("k", [0, 1, 3, 15])
def test_adaptive_slopes_equal_adaptive_slope_edge_by_edge(k: int) -> None:
    rng = np.random.default_rng(11)
    for _ in range(200):
        parts = _segments(rng)
        seg = np.concatenate([np.full(p.size, i) for i, p in enumerate(parts)])
        got = adaptive_slopes(np.concatenate(parts), seg, len(parts), k)
        want = np.concatenate([adaptive_slope(p, k) for p in parts])
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_segment_median_is_the_median_per_segment() -> None:
    rng = np.random.default_rng(12)
    for _ in range(100):
        parts = _segments(rng)
        seg = np.concatenate([np.full(p.size, i) for i, p in enumerate(parts)])
        got = segment_median(np.concatenate(parts), seg, len(parts) + 1)
        np.testing.assert_array_equal(got[:-1], [np.sort(p)[p.size // 2] for p in parts])
        assert np.isnan(got[-1])  # a segment without values
        mean_mid = segment_median(np.concatenate(parts), seg, len(parts), upper=False)
        np.testing.assert_allclose(mean_mid, [np.median(p) for p in parts], rtol=0, atol=1e-12)


def test_edge_rows_are_each_segments_good_rows() -> None:
    """Segments without a good row (or without any row) get an empty index array."""
    rng = np.random.default_rng(13)
    for _ in range(100):
        parts = _segments(rng)
        seg = np.concatenate([np.full(p.size, i) for i, p in enumerate(parts)])
        good = rng.random(seg.size) < 0.7
        got = edge_rows(good, seg, len(parts) + 1)
        assert len(got) == len(parts) + 1 and got[-1].size == 0
        for k, idx in enumerate(got):
            np.testing.assert_array_equal(idx, np.flatnonzero(good & (seg == k)))


@pytest.fixture(scope="module")
def scene() -> tuple[np.ndarray, np.ndarray]:
    sc = random_top_scene(np.random.default_rng(7), "plain")
    return sc.image.astype(np.float32), sc.corners_px


def test_the_four_sides_in_one_batch_equal_each_side_alone(
        scene: tuple[np.ndarray, np.ndarray]) -> None:
    img, c = scene
    sides = [(c[i] + 0.3, c[(i + 1) % 4] - 0.2) for i in range(4)]
    for hw in (5, 9):
        many = edge_points_many(img, sides, half_width=hw, margin_px=10.0, min_contrast=15.0)
        for (p0, p1), got in zip(sides, many, strict=True):
            one = edge_points(img, p0, p1, half_width=hw, margin_px=10.0, min_contrast=15.0)
            assert got.vertical == one.vertical and got.xy.shape[0] > 30
            np.testing.assert_allclose(got.xy, one.xy, rtol=0, atol=1e-9)
            np.testing.assert_allclose(got.contrast, one.contrast, rtol=0, atol=1e-9)
    lines = coarse_edges_many(img, sides, search_px=10, min_step=7.5)
    for (p0, p1), line in zip(sides, lines, strict=True):
        alone = coarse_edge(img, p0, p1, search_px=10, min_step=7.5)
        assert line is not None and alone is not None
        assert line.n_used == alone.n_used
        assert abs(line.d - alone.d) < 1e-9 and np.allclose(line.n, alone.n, atol=1e-12)


def test_an_edge_without_usable_columns_does_not_spoil_the_next(
        scene: tuple[np.ndarray, np.ndarray]) -> None:
    """A featureless stretch first (no column reaches the contrast) and the holder's side
    after it: the side's crossings are those it has alone (with a NaN median the first
    edge's running sums made the second lose every column)."""
    img, c = scene
    h, w = img.shape
    flat = np.full((h, w), 100.0, np.float32)
    both = np.hstack([flat, img])  # the holder moved right by w: a blank half on the left
    t_blank = np.arange(100, 200)
    c_blank = np.full(t_blank.size, h / 2)
    p0, p1 = c[0] + [w, 0.0], c[1] + [w, 0.0]
    side = edge_points(both, p0, p1, margin_px=10.0, min_contrast=15.0)
    ts, cs = (side.xy[:, 1], side.xy[:, 0]) if side.vertical else (side.xy[:, 0], side.xy[:, 1])
    alone = area_crossings(both, ts, np.round(cs), side.vertical, min_contrast=15.0)
    blank, after = area_crossings_many(
        both, [(t_blank, c_blank, False), (ts, np.round(cs), side.vertical)], min_contrast=15.0)
    assert blank.xy.shape[0] == 0
    assert alone.xy.shape[0] > 30
    np.testing.assert_allclose(after.xy, alone.xy, rtol=0, atol=1e-9)
