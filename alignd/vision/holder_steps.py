"""A check of a found holder: is one of its sides the outer edge of a shadow?

A dark holder casts a shadow onto a bright disc: going outward across that side the image
steps twice the same way, holder -> shadow -> disc. When the shadow band is wider than the
coarse side search (+-10 px), the found rectangle can take the shadow's outer edge for the
side and still pass every other check: it is straight, of the right polarity, and with a
band a tenth of the holder wide it is within the size tolerance. It is then wrong by the
band's width (16 px on a corpus scene). A true side has the holder's own level just inside
it; a shadow's edge has the band's level there, between the holder's and the outside's.
A sample strip darker than the disc beside a dark holder is such a band too. So, stepping
the other way, is a strip darker still than a dark holder standing flush along its side
(a thin dark sample seen from above): holder and strip read as one larger dark rectangle,
an 8 px strip 8 px wrong, within the size tolerance. (A label or a sample on the holder
near a side does not look like either: the level just inside is the holder's, whatever
lies further in.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FAR_PX", "InnerStep", "inner_step", "side_frame", "side_ratios"]

# levels are medians over positions along the middle 60 % of a side, each the mean of a
# few pixels at a depth band (px, + outward): outside, just inside (and deeper inside)
_OUT, _IN = (4.0, 7.0), (-7.0, -4.0)
# ... and nearer, for a sharp side (one whose outside has settled within _NEAR[1] px of
# it): a band only 3-7 px wide (a hard shadow beside a sharp holder) lies there
_NEAR = (-3.5, -2.0)
_SETTLED = 0.1  # sharp: the outside's level 2-3.5 px out within this of the step of 4-7 px
FAR_PX = 24.0  # the inner step is looked for this deep (at most 0.35 of the extent across)
# the level just inside a side differing from the level deeper inside and from the
# holder's interior (the median over its middle) the same way as the side's own step, by
# at least this fraction of that step, flags the side (docs/vision.md: the corpus' values;
# 0.3 until a dark strip beside a dark holder read 0.22, and 0.15 flagged right holders
# when the configured size was 5 % small)
_MIN_RATIO = 0.2
_MIN_STEP_DN = 8.0  # and at least this, in grey levels (texture and noise stay below)
# ... or at least _EDGE_RATIO where the inner step is an edge: as sharp as a side (its 25-75 %
# rise within _EDGE_WIDTH_PX) and at least _EDGE_DEPTH_PX inside (a sample plate 13.5 px
# wide beside a light holder, 25 DN darker than it on a 130 DN step, read 0.18: seed 9100
# #291, returned 13.5 px wrong; the right holders of two corpora read up to 0.18 too, but
# their inner steps were 3-5 px in, the side's own transition, or 4-16 px wide, shading)
_EDGE_RATIO, _EDGE_WIDTH_PX, _EDGE_DEPTH_PX = 0.1, 3, 6.0


@dataclass(frozen=True)
class InnerStep:
    """Side ``side`` (from corner ``side`` to ``side + 1``) has a second step
    ``depth_px`` inside it: the holder's true side is likely there."""

    side: int
    ratio: float  # the inner step over the side's own step
    depth_px: float  # from the found side inward to the inner step's half-way level
    inward: tuple[float, float]  # the side's unit normal toward the holder's inside


def _sample_points(gray: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Nearest-pixel grey levels at the points ``p`` (..., 2), as float32."""
    h, w = gray.shape
    x = np.clip(np.rint(p[..., 0]).astype(np.intp), 0, w - 1)
    y = np.clip(np.rint(p[..., 1]).astype(np.intp), 0, h - 1)
    return gray[y, x].astype(np.float32)


def _face_points() -> tuple[np.ndarray, np.ndarray]:
    """The (s, r) fractions across the quadrilateral that :func:`_interior` reads."""
    s, r = np.meshgrid(np.linspace(0.1, 0.9, 17), np.linspace(0.1, 0.9, 17))
    near = np.minimum(np.minimum(s, 1 - s), np.minimum(r, 1 - r)) <= 0.2 + 1e-9
    return s[near], r[near]


_FACE = _face_points()


def _interior(gray: np.ndarray, c: np.ndarray) -> float:
    """The median grey level over the quadrilateral's face near its sides (0.1-0.2 of the
    way in from each, 0.1-0.9 along it): the holder's own level. Not its middle: a label
    as large as half the face made that the label's level, and a band just inside a side
    over the floor's level then read as the holder's (a ring 8-16 px beyond a side taken
    for it, tests/test_vision_holder_beyond.py). A band along one side (what the check
    looks for), even 0.35 of the way across, covers under 40 % of these points."""
    s, r = _FACE
    p = ((1 - s) * (1 - r))[..., None] * c[0] + (s * (1 - r))[..., None] * c[1] \
        + (s * r)[..., None] * c[2] + ((1 - s) * r)[..., None] * c[3]
    return float(np.median(_sample_points(gray, p)))


def side_frame(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each side k's vector (corner k to k + 1), its length and its outward unit normal,
    of the quadrilateral ``c`` (4, 2, cyclic order)."""
    nxt = c[[1, 2, 3, 0]]
    edge = nxt - c
    length = np.linalg.norm(edge, axis=1)
    n = np.stack([-edge[:, 1], edge[:, 0]], axis=1) / np.maximum(length, 1e-9)[:, None]
    n[np.sum(((c + nxt) / 2 - c.mean(axis=0)) * n, axis=1) < 0] *= -1
    return edge, length, n


def side_ratios(gray: np.ndarray, corners: np.ndarray, far_px: float = FAR_PX
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per side of ``corners`` (4, 2, cyclic order): the level just inside it minus the
    level deeper inside (``far_px``, at most 0.35 of the extent across), and minus the
    holder's interior level, each in size over the side's own step (0 where the two
    differ in sign, or either is under ``_MIN_STEP_DN``, or the holder is too narrow);
    and how deep "just inside" was (px: 4 for a soft side, 2 for a sharp one, see
    ``_NEAR``)."""
    c = np.asarray(corners, float)
    edge, length, n = side_frame(c)
    zero = np.zeros(4)
    if length.min() < 8.0:
        return zero, zero, np.full(4, -_IN[1])
    far = np.minimum(far_px, 0.35 * length[[1, 2, 3, 0]])  # the extent across each side
    frac = np.linspace(0.2, 0.8, 16)
    band = np.arange(4.0)
    # depths per side: just inside, outside, the deep band (from -far, 4 px), and nearer
    # inside and outside (every 0.5 px)
    near = np.arange(4) * 0.5
    depths = np.concatenate([np.broadcast_to(np.arange(_IN[0], _IN[1] + 0.5), (4, 4)),
                             np.broadcast_to(np.arange(_OUT[0], _OUT[1] + 0.5), (4, 4)),
                             -far[:, None] + band[None],
                             np.broadcast_to(_NEAR[0] + near, (4, 4)),
                             np.broadcast_to(-_NEAR[1] + near, (4, 4))], axis=1)  # (4, 20)
    p = (c[:, None, None] + frac[None, :, None, None] * edge[:, None, None]
         + depths[:, None, :, None] * n[:, None, None])
    v = _sample_points(gray, p)  # (side, position, depth)
    inn, out, deep = v[..., :4].mean(axis=2), v[..., 4:8].mean(axis=2), v[..., 8:12].mean(axis=2)
    step = np.median(out - inn, axis=1)
    # a sharp side's outside has settled 2 px out: so has its inside, 2 px in, and a
    # level there unlike the deeper one is a second step (a band narrower than 4 px
    # reaches past the usual probe)
    sharp = np.abs(np.median(v[..., 16:20].mean(axis=2) - out, axis=1)) \
        <= _SETTLED * np.abs(step)
    inn = np.where(sharp[:, None], v[..., 12:16].mean(axis=2), inn)
    step = np.median(out - inn, axis=1)
    to_deep = np.median(inn - deep, axis=1)
    to_level = np.median(inn, axis=1) - _interior(gray, c)
    ok = (np.abs(step) > 1e-6) & (far > -_IN[0])
    out_r = []
    # the band just inside toward the outside's level (a shadow's band), or away from it
    # (a strip darker than a dark holder along it): both bands one way
    agree = to_deep * to_level > 0
    for d in (to_deep, to_level):
        good = ok & agree & (np.abs(d) >= _MIN_STEP_DN)
        out_r.append(np.where(good, np.abs(d) / np.where(good, np.abs(step), 1.0), 0.0))
    return out_r[0], out_r[1], np.where(sharp, -_NEAR[1], -_IN[1])


def inner_step(gray: np.ndarray, corners: np.ndarray, *, side: int | None = None,
               far_px: float = FAR_PX) -> InnerStep | None:
    """The side of the quadrilateral ``corners`` (4, 2, in cyclic order) whose inside
    band differs most, one way, from both the holder's level (its interior's median) and
    the level deeper inside, with a step between the two: a shadow's edge (or a strip's
    along the holder) taken for the side; else None. (Tracking runs it every frame: the four
    sides' bands are read in one go, about 0.3 ms.) ``side``: that side only; ``far_px``:
    how deep to look (:data:`FAR_PX`; at most 0.35 of the extent across)."""
    c = np.asarray(corners, float)
    r_deep, r_level, start = side_ratios(gray, c, far_px)
    ratio = np.minimum(r_deep, r_level)
    k = int(np.argmax(ratio)) if side is None else side
    if ratio[k] < _EDGE_RATIO:
        return None
    edge, length, n = side_frame(c)
    far = min(far_px, 0.35 * float(length[(k + 1) % 4]))
    found = _inner_depth(gray, c[k], edge[k] / length[k], n[k], float(length[k]), far,
                         float(start[k]))
    if found is None:
        return None
    depth, width = found
    if ratio[k] < _MIN_RATIO and not (width <= _EDGE_WIDTH_PX and depth >= _EDGE_DEPTH_PX):
        return None
    return InnerStep(k, float(ratio[k]), depth, (float(-n[k, 0]), float(-n[k, 1])))


def _inner_depth(gray: np.ndarray, a: np.ndarray, u: np.ndarray, n: np.ndarray,
                 length: float, far: float, start: float = -_IN[1]
                 ) -> tuple[float, int] | None:
    """How far inside the side (from corner ``a`` along ``u``, ``n`` outward) the median
    profile, going inward, first passes half-way from the level just inside to the level
    ``far`` inside: the inner step, where the holder's true side likely is; and over how
    many px it rises from a quarter to three quarters of the way (None when there is no
    such step, only a slow change)."""
    frac = np.linspace(0.2, 0.8, 16)
    depths = np.arange(-start, -far - 0.5, -1.0)  # from just inside (start px), inward
    p = a + (frac[:, None, None] * length) * u + depths[None, :, None] * n
    prof = np.median(_sample_points(gray, p), axis=0)
    half = 0.5 * (float(prof[:3].mean()) + float(prof[-3:].mean()))
    toward = np.sign(prof[0] - half)  # the profile's way from just inside to deep inside

    def first_past(level: float) -> int | None:
        i = np.nonzero((prof - level) * toward <= 0)[0]
        return int(i[0]) if i.size else None

    past = first_past(half)
    # a step: the profile crosses half-way within a few px (a blurred edge), not by a
    # slow change over the whole depth (a soft shadow, the light's gradient)
    lo = first_past(0.75 * float(prof[0]) + 0.25 * float(prof[-1]))
    hi = first_past(0.25 * float(prof[0]) + 0.75 * float(prof[-1]))
    if past is None or lo is None or hi is None or hi - lo > 8:
        return None
    return float(-depths[past]), hi - lo
