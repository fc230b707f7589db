"""Full search for the sample holder in a top-camera frame: approximate boxes to refine.

Two candidate sources, the first preferred: with the expected size, centre voting of
paired opposite edges at the holder's measured scale (:class:`FrameVotes`, no
threshold); then (and without an expected size, only) rectangular blobs over a ladder of
thresholds of a 4x-downsampled frame (:func:`_candidates`). Both give boxes good to about a
pixel at 1/4 scale; :mod:`alignd.vision.holder` refines them in turn (a refinement costs
about twice the whole search, so the order and the boxes left out matter as much as the
search's own speed: about 10 ms a frame on one core with the expected size, 5 ms without).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

_DOWN = 4
_MIN_SUPPORT_RATIO = 0.1  # a voted box this much weaker than the best is not refined


def search_candidates(gray: np.ndarray, votes: FrameVotes | None,
                      expected_size_px: tuple[float, float] | None, polarity: str | None,
                      max_voted: int | None = None) -> Iterator[np.ndarray]:
    """Approximate boxes (4 corners, full-res px), the likeliest first: at most
    ``max_voted`` of the ``votes`` (the frame's, with the expected size), then the
    ladder's.

    Lazy: the caller refines them in turn and stops at the first that passes, so the
    threshold ladder (about 5 ms) is only built when every voted box failed, or without
    an expected size. Voted boxes under a tenth of the best one's outline score are left
    out (peaks in texture; the corpus' holder never scored under 0.36 of the best).
    """
    if votes is not None:
        yield from _ranked(votes.voted(), max_voted)
    for _score, box, _pol in _candidates(gray, expected_size_px, polarity):
        yield box


def voted_by_voters(votes: FrameVotes, max_voted: int | None = None) -> list[np.ndarray]:
    """The voted boxes again, each peak's side directions taken from the edge pixels whose
    votes made it rather than from every edge pixel around it: for a frame where every
    box of :func:`search_candidates` failed. Beside a holder of low contrast, a brighter
    object's edges (a second rectangle, a cable) outweigh its sides around its centre and
    turn its box; taken first, these directions changed frames found right (a box a
    degree elsewhere refines to other sides in a few), so they come second."""
    return _ranked(votes.voted(by_voters=True), max_voted)


def voted_either_way(votes: FrameVotes, max_voted: int | None = None) -> list[np.ndarray]:
    """The voted boxes with opposite sides paired whichever way their gradients point:
    for a frame where every other box failed. A holder between two levels, lighter than
    the disc and darker than a white sample beside it (or the other way round), has that
    side's gradient the same way as the side opposite it, so its sides along the sample
    never paired and its box was not voted at all."""
    return _ranked(votes.voted(either_way=True), max_voted)


def _ranked(voted: list[tuple[float, np.ndarray, str]], max_voted: int | None
            ) -> list[np.ndarray]:
    """The voted boxes to refine, in order: those of a tenth of the best one's outline
    score or more, a box whose sides contrast both ways last."""
    if not voted:
        return []
    strong = [(pol, box) for score, box, pol in voted
              if score >= _MIN_SUPPORT_RATIO * voted[0][0]]
    # the holder's four sides contrast the same way: a box whose outline is darker
    # outside on some sides and brighter on others (it straddles two objects) is
    # refined only after every box that could be the holder
    ranked = [box for pol, box in strong if pol != "mixed"] + \
        [box for pol, box in strong if pol == "mixed"]
    return ranked[:max_voted]


def _candidates(gray: np.ndarray, expected_size_px: tuple[float, float] | None,
                polarity: str | None) -> list[tuple[float, np.ndarray, str]]:
    """Rectangular blobs as (score, 4 approx corners in full-res px, polarity)."""
    h, w = gray.shape
    small = cv2.resize(gray, (w // _DOWN, h // _DOWN), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), 1.0)
    lo, hi = _percentiles(small.ravel(), (0.5, 99.5))
    u8 = np.clip((small - lo) * (255.0 / max(hi - lo, 1e-6)), 0, 255).astype(np.uint8)
    otsu, _ = cv2.threshold(u8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    # Otsu alone fails when shadows or a third level split the histogram: try a ladder of
    # thresholds and keep the blobs that are rectangles (as MSER would, but cheaper)
    thresholds = sorted({int(otsu), *range(32, 240, 32)})
    sh, sw = u8.shape
    min_area = 40 if expected_size_px is None else 0.4 * expected_size_px[0] * \
        expected_size_px[1] / _DOWN ** 2
    out = []
    kernel = np.ones((3, 3), np.uint8)
    pols = ("dark", "light") if polarity is None else (polarity,)
    for pol in pols:
        # each level's mask is opened (3x3) to cut 1-px bridges; a flat opening commutes
        # with a threshold, so one grey-level opening (closing, for the dark side's
        # complement) of the frame serves every level of the ladder
        if pol == "dark":
            ref, kind = cv2.morphologyEx(u8, cv2.MORPH_CLOSE, kernel), cv2.THRESH_BINARY_INV
        else:
            ref, kind = cv2.morphologyEx(u8, cv2.MORPH_OPEN, kernel), cv2.THRESH_BINARY
        for thr in thresholds:
            # dark: u8 < thr, i.e. not u8 > thr - 1; light: u8 > thr
            _, mask = cv2.threshold(ref, thr - 1 if pol == "dark" else thr, 1, kind)
            cnts, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
            for cnt in cnts:
                if cnt.shape[0] < 4:
                    continue
                x, y, bw, bh = cv2.boundingRect(cnt)
                # not touching the border (cannot be measured whole), not the whole frame
                if x <= 0 or y <= 0 or x + bw >= sw or y + bh >= sh:
                    continue
                area = cv2.contourArea(cnt) + 0.5 * cv2.arcLength(cnt, True) + 1.0
                if area < min_area or area > 0.5 * sh * sw:
                    continue
                (cx, cy), (rw, rh), ang = cv2.minAreaRect(cnt)
                rw, rh = rw + 1.0, rh + 1.0  # pixel centres -> pixel extents
                if rw * rh <= 0 or min(rw, rh) < 4:
                    continue
                rect = area / (rw * rh)
                if rect < 0.86:
                    continue
                # the threshold must cut the blob's edge near half height, else the box
                # is grown by the blur halo or shrunk (a pass-1 window misses the edge)
                y0, y1 = max(y - 3, 0), min(y + bh + 3, sh)
                x0, x1 = max(x - 3, 0), min(x + bw + 3, sw)
                blob = np.zeros((y1 - y0, x1 - x0), np.uint8)
                cv2.drawContours(blob, [cnt - np.array([x0, y0])], -1, 1, thickness=-1)
                blob = blob.astype(bool)
                grown = cv2.dilate(blob.astype(np.uint8), kernel, iterations=3).astype(bool)
                core = cv2.erode(blob.astype(np.uint8), kernel, iterations=2).astype(bool)
                ring = grown & ~cv2.dilate(blob.astype(np.uint8), kernel).astype(bool)
                if not core.any() or not ring.any():
                    continue
                win = u8[y0:y1, x0:x1]
                lin, lout = _median(win[core]), _median(win[ring])
                if abs(lout - lin) < 8:
                    continue
                r = (thr - lin) / (lout - lin)
                if not 0.3 <= r <= 0.7:
                    continue
                score = rect * (1.0 - abs(r - 0.5)) * math.log(float(area))
                if expected_size_px is not None:
                    L, S = max(rw, rh) * _DOWN, min(rw, rh) * _DOWN
                    eL, eS = max(expected_size_px), min(expected_size_px)
                    err = max(abs(L / eL - 1), abs(S / eS - 1))
                    if err > 0.3:
                        continue
                    score *= 1.0 - err
                box = cv2.boxPoints(((cx, cy), (rw, rh), ang))
                full = (box + 0.5) * _DOWN - 0.5
                out.append((score, full.astype(float), pol))
    out.sort(key=lambda t: -t[0])
    return out


def _median(v: np.ndarray) -> float:
    """np.median of a 1-D array, without its generic machinery (called per blob)."""
    n = v.size
    k = n // 2
    if n % 2:
        return float(np.partition(v, k)[k])
    part = np.partition(v, (k - 1, k))
    return (float(part[k - 1]) + float(part[k])) / 2.0


def _select(a: np.ndarray, ks: list[int]) -> np.ndarray:
    """``np.partition(a, ks)[ks]`` for a 1-D array, exactly, in a fraction of the time for a
    large one: the order statistics are bracketed on a sorted subsample, and only the
    values between the brackets are partitioned (all below them precede these)."""
    n = a.size
    if n < 4096:
        return np.partition(a, ks)[ks]
    sub = np.sort(a[::16])
    m = sub.size
    lo = sub[max(min(ks) * m // n - 40, 0)]
    hi = sub[min(max(ks) * m // n + 40, m - 1)]
    below = int(np.count_nonzero(a < lo))
    mid = a[(a >= lo) & (a <= hi)]
    rel = [k - below for k in ks]
    if min(rel) >= 0 and max(rel) < mid.size:
        return np.partition(mid, rel)[rel]
    return np.partition(a, ks)[ks]  # the subsample misled the brackets


def _percentiles(a: np.ndarray, qs: tuple[float, ...]) -> list[float]:
    """``np.percentile(a, qs)`` (linear interpolation) of a 1-D float array without NaN,
    exactly, each from its two order statistics by :func:`_select`: numpy partitions the
    whole array around both ends at once, a millisecond of a 4 ms ladder."""
    n = a.size
    out = []
    for q in np.true_divide(np.asarray(qs, float), 100):
        v = (n - 1) * q
        i = min(max(math.floor(v), 0), n - 1)
        j = min(i + 1, n - 1) if v < n - 1 else i
        pair = _select(a, [i, j])
        prev, nxt = pair[:1], pair[1:]
        t = np.asarray([v - math.floor(v)])
        # numpy's _lerp, step by step in the same dtypes (the pair's, then float64)
        diff = nxt - prev
        val = prev + diff * t
        if t[0] >= 0.5:
            val = nxt - diff * (1 - t)
        out.append(float(val[0]))
    return out


def _noise_sigma(img: np.ndarray) -> float:
    """Robust noise standard deviation of an image (MAD of its Laplacian)."""
    lap = cv2.Laplacian(img, cv2.CV_32F, ksize=1)
    a = np.abs(lap[2:-2, 2:-2]).ravel()
    k = a.size // 2
    # np.median: the middle value, or the mean of the middle two (in the array's dtype)
    med = float(np.mean(_select(a, [k - 1, k] if a.size % 2 == 0 else [k])))
    return med * 1.4826 / math.sqrt(20.0) + 1e-3


_SHIFTS = np.stack(np.meshgrid(np.arange(-3, 4), np.arange(-3, 4)), -1).reshape(-1, 2).astype(float)


@dataclass(frozen=True)
class _EdgeMap:
    """Significant, thin edge pixels of a 1/4-scale frame: where, which way, how strong."""

    xs: np.ndarray
    ys: np.ndarray
    nx: np.ndarray  # unit gradient
    ny: np.ndarray
    mag: np.ndarray
    gx: np.ndarray  # the whole gradient images
    gy: np.ndarray
    near_edge: np.ndarray  # edge pixels grown by 1 px


@dataclass(frozen=True)
class _Peaks:
    """The votes at one size and the peaks they make: which edge pixel (``ei``) voted for
    where (``cx``, ``cy``), the peaks' centres and, per peak, the edge pixels near enough
    to be its outline."""

    ei: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    ctrs: np.ndarray  # (P, 2)
    near: np.ndarray  # (P, N) bool


class FrameVotes:
    """Rectangles of the expected size found by centre voting, threshold-ladder free, in
    one frame at one minimum contrast.

    At 1/4 scale every significant gradient pixel (beyond 4 noise sigma and twice the
    minimum contrast, thinned by non-maximum suppression) that has a partner edge a whole
    side (short or long) away along its gradient, with the opposite gradient, votes for
    the midpoint: the holder's long sides vote along its long midline and its short sides
    along the short one, so its centre is where the two cross (the two kinds of votes are
    gathered apart and a peak needs both); edges of anything else scatter or do not
    pair. The pairing needs the side to within about 1 px at 1/4 scale (2 % of a 160 px
    side), much less than ``size_tolerance``: a configured pixel size a few per cent off
    (commissioning passes 5 %) would pair nothing. So the holder's scale
    in the image is measured first (:func:`_pair_scales`) and the votes cast at that size.
    At each peak the side directions are the dominant gradient orientation (mod 90 deg)
    around it (``by_voters``: of the edge pixels whose votes made it), and the long side is
    the assignment whose outline has the stronger gradient. ``either_way``: a partner's
    gradient may point either way (:func:`voted_either_way`).

    The edge map, the scales and the peaks are computed once: a frame whose boxes all
    failed votes again, with the peaks' own directions and with sides paired either way,
    and each vote computed them anew (a third of such a frame's search).
    """

    def __init__(self, gray: np.ndarray, expected_size_px: tuple[float, float],
                 min_contrast: float, size_tolerance: float = 0.12) -> None:
        self._gray = gray
        self._long = max(expected_size_px) / _DOWN
        self._short = min(expected_size_px) / _DOWN
        self._min_contrast = min_contrast
        self._tolerance = size_tolerance
        self._scales: dict[bool, list[float]] = {}
        self._peaks: dict[tuple[float, bool, int], _Peaks | None] = {}

    @cached_property
    def _edges(self) -> _EdgeMap | None:
        """The frame's edge map, or None where it has too few edge pixels to vote."""
        gray = self._gray
        h, w = gray.shape
        small = cv2.resize(gray, (w // _DOWN, h // _DOWN), interpolation=cv2.INTER_AREA)
        small = cv2.GaussianBlur(small, (0, 0), 0.8)
        gx = cv2.Sobel(small, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(small, cv2.CV_32F, 0, 1, ksize=3)
        mag = cv2.magnitude(gx, gy)
        # significant (4 noise sigma, a Sobel step response of the minimum contrast) and
        # thin (Canny's non-maximum suppression): shading and texture do not vote
        thr = max(4.0 * _noise_sigma(small) * math.sqrt(12.0), 2.0 * self._min_contrast)
        edges = cv2.Canny(np.clip(gx * 4, -32767, 32767).astype(np.int16),
                          np.clip(gy * 4, -32767, 32767).astype(np.int16), 4 * thr, 8 * thr,
                          L2gradient=True)
        ys, xs = np.nonzero(edges)
        if xs.size < 20:
            return None
        m = mag[ys, xs]
        return _EdgeMap(xs, ys, gx[ys, xs] / m, gy[ys, xs] / m, m, gx, gy,
                        cv2.dilate(edges, np.ones((3, 3), np.uint8)) > 0)

    def voted(self, max_peaks: int = 12, by_voters: bool = False, either_way: bool = False
              ) -> list[tuple[float, np.ndarray, str]]:
        """(outline score, 4 corners in full-res px, polarity) of each voted box, the
        best first."""
        em = self._edges
        if em is None:
            return []
        if either_way not in self._scales:
            self._scales[either_way] = _pair_scales(em, (self._short, self._long),
                                                    self._tolerance, either_way)
        scales = self._scales[either_way]
        out = []
        for scale in scales:  # as many peaks in all as one size had
            eL, eS = self._long * scale, self._short * scale
            key = (scale, either_way, max_peaks // len(scales))
            if key not in self._peaks:
                self._peaks[key] = _peaks_at_size(em, eL, eS, key[2], either_way)
            peaks = self._peaks[key]
            if peaks is not None:
                out += _boxes_at_peaks(em, peaks, eL, eS, by_voters)
        out.sort(key=lambda t: -t[0])
        return out


def _partners(em: _EdgeMap, dist: np.ndarray, step: int = 1, either_way: bool = False
              ) -> np.ndarray:
    """(N / step, len(dist)) bool: edge pixel i (every ``step``-th) has a partner edge,
    gradient the other way (``either_way``: or the same way, parallel), ``dist[j]`` px away
    along its gradient (negative: against it)."""
    sh, sw = em.near_edge.shape
    xs, ys, nx, ny = em.xs[::step], em.ys[::step], em.nx[::step], em.ny[::step]
    qx = np.rint(xs[:, None] + dist[None] * nx[:, None]).astype(np.intp)
    qy = np.rint(ys[:, None] + dist[None] * ny[:, None]).astype(np.intp)
    inside = (qx >= 0) & (qx < sw) & (qy >= 0) & (qy < sh)
    flat = qy * sw + qx  # flat indices: one gather per image instead of boolean masks
    flat[~inside] = 0
    hit = inside & em.near_edge.ravel()[flat]
    i, j = np.nonzero(hit)
    f = flat[i, j]
    qgx, qgy = em.gx.ravel()[f], em.gy.ravel()[f]
    along = qgx * nx[i] + qgy * ny[i]
    hit[i, j] = (np.abs(along) if either_way else -along) > 0.7 * np.hypot(qgx, qgy)
    return hit


def _pair_scales(em: _EdgeMap, sides: tuple[float, float], tolerance: float,
                 either_way: bool = False) -> list[float]:
    """The holder's size in the image over the expected size (within ``tolerance``), as
    measured from the distances at which opposite edges pair, and 1 (the expected size
    itself: a busy scene can outscore the holder's pairs) when that differs.

    For each side (short, long) the partners every edge pixel has within the tolerance are
    counted per distance (1/4-scale px). Every pair of the holder's sides gives a narrow
    peak (3 px: the grown edge), other edges a broad background that grows with the
    distance; a [1, 2, 1] filter less an 11 px mean keeps the peaks. A ratio scores the
    geometric mean of both sides' peaks there: the holder pairs at the same ratio on
    both, other things rarely do.
    """
    grid = np.arange(1 - tolerance, 1 + tolerance + 1e-9, 0.005)
    score = np.ones_like(grid)
    for e in sides:
        dist = np.arange(math.floor(e * (1 - tolerance)) - 6,
                         math.ceil(e * (1 + tolerance)) + 7, dtype=float)
        # every other edge pixel: the holder's sides have hundreds, and it halves the cost
        counts = (_partners(em, dist, 2, either_way).sum(axis=0)
                  + _partners(em, -dist, 2, either_way).sum(axis=0)).astype(float)
        peak = (np.convolve(counts, [0.25, 0.5, 0.25], "same")
                - np.convolve(counts, np.ones(11) / 11, "same"))
        score *= np.clip(np.interp(grid * e, dist, peak), 0.0, None)
    k = int(np.argmax(score))
    if score[k] <= 0 or abs(grid[k] - 1.0) < 0.005:
        return [1.0]
    return [float(grid[k]), 1.0]


def _peaks_at_size(em: _EdgeMap, eL: float, eS: float, max_peaks: int,
                   either_way: bool = False) -> _Peaks | None:
    """Centre voting (see :class:`FrameVotes`) for a holder of eL x eS (1/4-scale px): its
    peaks, or None where there is none.

    Every peak is handled at once (one distance matrix, one histogram, and in
    :func:`_boxes_at_peaks` one remap of all outlines): a loop over the peaks cost more in
    numpy calls than in arithmetic.
    """
    xs, ys, nx, ny = em.xs, em.ys, em.nx, em.ny
    sh, sw = em.near_edge.shape
    # only where the opposite side is there too: an edge a whole side away, its gradient
    # the other way (a circle, a single edge or another size does not pair)
    half = np.array([eS / 2, eL / 2, -eS / 2, -eL / 2])
    ok = _partners(em, 2 * half, either_way=either_way)  # (N, 4)
    ei, di = np.nonzero(ok)
    cx = np.rint(xs[ei] + half[di] * nx[ei]).astype(np.int64)
    cy = np.rint(ys[ei] + half[di] * ny[ei]).astype(np.int64)
    # the long sides' votes (pairs a short side apart) and the short sides' apart: the
    # centre is where both are, a bump along one midline (a plate's ends, a row of floor
    # holes pairing at one of the distances) has one only
    at = cy * sw + cx
    A_s, A_l = (cv2.GaussianBlur(np.bincount(at[di % 2 == k], minlength=sh * sw)
                                 .reshape(sh, sw).astype(np.float32), (0, 0), 1.2)
                for k in (0, 1))
    A = np.sqrt(A_s * A_l) + 0.25 * (A_s + A_l)
    peaks_mask = (cv2.dilate(A, np.ones((5, 5), np.uint8)) <= A) & (0.25 * A.max() < A)
    py, px = np.nonzero(peaks_mask)
    order = np.argsort(-A[py, px])[:max_peaks]
    ctrs = np.column_stack([px[order], py[order]]).astype(float)  # (P, 2)
    r_max = math.hypot(eL, eS) / 2 + 3
    near = ((xs[None] - ctrs[:, :1]) ** 2 + (ys[None] - ctrs[:, 1:]) ** 2) <= r_max ** 2
    keep = near.sum(axis=1) >= 10
    if not np.any(keep):
        return None
    return _Peaks(ei, cx, cy, ctrs[keep], near[keep])


def _boxes_at_peaks(em: _EdgeMap, peaks: _Peaks, eL: float, eS: float,
                    by_voters: bool = False) -> list[tuple[float, np.ndarray, str]]:
    """The box of eL x eS (1/4-scale px) at each peak: its side directions and long side
    (see :class:`FrameVotes`), as (outline score, 4 corners in full-res px, polarity)."""
    nx, ny, m = em.nx, em.ny, em.mag
    ctrs, near = peaks.ctrs, peaks.near
    n_p = len(ctrs)
    # the side directions: the dominant gradient orientation (mod 90 deg) around each peak
    # (by_voters: of the edge pixels whose votes landed within 2.5 px of it; all around a
    # peak with none)
    theta_px = np.degrees(np.arctan2(ny, nx)) % 90.0
    if by_voters:
        cx, cy = peaks.cx, peaks.cy
        voter = ((cx[None] - ctrs[:, :1]) ** 2 + (cy[None] - ctrs[:, 1:]) ** 2) <= 2.5 ** 2
        pv, vi = np.nonzero(voter)
        pn, nn = np.nonzero(near & ~np.any(voter, axis=1)[:, None])
        pi, ni = np.concatenate([pv, pn]), np.concatenate([peaks.ei[vi], nn])
    else:
        pi, ni = np.nonzero(near)
    th, wt = theta_px[ni], m[ni]
    hist = np.bincount(pi * 90 + th.astype(int) % 90, weights=wt,
                       minlength=n_p * 90).reshape(n_p, 90)
    wrapped = np.concatenate([hist[:, -2:], hist, hist[:, :2]], axis=1)
    smooth = sum(wrapped[:, k:k + 90] for k in range(5))
    t0 = np.argmax(smooth, axis=1) + 0.5
    # refine: magnitude-weighted circular mean of the orientations within +-3 deg
    dt = (th - t0[pi] + 45.0) % 90.0 - 45.0
    sel = np.abs(dt) < 3.0
    w_sum = np.bincount(pi[sel], weights=wt[sel], minlength=n_p)
    dt_sum = np.bincount(pi[sel], weights=wt[sel] * dt[sel], minlength=n_p)
    t0 = t0 + np.divide(dt_sum, w_sum, out=np.zeros(n_p), where=w_sum > 0)
    # the box of the expected size there, its long side either way, nudged by up to 3 px
    # (1/4 scale) to where its outline has the strongest gradient: a peak made by
    # something else (a disc's rim votes a small ring) has no such outline
    boxes = np.array([cv2.boxPoints(((float(c[0]), float(c[1])), (eL, eS), float(a)))
                      for c, t in zip(ctrs, t0, strict=True) for a in (t, t + 90.0)],
                     float).reshape(n_p, 2, 4, 2)
    sides, signed = _outline_sides(em.gx, em.gy, boxes.reshape(-1, 4, 2), _SHIFTS)
    sup = _support_score(sides).reshape(n_p, 2, len(_SHIFTS))
    j = np.argmax(sup, axis=2)  # (P, 2) best shift for either long-side direction
    s = np.take_along_axis(sup, j[..., None], axis=2)[..., 0]
    a = (s[:, 1] > s[:, 0]).astype(int)  # the first direction unless the second is better
    rows = np.arange(n_p)
    best = boxes[rows, a] + _SHIFTS[j[rows, a]][:, None, :]
    full = (best + 0.5) * _DOWN - 0.5
    # which way each side of the chosen box contrasts (outside brighter: a dark holder)
    side_sign = np.sign(signed.reshape(n_p, 2, len(_SHIFTS), 4)[rows, a, j[rows, a]])
    pols = ["dark" if np.all(v > 0) else "light" if np.all(v < 0) else "mixed"
            for v in side_sign]
    out = [(float(s[k, a[k]]), full[k], pols[k]) for k in range(n_p)]
    out.sort(key=lambda t: -t[0])
    return out


def _outline_support(gx: np.ndarray, gy: np.ndarray, boxes: np.ndarray,
                     shifts: np.ndarray | None = None) -> np.ndarray:
    """(B, K): for each box (B, 4, 2) and shift (K, 2): mean |gradient . normal| along the
    middle 80 % of its sides, times the square root of (weakest side / strongest side)."""
    return _support_score(_outline_sides(gx, gy, boxes, shifts)[0])


def _support_score(v: np.ndarray) -> np.ndarray:
    """The outline score from the per-side means (..., 4) of |gradient . normal|."""
    return v.mean(axis=-1) * np.sqrt(v.min(axis=-1) / (v.max(axis=-1) + 1e-9))


def _outline_sides(gx: np.ndarray, gy: np.ndarray, boxes: np.ndarray,
                   shifts: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(B, K, 4) twice: per box, shift and side, the mean of |gradient . outward normal|
    and of gradient . outward normal (> 0: the outside is brighter) along the middle 80 %
    of the side."""
    if shifts is None:
        shifts = np.zeros((1, 2))
    boxes = np.asarray(boxes, float).reshape(-1, 4, 2)
    ctr = boxes.mean(axis=1, keepdims=True)  # (B, 1, 2)
    p0 = boxes
    d = np.roll(boxes, -1, axis=1) - p0  # side i: corner i to i + 1
    ln = np.linalg.norm(d, axis=2, keepdims=True)
    n = np.stack([-d[..., 1], d[..., 0]], axis=2) / np.where(ln > 0, ln, 1.0)
    flip = np.sum((p0 + d / 2 - ctr) * n, axis=2, keepdims=True) < 0
    n = np.where(flip, -n, n)  # outward
    t = np.linspace(0.1, 0.9, 24)
    P = p0[:, :, None, :] + t[None, None, :, None] * d[:, :, None, :]  # (B, 4, 24, 2)
    nb, k = len(boxes), len(shifts)
    # float32, x and y apart: the arrays are (B x K x 96), and numpy's loops over a
    # trailing axis of 2 would cost more than the remap itself
    s = shifts.astype(np.float32)
    P32 = P.reshape(nb, 1, 96, 2).astype(np.float32)
    qx = (s[None, :, 0, None] + P32[..., 0]).reshape(nb * k, 96)
    qy = (s[None, :, 1, None] + P32[..., 1]).reshape(nb * k, 96)
    ax = cv2.remap(gx, qx, qy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    ay = cv2.remap(gy, qx, qy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    nxs = np.repeat(n[..., 0], 24, axis=1).astype(np.float32)[:, None]  # (B, 1, 96)
    nys = np.repeat(n[..., 1], 24, axis=1).astype(np.float32)[:, None]
    proj = ax.reshape(nb, k, 96) * nxs
    proj += ay.reshape(nb, k, 96) * nys
    proj = proj.reshape(nb, k, 4, 24)
    return (np.abs(proj).mean(axis=3, dtype=np.float64),
            proj.mean(axis=3, dtype=np.float64))
