"""The holder's full search (alignd.vision.holder_search): which candidates reach the
refinement, in which order, and the batched outline score against a plain reference."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from alignd.vision import holder_search
from alignd.vision.holder import order_corners, track_holder
from drivers.sim.render import Polygon, Raster, coverage

Cand = tuple[float, np.ndarray, str]


def _votes(voted: list[Cand]) -> holder_search.FrameVotes:
    """A frame's votes that give ``voted`` (the frame itself is never looked at)."""
    votes = holder_search.FrameVotes(np.zeros((720, 1280), np.float32), (300.0, 160.0), 15.0)
    votes.voted = lambda *a_, **k: voted  # type: ignore[method-assign]
    return votes


def _box(cx: float, cy: float, L: float = 300.0, S: float = 160.0, a: float = 7.0
         ) -> np.ndarray:
    return cv2.boxPoints(((cx, cy), (L, S), a)).astype(float)


def _scene(contrast: float = 140.0) -> np.ndarray:
    """One dark 300 x 160 px rectangle on a grey floor, exact edges, noise 1.5 DN."""
    img = np.full((720, 1280), 190.0, np.float32)
    ras = Raster((1280, 720), 1000.0, (640.0, 360.0), 0.0)
    cov = coverage(Polygon(_box(520.3, 340.7)), ras, (0, 0, 1280, 720))
    img += -contrast * cov
    noise = np.random.default_rng(7).normal(0, 1.5, img.shape)
    return np.clip(np.rint(img + noise), 0, 255).astype(np.uint8)


def test_the_threshold_ladder_is_built_only_when_the_vote_fails(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """With an expected size the voted box is refined first and passes: the ladder (a
    third of a search's time) is never built. Without a size it is the only source."""
    img = _scene()
    built: list[bool] = []
    ladder = holder_search._candidates

    def counted(*args: object, **kw: object) -> list[Cand]:
        built.append(True)
        return ladder(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(holder_search, "_candidates", counted)
    det = track_holder(img, expected_size_px=(300.0, 160.0))
    assert det.ok and not built
    free = track_holder(img)
    assert free.ok and built == [True]
    np.testing.assert_allclose(det.corners_px, free.corners_px, atol=0.005)


def test_weak_voted_boxes_are_not_refined_and_the_ladder_follows(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Voted boxes come strongest first; one with under a tenth of the best box's outline
    support (a peak in texture) is dropped, and the ladder's boxes come after the rest."""
    a, b, weak, d = _box(100, 100), _box(400, 100), _box(700, 100), _box(100, 400)
    voted: list[Cand] = [(100.0, a, "?"), (11.0, b, "?"), (9.0, weak, "?")]
    monkeypatch.setattr(holder_search, "_candidates", lambda *a_, **k: [(1.0, d, "dark")])
    gray = np.zeros((720, 1280), np.float32)
    got = list(holder_search.search_candidates(gray, _votes(voted), (300.0, 160.0), None))
    assert [g.tolist() for g in got] == [a.tolist(), b.tolist(), d.tolist()]
    # without an expected size there are no votes
    got = list(holder_search.search_candidates(gray, None, None, None))
    assert [g.tolist() for g in got] == [d.tolist()]


def test_voted_boxes_stop_at_max_voted_and_the_ladder_follows(
        monkeypatch: pytest.MonkeyPatch) -> None:
    a, b, c, d = _box(100, 100), _box(400, 100), _box(700, 100), _box(100, 400)
    voted: list[Cand] = [(100.0, a, "dark"), (90.0, b, "dark"), (80.0, c, "mixed")]
    monkeypatch.setattr(holder_search, "_candidates", lambda *a_, **k: [(1.0, d, "dark")])
    gray = np.zeros((720, 1280), np.float32)
    got = list(holder_search.search_candidates(gray, _votes(voted), (300.0, 160.0), None,
                                               max_voted=2))
    assert [g.tolist() for g in got] == [a.tolist(), b.tolist(), d.tolist()]


def _outline_reference(gx: np.ndarray, gy: np.ndarray, box: np.ndarray,
                       shift: np.ndarray) -> float:
    """The outline score of one box at one shift, written out side by side."""
    ctr = box.mean(axis=0)
    sides = []
    for i in range(4):
        p0, p1 = box[i] + shift, box[(i + 1) % 4] + shift
        d = p1 - p0
        n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
        if np.dot((p0 + p1) / 2 - shift - ctr, n) < 0:
            n = -n
        vals = []
        for t in np.linspace(0.1, 0.9, 24):
            p = p0 + t * d
            x0, y0 = int(np.floor(p[0])), int(np.floor(p[1]))
            fx, fy = p[0] - x0, p[1] - y0

            def bil(g: np.ndarray, x0: int = x0, y0: int = y0, fx: float = fx,
                    fy: float = fy) -> float:
                return float((1 - fy) * ((1 - fx) * g[y0, x0] + fx * g[y0, x0 + 1])
                             + fy * ((1 - fx) * g[y0 + 1, x0] + fx * g[y0 + 1, x0 + 1]))
            vals.append(abs(bil(gx) * n[0] + bil(gy) * n[1]))
        sides.append(np.mean(vals))
    v = np.asarray(sides)
    return float(v.mean() * np.sqrt(v.min() / (v.max() + 1e-9)))


def test_batched_outline_support_matches_the_plain_computation() -> None:
    """Every box and shift at once (one remap) gives each box's score as computed alone:
    the ranking of the voted boxes did not change with the batching."""
    rng = np.random.default_rng(11)
    gx = cv2.GaussianBlur(rng.normal(0, 40, (180, 320)).astype(np.float32), (0, 0), 1.5)
    gy = cv2.GaussianBlur(rng.normal(0, 40, (180, 320)).astype(np.float32), (0, 0), 1.5)
    boxes = np.array([cv2.boxPoints(((float(rng.uniform(60, 260)), float(rng.uniform(50, 130))),
                                     (float(rng.uniform(30, 80)), float(rng.uniform(20, 40))),
                                     float(rng.uniform(0, 180)))) for _ in range(5)], float)
    got = holder_search._outline_support(gx, gy, boxes, holder_search._SHIFTS)
    assert got.shape == (5, len(holder_search._SHIFTS))
    for b in range(5):
        for k in (0, 17, 24, 48):  # corners and centre of the 7 x 7 shift grid
            ref = _outline_reference(gx, gy, boxes[b], holder_search._SHIFTS[k])
            # remap interpolates with 5-bit fixed-point weights: about 1/32 px of slope
            assert got[b, k] == pytest.approx(ref, rel=0.02, abs=0.05)


def test_boxes_straddling_two_objects_are_refined_last(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A voted box whose sides contrast both ways (it straddles two objects) cannot be
    the holder: every box that could be comes first, the ladder's after all of them."""
    a, b, c, d = _box(100, 100), _box(400, 100), _box(700, 100), _box(100, 400)
    voted: list[Cand] = [(100.0, a, "mixed"), (80.0, b, "dark"), (50.0, c, "light")]
    monkeypatch.setattr(holder_search, "_candidates", lambda *a_, **k: [(1.0, d, "dark")])
    gray = np.zeros((720, 1280), np.float32)
    got = list(holder_search.search_candidates(gray, _votes(voted), (300.0, 160.0), None))
    assert [g.tolist() for g in got] == [b.tolist(), c.tolist(), a.tolist(), d.tolist()]


@pytest.mark.parametrize("invert", [False, True], ids=["dark", "light"])
def test_voted_box_knows_which_way_its_sides_contrast(invert: bool) -> None:
    img = _scene()
    if invert:
        img = 255 - img
    voted = holder_search.FrameVotes(img.astype(np.float32), (300.0, 160.0), 15.0).voted()
    _score, box, pol = voted[0]
    assert pol == ("light" if invert else "dark")
    truth = _box(520.3, 340.7)
    # the box is found to about a 1/4-scale pixel (the fine fit does the rest)
    d = np.linalg.norm(box[:, None] - truth[None], axis=2).min(axis=1)
    assert d.max() < 6.0, d


@pytest.mark.parametrize("n", [4095, 5000, 5001, 57000])
def test_bracketed_selection_is_np_partition(n: int) -> None:
    """The noise estimate's median by bracketing equals numpy's, ties and all."""
    rng = np.random.default_rng(n)
    k = n // 2
    ks = [k - 1, k] if n % 2 == 0 else [k]
    for v in (rng.normal(size=n), rng.integers(0, 4, n), np.zeros(n),
              np.abs(rng.standard_cauchy(n))):
        a = v.astype(np.float32)
        np.testing.assert_array_equal(holder_search._select(a, ks), np.partition(a, ks)[ks])
        assert float(np.mean(holder_search._select(a, ks))) == float(np.median(a))


@pytest.mark.parametrize("n", [1, 2, 4095, 57600])
def test_percentiles_are_np_percentile(n: int) -> None:
    """The ladder's contrast stretch reads the 0.5 and 99.5 percentiles by two order
    statistics each: the same numbers as numpy's linear interpolation, ties and all."""
    rng = np.random.default_rng(n)
    for v in (rng.normal(100, 30, n), rng.integers(0, 4, n), np.full(n, 7.0),
              np.round(rng.uniform(0, 255, n), 1)):
        for a in (v.astype(np.float32), v.astype(np.float64)):
            for qs in ((0.5, 99.5), (0.0, 100.0), (37.3, 50.0)):
                got = holder_search._percentiles(a, qs)
                assert got == np.percentile(a, qs).tolist()


def _on_a_breadboard(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A dark 440 x 190 px holder (88 DN) with a lighter 21 px plate (127 DN) along one long
    side, on a floor (185 DN) with M6 holes on a 25 mm grid (55 DN; 117 px pitch, 14 px
    radius: corpus #236 of seed 5100, a 213 um pixel). A hole's edge pairs with the holes
    four pitches on at 440 px, the holder's long side: those pairs vote at their midpoints
    as strongly as the holder's short sides vote at its centre."""
    w, h = 1280, 720
    img = np.full((h, w), 185.0, np.float32)
    holes = np.zeros((h, w), np.uint8)
    for y in np.arange(97.5, h, 117.0):
        for x in np.arange(78.0, w, 117.0):
            cv2.circle(holes, (round(4 * x), round(4 * y)), 56, 255, -1, cv2.LINE_AA, shift=2)
    img += (55.0 - img) * (holes / 255.0)
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    held = cv2.boxPoints(((575.3, 315.2), (440.0, 190.0), -27.5)).astype(float)
    t = np.radians(-27.5)
    out = np.array([-np.sin(t), np.cos(t)]) * 10.5
    union = cv2.boxPoints(((575.3 + out[0], 315.2 + out[1]), (440.0, 211.0), -27.5))
    img += (127.0 - img) * coverage(Polygon(union.astype(float)), ras, (0, 0, w, h))
    img += (88.0 - img) * coverage(Polygon(held), ras, (0, 0, w, h))
    img = cv2.GaussianBlur(img, (0, 0), 0.4)
    img += np.random.default_rng(seed).normal(0, 1.0, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), held


def test_the_centre_is_where_both_midlines_vote() -> None:
    """The long sides' votes and the short sides' are kept apart and a centre needs both:
    a bump on one midline alone (here the holes' pairs) no longer outranks the holder,
    which every voted box missed before (no holder found)."""
    img, held = _on_a_breadboard()
    voted = holder_search.FrameVotes(img.astype(np.float32), (440.0, 190.0), 15.0).voted()
    assert np.linalg.norm(voted[0][1].mean(axis=0) - held.mean(axis=0)) < 4.0
    det = track_holder(img, expected_size_px=(440.0, 190.0))
    assert det.ok, det.reason
    assert np.max(np.linalg.norm(order_corners(det.corners_px, held) - held, axis=1)) < 0.3


def _beside_a_bright_rectangle(gap_px: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A dark 378 x 169 px holder (25 DN on a 60 DN floor) square to the frame, and ``gap_px``
    above it a white 247 x 160 px rectangle at 42 deg (230 DN): corpus #463 of seed 7100
    (the second rectangle of the "distractors"). Blur 0.8 px, noise 2 DN, exact areas."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    img = np.full((h, w), 60.0, np.float32)
    held = cv2.boxPoints(((640.3, 400.2), (378.0, 169.0), -1.5)).astype(float)
    other = cv2.boxPoints(((0.0, 0.0), (247.0, 160.0), 42.0)).astype(float)
    other += np.array([700.0, 400.2 - 84.5 - gap_px]) - other[np.argmax(other[:, 1])]
    img += (230.0 - img) * coverage(Polygon(other), ras, (0, 0, w, h))
    img += (25.0 - img) * coverage(Polygon(held), ras, (0, 0, w, h))
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    img += np.random.default_rng(seed).normal(0, 2.0, img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), held


@pytest.mark.parametrize("gap_px", [10.0, 40.0])
def test_a_peaks_side_directions_from_its_own_voters(gap_px: float) -> None:
    """The white rectangle's edges, four times the holder's contrast, dominate every edge
    around the holder's centre: its voted box lies at 42 deg, 155-165 px off at a corner.
    Where every box failed, the boxes are voted again with each peak's side directions
    from the edge pixels whose votes made it: the holder is found."""
    img, held = _beside_a_bright_rectangle(gap_px)
    gray = img.astype(np.float32)
    votes = holder_search.FrameVotes(gray, (378.0, 169.0), 15.0)
    first = votes.voted()[0][1]
    assert np.max(np.linalg.norm(order_corners(first, held) - held, axis=1)) > 100.0
    again = holder_search.voted_by_voters(votes)[0]
    assert np.max(np.linalg.norm(order_corners(again, held) - held, axis=1)) < 4.0
    det = track_holder(img, expected_size_px=(378.0, 169.0))
    assert det.ok, det.reason
    assert np.max(np.linalg.norm(order_corners(det.corners_px, held) - held, axis=1)) < 0.1


def test_a_frames_votes_again_reuse_its_edge_map_and_peaks(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A frame whose boxes all failed is voted again twice (the peaks' own directions,
    sides paired either way): the edge map and the peaks are computed once, and each vote
    gives the boxes a vote of its own would."""
    img, _held = _beside_a_bright_rectangle(10.0)
    gray = img.astype(np.float32)
    size = (378.0, 169.0)
    fresh = [holder_search.FrameVotes(gray, size, 15.0).voted(by_voters=bv, either_way=ew)
             for bv, ew in ((False, False), (True, False), (False, True))]
    votes = holder_search.FrameVotes(gray, size, 15.0)
    pairings: list[bool] = []
    partners = holder_search._partners

    def counted(em: object, dist: np.ndarray, step: int = 1, either_way: bool = False
                ) -> np.ndarray:
        pairings.append(either_way)
        return partners(em, dist, step, either_way)  # type: ignore[arg-type]

    monkeypatch.setattr(holder_search, "_partners", counted)
    first = votes.voted()
    n_first = len(pairings)
    assert n_first > 0
    again = votes.voted(by_voters=True)
    assert len(pairings) == n_first  # no pairing, no scale, no peak computed again
    either = votes.voted(either_way=True)
    assert pairings[n_first:] and all(pairings[n_first:])  # only the either-way pairs
    for got, ref in zip((first, again, either), fresh, strict=True):
        assert len(got) == len(ref)
        for (s1, b1, p1), (s2, b2, p2) in zip(got, ref, strict=True):
            assert (s1, p1) == (s2, p2)
            np.testing.assert_array_equal(b1, b2)
