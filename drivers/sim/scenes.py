"""Randomised camera scenes with exact truth: what real rigs vary, not what we drew once.

Every scene is drawn directly in pixel space (no world model) so that its truth is exact:
the measured outlines (the holder, the sample beside it, the turntable disc, the side
camera's pole and sample silhouette) use the renderer's exact pixel-area coverage
(:mod:`drivers.sim.render`, including radial lens distortion); everything that is not
measured (textures, screws, labels and text, cables, speculars) is drawn anti-aliased at
4x and area-averaged. Light is multiplicative (gradient, vignetting, soft and cast
shadows), then defocus, shot and read noise, quantisation to 8 bit or 12 bit (stored in 16,
LSB or MSB aligned) and optionally a JPEG round trip (UVC cameras stream MJPEG).

- :func:`random_top_scene`: the top camera. The holder is darker or lighter than its
  surroundings; the turntable disc brighter, darker or absent; pixel scales 50-250 um/px,
  holder sizes 20-100 mm, aspect 1-2.5, any image rotation (camera roll); distractors: screws
  and a label with text on the holder, cables, floor holes and screws, a second rectangle of
  another size; soft and cast shadows, speculars; vignetting, defocus, lens distortion.
- :func:`random_side_scene`: the side camera. A narrow full-height pole and the sample's
  silhouette, in either order and either contrast, the sample spanning the full height or
  standing on a holder and a platform; uneven light; the regions of interest a config
  would give. Drawn at 4 sub-columns per pixel and defocused before the pixels integrate
  (a lens blurs the light, not the pixels).
- :func:`random_rim_scene`: the turntable rim (e 0.01-0.2), brighter or darker than the
  floor, partly hidden by the holder, cables and shadows.

Scenes are reproducible from the generator passed in. Some choices keep the truth exact
and the task defined, and are stated where made: nothing unmeasured crosses a measured
outline (cables and speculars keep clear of the holder's sides), a sample beside the holder
differs from it in the sense opposite to the holder's own contrast, a second rectangle differs
from the holder's size by at least 30 %, the pole stands clear of the sample by twice its
width.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np

from drivers.config import ToneCurve
from drivers.sim.render import Conic, Polygon, Raster, coverage, mjpeg, tone_curve
from drivers.tone_curves import is_linear

__all__ = [
    "RIM_CATEGORIES",
    "SIDE_CATEGORIES",
    "TOP_CATEGORIES",
    "Defocus",
    "RimSceneSample",
    "SideSceneSample",
    "TopSceneSample",
    "Turn",
    "disc_defocus_scene",
    "disc_kernel",
    "ellipse_conic",
    "hard_shadow_scene",
    "hole_beside_scene",
    "random_rim_scene",
    "random_side_scene",
    "random_top_scene",
    "soft_band_scene",
    "strip_under_scene",
]

Defocus = Literal["gaussian", "disc"]  # a blur's shape (:func:`random_top_scene`)
TopCategory = Literal["plain", "distractors", "shadows", "optics", "jpeg", "12-bit", "everything"]
TOP_CATEGORIES: tuple[TopCategory, ...] = ("plain", "distractors", "shadows", "optics", "jpeg",
                                           "12-bit", "everything")
SideCategory = Literal["full-height sample", "sample on holder", "uneven light", "jpeg",
                       "12-bit"]
SIDE_CATEGORIES: tuple[SideCategory, ...] = ("full-height sample", "sample on holder",
                                             "uneven light", "jpeg", "12-bit")
RimCategory = Literal["clear", "occluded", "dark disc", "jpeg"]
RIM_CATEGORIES: tuple[RimCategory, ...] = ("clear", "occluded", "dark disc", "jpeg")


@dataclass(frozen=True)
class Encoding:
    """How the frame leaves the camera: bit depth, alignment in 16 bit, JPEG quality."""

    bits: Literal[8, 12] = 8
    msb_aligned: bool = False  # 12-bit values shifted into the top of 16 bits
    jpeg_quality: int | None = None
    gamma: ToneCurve = 1.0  # the tone curve: values (light)^(1/gamma) of full scale, or a
    # named one (drivers.tone_curves), before coding


@dataclass(frozen=True)
class TopSceneSample:
    """A top-camera frame and its truth (corners in frame pixels, the drawn order)."""

    image: np.ndarray
    category: str
    corners_px: np.ndarray  # (4, 2), distorted (frame) pixels
    holder_size_mm: tuple[float, float]  # long, short
    pixel_size_um: float  # at the principal point, undistorted
    polarity: Literal["dark", "light"]
    lens: tuple[float, tuple[float, float], float] | None  # focal px, principal px, k1
    encoding: Encoding
    params: dict[str, object] = field(default_factory=dict)

    @property
    def expected_size_px(self) -> tuple[float, float]:
        return (self.holder_size_mm[0] * 1000.0 / self.pixel_size_um,
                self.holder_size_mm[1] * 1000.0 / self.pixel_size_um)


class _Views:
    """A view drawn as several frames: ``image`` and ``more_frames`` (each with its own
    noise and coding), as a camera streams them."""

    image: np.ndarray
    more_frames: tuple[np.ndarray, ...]

    @property
    def frames(self) -> tuple[np.ndarray, ...]:
        """Every frame of the view: ``image`` first."""
        return (self.image, *self.more_frames)


class FrameStream:
    """A view's further frames on demand, as a camera keeps streaming them: each call
    returns the next ``k``. ``asked`` lists the calls' k, ``drawing_s`` the process time
    spent drawing them (a camera's, not the measurement's)."""

    def __init__(self, frame: Callable[[int], np.ndarray]) -> None:
        self.frame = frame
        self.asked: list[int] = []
        self.drawing_s = 0.0

    def __call__(self, k: int) -> list[np.ndarray]:
        t0 = time.process_time()
        start = sum(self.asked)
        self.asked.append(k)
        out = [self.frame(start + j) for j in range(k)]
        self.drawing_s += time.process_time() - t0
        return out


@dataclass(frozen=True)
class SideSceneSample(_Views):
    """A side-camera frame and its truth (angles in deg from the image vertical, + when the
    line's top leans toward +x; tilt = sample - pole)."""

    image: np.ndarray
    category: str
    sample_angle_deg: float
    pole_angle_deg: float
    sample_x_px: tuple[float, float]  # both sample edges' x at the sample's middle row
    near_x_px: float  # x of the sample edge nearest the pole, at the sample's middle row
    pole_x_px: float  # pole centre x at the image's middle row
    sample_rows: tuple[int, int]
    pole_roi_px: tuple[int, int, int, int]  # x0, y0, x1, y1 (exclusive), as a config gives
    sample_roi_px: tuple[int, int, int, int]
    encoding: Encoding
    params: dict[str, object] = field(default_factory=dict)
    more_frames: tuple[np.ndarray, ...] = ()  # further frames of the view, own noise
    # j -> the view's frame j after ``frames`` (own noise; the same j, the same frame): as a
    # camera keeps streaming, for the pre-check's frame taking by its uncertainty
    further: Callable[[int], np.ndarray] | None = None

    @property
    def tilt_deg(self) -> float:
        return self.sample_angle_deg - self.pole_angle_deg

    def stream(self) -> FrameStream:
        """The view's further frames from the first on, as a new stream."""
        if self.further is None:
            raise ValueError("this side view was drawn without further frames")
        return FrameStream(self.further)


@dataclass(frozen=True)
class RimSceneSample(_Views):
    """A frame with the turntable rim and its truth (the outer ellipse)."""

    image: np.ndarray
    category: str
    center_px: tuple[float, float]
    axes_px: tuple[float, float]
    angle_deg: float
    eccentricity: float
    encoding: Encoding
    params: dict[str, object] = field(default_factory=dict)
    more_frames: tuple[np.ndarray, ...] = ()  # further frames of the view, own noise


# ---- drawing helpers -------------------------------------------------------------------
def ellipse_conic(center: tuple[float, float], a: float, b: float, angle_deg: float
                  ) -> np.ndarray:
    """3x3 conic matrix of an ellipse (semi-axes a, b; a along angle_deg, x toward y)."""
    t = math.radians(angle_deg)
    R = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    M = R @ np.diag([1 / a ** 2, 1 / b ** 2]) @ R.T
    c = np.asarray(center, float)
    C = np.zeros((3, 3))
    C[:2, :2] = M
    C[:2, 2] = C[2, :2] = -M @ c
    C[2, 2] = c @ M @ c - 1.0
    return C / np.abs(C).max()


def rectangle(center: np.ndarray | tuple[float, float], L: float, S: float,
              angle_deg: float) -> np.ndarray:
    """The corners (4, 2) of an L x S rectangle about ``center``, its L side turned
    ``angle_deg`` from +x toward +y, in order round it (the scenes' and the tests')."""
    center = np.asarray(center, float)
    t = math.radians(angle_deg)
    u = np.array([math.cos(t), math.sin(t)])
    v = np.array([-math.sin(t), math.cos(t)])
    return np.array([center - u * L / 2 - v * S / 2, center + u * L / 2 - v * S / 2,
                     center + u * L / 2 + v * S / 2, center - u * L / 2 + v * S / 2])


def _paint(img: np.ndarray, shape: Polygon | Conic, ras: Raster, level: float | np.ndarray,
           region: tuple[int, int, int, int] | None = None) -> None:
    """Composite ``level`` over img where ``shape`` covers it (exact pixel-area coverage)."""
    h, w = img.shape
    if region is None:
        if isinstance(shape, Polygon):
            b = shape.bbox(ras)
            region = (max(0, math.floor(b[0])), max(0, math.floor(b[1])),
                      min(w, math.ceil(b[2]) + 1), min(h, math.ceil(b[3]) + 1))
        else:
            region = (0, 0, w, h)
    x0, y0, x1, y1 = region
    if x1 <= x0 or y1 <= y0:
        return
    cov = coverage(shape, ras, region)
    sub = img[y0:y1, x0:x1]
    lv = level if np.isscalar(level) else np.asarray(level)[y0:y1, x0:x1]
    sub += (lv - sub) * cov


def _aa_mask(shape: tuple[int, int], draw: Callable[[np.ndarray, int], None]) -> np.ndarray:
    """An anti-aliased coverage mask: ``draw(mask4, shift)`` draws at 4x in 8-bit,
    the result is area-averaged back (for what is not measured: cables, text, screws)."""
    h, w = shape
    big = np.zeros((h * 4, w * 4), np.uint8)
    draw(big, 4)
    return cv2.resize(big, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


def _texture(rng: np.random.Generator, shape: tuple[int, int], scale_px: float,
             amp: float) -> np.ndarray:
    """Smooth random texture of about ``scale_px`` correlation length, std ``amp``."""
    h, w = shape
    sh, sw = max(2, int(h / scale_px) + 2), max(2, int(w / scale_px) + 2)
    t = cv2.resize(rng.standard_normal((sh, sw)).astype(np.float32), (w, h),
                   interpolation=cv2.INTER_CUBIC)
    s = float(t.std()) or 1.0
    return t * np.float32(amp / s)


def _light(rng: np.random.Generator, shape: tuple[int, int], *, gradient: float,
           vignetting: float, shadow: bool) -> tuple[np.ndarray, dict[str, object]]:
    """Multiplicative illumination: gradient, vignetting and a soft partial shadow."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    gx, gy = rng.uniform(-gradient, gradient, 2)
    L = 1.0 + np.float32(gx) * (xx / w - 0.5) + np.float32(gy) * (yy / h - 0.5)
    info: dict[str, object] = {"gradient": (float(gx), float(gy))}
    if vignetting > 0:
        cx, cy = w / 2 + rng.uniform(-0.1, 0.1) * w, h / 2 + rng.uniform(-0.1, 0.1) * h
        r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / float((w / 2) ** 2 + (h / 2) ** 2)
        L *= 1.0 - np.float32(vignetting) * r2
        info["vignetting"] = vignetting
    if shadow:
        a = rng.uniform(0, 2 * math.pi)
        px, py = rng.uniform(0.2, 0.8) * w, rng.uniform(0.2, 0.8) * h
        soft = rng.uniform(4.0, 60.0)
        depth = rng.uniform(0.1, 0.4)
        t = np.tanh(((xx - px) * math.cos(a) + (yy - py) * math.sin(a)) / soft)
        L *= 1.0 - np.float32(depth / 2) * (1.0 + t)
        info["soft_shadow"] = {"softness_px": soft, "depth": depth}
    return L.astype(np.float32), info


def _finish(img: np.ndarray, rng: np.random.Generator, *, blur: float, read_noise: float,
            electrons_per_dn: float, enc: Encoding) -> np.ndarray:
    """Defocus, noise, the tone curve, quantisation and coding of an image in 8-bit DN
    (float)."""
    if blur > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur, borderType=cv2.BORDER_REFLECT)
    scale = 4095.0 / 255.0 if enc.bits == 12 else 1.0
    img = img * np.float32(scale)
    var = np.float32((read_noise * scale) ** 2) + np.clip(img, 0, None) * np.float32(
        scale / electrons_per_dn)
    img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.sqrt(var)
    if not is_linear(enc.gamma):
        img = tone_curve(img, enc.gamma, 4095.0 if enc.bits == 12 else 255.0)
    np.rint(img, out=img)
    if enc.bits == 12:
        out16 = np.clip(img, 0, 4095).astype(np.uint16)
        return out16 << 4 if enc.msb_aligned else out16
    out = np.clip(img, 0, 255).astype(np.uint8)
    if enc.jpeg_quality is not None:
        out = mjpeg(out, enc.jpeg_quality)
    return out


def _drawn_8bit(img: np.ndarray, blur_px: float, noise_dn: float, seed: int) -> np.ndarray:
    """A drawn scene's exact levels as an 8-bit frame: blurred by a Gaussian of
    ``blur_px`` (0: not), with read noise of ``noise_dn`` (rms) from ``seed``, rounded and
    clipped."""
    img = img.astype(np.float32)
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    noise = np.random.default_rng(seed).normal(0, noise_dn, img.shape)
    return np.clip(np.rint(img + noise), 0, 255).astype(np.uint8)


def _encoding(rng: np.random.Generator, category: str) -> Encoding:
    if category == "jpeg" or (category == "everything" and rng.random() < 0.4):
        return Encoding(8, False, int(rng.integers(60, 96)))
    if category == "12-bit" or (category == "everything" and rng.random() < 0.3):
        return Encoding(12, bool(rng.random() < 0.5), None)
    return Encoding()


def _dist_to_poly(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Signed distance (px, + inside) of points to a convex polygon."""
    c = poly.astype(np.float32).reshape(-1, 1, 2)
    return np.array([cv2.pointPolygonTest(c, (float(p[0]), float(p[1])), True) for p in pts])


def _bezier(rng: np.random.Generator, w: int, h: int, n: int = 80) -> np.ndarray:
    """A cable: a cubic curve entering and leaving through the image border."""
    def border() -> np.ndarray:
        s = int(rng.integers(4))
        t = rng.uniform(0, 1)
        return np.array([[t * w, -10.0], [w + 10.0, t * h], [t * w, h + 10.0],
                         [-10.0, t * h]][s])
    p0, p3 = border(), border()
    p1 = np.array([rng.uniform(0, w), rng.uniform(0, h)])
    p2 = np.array([rng.uniform(0, w), rng.uniform(0, h)])
    t = np.linspace(0, 1, n)[:, None]
    return ((1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t ** 2 * p2
            + t ** 3 * p3)


def _draw_cables(rng: np.random.Generator, img: np.ndarray, n: int,
                 keep_out: list[np.ndarray], clearance: float,
                 layers: list[tuple[np.ndarray, float]] | None = None) -> int:
    """Draw up to n cables that stay ``clearance`` px outside every keep-out polygon;
    ``layers`` (optional) receives each cable's coverage mask and level, to draw it again."""
    h, w = img.shape
    drawn = 0
    for _ in range(n * 6):
        if drawn >= n:
            break
        curve = _bezier(rng, w, h)
        width = rng.uniform(3.0, 12.0)
        if any(np.max(_dist_to_poly(curve, k)) > -(clearance + width) for k in keep_out):
            continue
        pts = np.round(curve * 16).astype(np.int32).reshape(-1, 1, 2)

        def draw(m: np.ndarray, s: int, pts: np.ndarray = pts, width: float = width) -> None:
            cv2.polylines(m, [pts * s], False, 255, thickness=max(1, round(width * s)),
                          lineType=cv2.LINE_AA, shift=4)
        mask = _aa_mask((h, w), draw)
        level = rng.choice([rng.uniform(10, 50), rng.uniform(180, 240)])
        img += (np.float32(level) - img) * mask
        if layers is not None:
            layers.append((mask, float(level)))
        drawn += 1
    return drawn


def _draw_circles(img: np.ndarray, centers: np.ndarray, radii: np.ndarray,
                  levels: np.ndarray) -> None:
    h, w = img.shape
    for (cx, cy), r, lv in zip(centers, radii, levels, strict=True):
        x0, y0 = max(int(cx - r - 3), 0), max(int(cy - r - 3), 0)
        x1, y1 = min(int(cx + r + 4), w), min(int(cy + r + 4), h)
        if x1 <= x0 or y1 <= y0:
            continue

        def draw(m: np.ndarray, s: int, cx: float = cx, cy: float = cy, r: float = r,
                 x0: int = x0, y0: int = y0) -> None:
            cv2.circle(m, (round((cx - x0) * s * 16), round((cy - y0) * s * 16)),
                       round(r * s * 16), 255, -1, cv2.LINE_AA, 4)
        mask = _aa_mask((y1 - y0, x1 - x0), draw)
        sub = img[y0:y1, x0:x1]
        sub += (np.float32(lv) - sub) * mask


def _speculars(rng: np.random.Generator, shape: tuple[int, int], n: int,
               keep_out: list[np.ndarray]) -> np.ndarray:
    """Additive Gaussian highlights, each at least 3 sigma + 8 px from the keep-out outlines."""
    h, w = shape
    out = np.zeros(shape, np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    placed = 0
    for _ in range(n * 10):
        if placed >= n:
            break
        sig = rng.uniform(4.0, 25.0)
        p = np.array([[rng.uniform(0, w), rng.uniform(0, h)]])
        if any(abs(float(_dist_to_poly(p, k)[0])) < 3 * sig + 8 for k in keep_out):
            continue
        amp = rng.uniform(20, 70)
        out += np.float32(amp) * np.exp(-((xx - p[0, 0]) ** 2 + (yy - p[0, 1]) ** 2)
                                        / np.float32(2 * sig * sig))
        placed += 1
    return out


# ---- top camera --------------------------------------------------------------------------
@dataclass(frozen=True)
class Turn:
    """A top scene with the turntable turned: the holder, its sample plate, screws and label
    turned by ``deg`` about ``axis_px`` (undistorted px; + turns the image clockwise, as the
    design notes' R(a)); the floor, the disc (its faint texture too), the light, the cast
    shadow's offset, the cables and the holder face's faint texture stay where they are.
    The sensor noise is drawn from ``noise_seed`` (each frame its own)."""

    deg: float
    axis_px: tuple[float, float]
    noise_seed: int


def random_top_scene(rng: np.random.Generator, category: str | None = None,
                     size_px: tuple[int, int] = (1280, 720), *,
                     turn: Turn | None = None, defocus: Defocus = "gaussian"
                     ) -> TopSceneSample:
    """One randomised top-camera frame with its exact corners (see the module docstring).

    ``defocus``: the blur's shape, a Gaussian of the drawn blur or a lens out of focus, a
    disc of twice that radius (:func:`disc_kernel`; the same draws, so the same scenes).

    ``turn``: the same scene (the same draws from ``rng``) with the holder turned (a sweep's
    frame). Where the turn changes which of the scene's draws are kept (a cable or a
    second rectangle clear of the holder in one frame and not in another), the frames
    differ in more than the turn: compare their ``params``.
    """
    cat = str(category or TOP_CATEGORIES[int(rng.integers(len(TOP_CATEGORIES)))])
    every = cat == "everything"
    distract = cat == "distractors" or (every and rng.random() < 0.7)
    shadows = cat == "shadows" or (every and rng.random() < 0.7)
    optics = cat == "optics" or (every and rng.random() < 0.7)
    w, h = size_px
    enc = _encoding(rng, cat)
    # geometry: the holder must fit (any rotation) with room around it
    for _ in range(1000):
        px_um = float(rng.uniform(50, 250))
        L_mm = float(rng.uniform(20, 100))
        S_mm = L_mm / float(rng.uniform(1.0, 2.5))
        Lp, Sp = L_mm * 1000 / px_um, S_mm * 1000 / px_um
        if Sp >= 50 and math.hypot(Lp, Sp) <= 0.75 * h:
            break
    angle = float(rng.uniform(-180, 180))
    k1 = float(rng.uniform(-0.12, 0.12)) if optics and rng.random() < 0.7 else 0.0
    focal = float(rng.uniform(0.9, 1.6) * w)
    principal = (w / 2 - 0.5 + float(rng.uniform(-20, 20)),
                 h / 2 - 0.5 + float(rng.uniform(-20, 20)))
    ras = Raster(size_px, focal, principal, k1)
    sample_th = float(rng.uniform(3, 10)) * 1000 / px_um if rng.random() < 0.5 else 0.0
    margin = 25.0
    room = math.sqrt(max((h - 2 * margin - 2) ** 2 - Lp ** 2, 0.0))  # for Sp + 2 * sample
    # a plate as wide as the holder's short side would be a second holder-sized
    # rectangle: the plate is at most half of it
    sample_th = min(sample_th, (room - Sp) / 2, 0.5 * Sp)
    if sample_th < 8.0:
        sample_th = 0.0  # no room for a sample plate in this frame
    half = math.hypot(Lp, Sp + 2 * sample_th) / 2
    ctr = np.array([rng.uniform(margin + half, w - margin - half),
                    rng.uniform(margin + half, h - margin - half)])

    def drawn(ctr: np.ndarray, angle: float) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """The holder, its sample plate (along side 0-1, outside it) and their hull."""
        holder = rectangle(ctr, Lp, Sp, angle)
        sample = None
        if sample_th > 0:
            t = math.radians(angle)
            out_n = np.array([math.sin(t), -math.cos(t)])  # away from side 2-3
            sample = np.array([holder[0], holder[1], holder[1] + out_n * sample_th,
                               holder[0] + out_n * sample_th])
        outline = holder if sample is None else np.vstack([holder, sample[2:]])
        return holder, sample, cv2.convexHull(outline.astype(np.float32))[:, 0].astype(float)

    holder, sample, hull = drawn(ctr, angle)
    ctr0, hull0 = ctr, hull  # where the holder stands unturned (the disc is placed by it)
    if turn is not None:
        t = math.radians(turn.deg)
        axis = np.asarray(turn.axis_px, float)
        ctr = axis + np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]]) @ (
            ctr - axis)
        angle += turn.deg
        holder, sample, hull = drawn(ctr, angle)
    corners = ras.distort(holder)
    hull_px = ras.distort(hull)

    # levels: floor, disc (brighter, darker or absent), holder of either polarity
    disc_mode = str(rng.choice(["brighter", "darker", "absent"], p=[0.45, 0.3, 0.25]))
    cast = shadows and rng.random() < 0.7
    cast_depth = float(rng.uniform(0.1, 0.4)) if cast else 0.0
    floor, disc, hold = 200.0, 150.0, 40.0  # (replaced by the first levels that fit)
    pol: Literal["dark", "light"] = "dark"
    for _ in range(1000):
        floor = float(rng.uniform(25, 225))
        disc = floor
        if disc_mode == "brighter":
            disc = floor + float(rng.uniform(30, 130))
        elif disc_mode == "darker":
            disc = floor - float(rng.uniform(30, 130))
        if not 15 <= disc <= 235:
            continue
        pol = "dark" if rng.random() < 0.5 else "light"
        if pol == "dark":
            top = disc * (1 - cast_depth) - 30
            if top < 10:
                continue
            hold = float(rng.uniform(5, top))
        else:
            if disc + 40 > 240:
                continue
            hold = float(rng.uniform(disc + 40, 240))
        break
    params: dict[str, object] = {"pixel_size_um": px_um, "holder_mm": (L_mm, S_mm),
                                 "disc": disc_mode, "polarity": pol, "k1": k1,
                                 "sample_px": sample_th}
    img: np.ndarray = np.full((h, w), floor, np.float32)
    floor_kind = str(rng.choice(["smooth", "grain", "breadboard"]))
    img += _texture(rng, (h, w), rng.uniform(40, 200), rng.uniform(0, 8))
    if floor_kind == "grain":
        img += _texture(rng, (h, w), rng.uniform(1.5, 4), rng.uniform(2, 6))
    params["floor"] = floor_kind
    if floor_kind == "breadboard":  # an optical table: M6 holes on a 25 mm grid
        pitch = 25000 / px_um
        ox, oy = rng.uniform(0, pitch, 2)
        gx = np.arange(ox, w, pitch)
        gy = np.arange(oy, h, pitch)
        cs = np.array([(x, y) for x in gx for y in gy])
        if cs.size:
            r = np.full(len(cs), 3000 / px_um)
            _draw_circles(img, cs, r, np.full(len(cs), floor * 0.3))
    if disc_mode != "absent":
        e = float(rng.uniform(0.0, 0.2))
        need = float(np.max(np.linalg.norm(hull0 - ctr0, axis=1))) + 20
        b = float(rng.uniform(need / 0.98 + 5, max(need / 0.98 + 6, 1.5 * w)))
        a = b / math.sqrt(1 - e * e)
        # the disc centre, offset from the holder so that the holder stays inside
        off = rng.uniform(-1, 1, 2) * max(b - need, 0.0) * 0.5
        dctr = ctr0 + off
        dang = float(rng.uniform(-90, 90))
        ring = rng.random() < 0.4
        disc_tex = disc + _texture(rng, (h, w), rng.uniform(2, 30), rng.uniform(0.5, 3))
        if ring:
            rw = float(rng.uniform(4, 20))
            rl = float(np.clip(disc + rng.choice([-1, 1]) * rng.uniform(20, 60), 10, 245))
            _paint(img, Conic(ellipse_conic(tuple(dctr), a, b, dang)), ras, rl)
            _paint(img, Conic(ellipse_conic(tuple(dctr), a - rw, b - rw, dang)), ras, disc_tex)
        else:
            _paint(img, Conic(ellipse_conic(tuple(dctr), a, b, dang)), ras, disc_tex)
        params["disc_e"] = e
    keep_out = [hull_px]
    if distract:
        # floor/disc screws away from the holder
        n = int(rng.integers(2, 8))
        cs = np.column_stack([rng.uniform(0, w, n), rng.uniform(0, h, n)])
        rr = rng.uniform(3, 10, n)
        far = _dist_to_poly(cs, hull_px) < -(rr + 15)
        _draw_circles(img, cs[far], rr[far], rng.uniform(10, 240, n)[far])
        # a second rectangle that is not the holder: at least 30 % off in size
        for _ in range(50):
            f = float(rng.choice([rng.uniform(0.35, 0.7), rng.uniform(1.3, 1.7)]))
            L2 = Lp * f
            S2 = min(L2 / rng.uniform(1.0, 2.5), Sp * float(rng.uniform(0.4, 2.0)))
            c2 = np.array([rng.uniform(0, w), rng.uniform(0, h)])
            r2 = rectangle(c2, L2, S2, float(rng.uniform(-180, 180)))
            if np.min(-_dist_to_poly(r2, hull)) < 25 or np.any(
                    _dist_to_poly(hull, r2) > -25):
                continue
            lv2 = float(rng.choice([rng.uniform(5, 60), rng.uniform(190, 250)]))
            _paint(img, Polygon(r2), ras, lv2)
            keep_out.append(ras.distort(r2))
            params["second_rectangle"] = (L2, S2)
            break
    # the holder's cast shadow on the ground
    if cast:
        dx, dy = rng.uniform(-18, 18, 2)
        shade_blur = float(rng.uniform(2, 10))  # (recorded: the corpus' worst sides sit by it)
        mask: np.ndarray = np.zeros((h, w), np.float32)
        pts = np.round((hull_px + np.array([dx, dy])) * 16).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 1.0, lineType=cv2.LINE_AA, shift=4)
        mask = cv2.GaussianBlur(mask, (0, 0), shade_blur)
        np.multiply(img, 1.0 - cast_depth * mask, out=img, casting="unsafe")
        params["cast_shadow"] = {"offset_px": (float(dx), float(dy)), "depth": cast_depth,
                                 "blur_px": shade_blur}
    # holder and sample (exact coverage)
    hold_map = hold + _texture(rng, (h, w), rng.uniform(2, 40), rng.uniform(0.3, 2.0))
    if sample is None:
        _paint(img, Polygon(holder), ras, hold_map)
    else:
        # one composite for both: painting them in turn would let the ground show
        # through their shared side (each covers part of those pixels)
        lv = (float(rng.uniform(hold + 30, 250)) if pol == "dark" and hold + 30 < 250 else
              float(rng.uniform(5, max(hold - 30, 6))))
        hp, sp = Polygon(holder), Polygon(sample)
        b1, b2 = hp.bbox(ras), sp.bbox(ras)
        region = (max(0, math.floor(min(b1[0], b2[0]))), max(0, math.floor(min(b1[1], b2[1]))),
                  min(w, math.ceil(max(b1[2], b2[2])) + 1),
                  min(h, math.ceil(max(b1[3], b2[3])) + 1))
        x0, y0, x1, y1 = region
        ch, cs = coverage(hp, ras, region), coverage(sp, ras, region)
        sub = img[y0:y1, x0:x1]
        img[y0:y1, x0:x1] = (sub * np.clip(1.0 - ch - cs, 0.0, 1.0)
                             + hold_map[y0:y1, x0:x1] * ch + np.float32(lv) * cs)
    if distract:
        _holder_furniture(rng, img, holder, Lp, Sp, angle, hold, params)
        params["cables"] = _draw_cables(rng, img, int(rng.integers(1, 4)), keep_out=[hull_px],
                                        clearance=12.0)
    light, info = _light(rng, (h, w), gradient=0.4 if shadows or optics else 0.2,
                         vignetting=float(rng.uniform(0.1, 0.45)) if optics else 0.0,
                         shadow=shadows and rng.random() < 0.7)
    params.update(info)
    if shadows:
        inner = rectangle(ctr, Lp - 40, Sp - 40, angle) if Sp > 80 else None
        spec = _speculars(rng, (h, w), int(rng.integers(1, 4)), [hull_px])
        if inner is not None and rng.random() < 0.5:  # a highlight on the holder's face
            c = ctr + rng.uniform(-0.2, 0.2, 2) * (Sp - 40)
            sig = min(Sp / 10, 15.0)
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
            spec += np.float32(rng.uniform(15, 50)) * np.exp(
                -((xx - c[0]) ** 2 + (yy - c[1]) ** 2) / np.float32(2 * sig * sig))
        img += spec
    img *= light
    blur = float(rng.uniform(0.8, 2.0)) if optics else float(rng.uniform(0.3, 1.0))
    read_noise = float(rng.uniform(0.5, 2.5))  # (drawn in this order: the corpus stays)
    electrons_per_dn = float(rng.uniform(20, 80))
    if defocus == "disc":  # a lens out of focus: a disc of twice the blur's radius
        img = cv2.filter2D(img, -1, disc_kernel(2.0 * blur), borderType=cv2.BORDER_REFLECT)
    out = _finish(img, rng if turn is None else np.random.default_rng(turn.noise_seed),
                  blur=blur if defocus == "gaussian" else 0.0, read_noise=read_noise,
                  electrons_per_dn=electrons_per_dn, enc=enc)
    # the sensor's noise model (8-bit DN), as bench/vision_bounds.py's bound needs it
    params.update(blur_px=blur, read_noise_dn=read_noise, electrons_per_dn=electrons_per_dn)
    return TopSceneSample(out, cat, corners, (max(L_mm, S_mm), min(L_mm, S_mm)), px_um, pol,
                          (focal, principal, k1) if k1 else None, enc, params)


def hard_shadow_scene(offset_px: float, angle_deg: float, seed: int = 0,
                      levels: tuple[float, float, float] = (210.0, 128.0, 85.0)
                      ) -> tuple[np.ndarray, np.ndarray]:
    """A sharp dark 303 x 193 px holder in a 1280 x 720 frame (``levels``: disc, shadow,
    holder DN; blur 0.49 px, noise 0.8 DN) with its hard cast shadow shifted by
    (``offset_px``, -0.73) px: a band that wide beside one or two sides, stepping the
    same way as the side (a small lamp's shadow; corpus #639 of seed 6100 had one, 5 px
    wide). Not in the random corpus, whose cast shadows are soft. The 8-bit frame and
    the holder's corners (exact pixel-area coverage)."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    disc, shade, dark = levels
    held = rectangle((492.4, 221.1), 303.2, 193.0, angle_deg)
    box = (0, 0, w, h)
    img = np.full((h, w), disc)
    img += (shade - img) * coverage(Polygon(held + np.array([offset_px, -0.73])), ras, box)
    img += (dark - img) * coverage(Polygon(held), ras, box)
    return _drawn_8bit(img, 0.49, 0.8, seed), held


def soft_band_scene(width_px: float, shadow_blur_px: float, angle_deg: float,
                    seed: int = 0, blur_px: float = 2.2,
                    levels: tuple[float, float] = (200.0, 60.0), across_px: float = 0.0,
                    supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A dark 260 x 160 px holder at ``angle_deg`` in a 1280 x 720 frame (``levels``: disc
    and holder DN) with its cast shadow, 35 % deep, shifted ``width_px`` along its long
    side and blurred ``shadow_blur_px`` (a Gaussian): a soft band that wide beyond one
    short side, whose outer step is softer than the holder's edge (the random corpus'
    cast shadows, one side's worth). The frame blurred ``blur_px`` (a defocused camera:
    both steps within a few blurs of each other), noise 1 DN. ``across_px``: the shadow
    shifted that far across the long sides as well (toward side 0 to 1's outside). The
    8-bit frame and the holder's corners (corner 1 to 2 the side beside the band).

    ``supersample``: drawn on a grid that many times finer, blurred there and each pixel
    the mean of its subpixels, as a camera forms it (its lens blurs the light, then each
    pixel gathers its area). Otherwise the blur is a kernel sampled at whole pixels over
    the pixels' areas, which departs from that near the pixel axes: a side at 8 deg then
    misfits one blurred step by 2-3 times its noise (docs/vision.md, "A shadow's edge at
    a side")."""
    f = supersample
    w, h = 1280, 720
    ras = Raster((w * f, h * f), 1000.0 * f, (w * f / 2, h * f / 2), 0.0)
    disc, dark = levels
    held = rectangle((640.3, 360.7), 260.0, 160.0, angle_deg)
    t = math.radians(angle_deg)
    u = np.array([math.cos(t), math.sin(t)])
    box = (0, 0, w * f, h * f)
    n = np.array([math.sin(t), -math.cos(t)])  # out of side 0 to 1

    def fine(p: np.ndarray) -> Polygon:  # (a pixel's centre is its subpixels' middle)
        return Polygon(p * f + (f - 1) / 2)

    shade = coverage(fine(held + width_px * u + across_px * n), ras, box).astype(np.float32)
    img = disc * (1.0 - 0.35 * cv2.GaussianBlur(shade, (0, 0), shadow_blur_px * f))
    img += (dark - img) * coverage(fine(held), ras, box)
    if f > 1:
        lens = cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur_px * f)
        return _drawn_8bit(lens.reshape(h, f, w, f).mean(axis=(1, 3)), 0.0, 1.0, seed), held
    return _drawn_8bit(img, blur_px, 1.0, seed), held


def disc_kernel(radius_px: float, sub: int = 16, across: int = 1) -> np.ndarray:
    """A lens' defocus: a uniform disc of ``radius_px``, each pixel's weight the share of
    ``sub`` x ``sub`` points within it that fall in the disc (normalised to 1). ``across``:
    the image's sub-columns per pixel (a side scene is drawn at :data:`_SIDE_SS`): the
    disc is then that many times as wide in its columns."""
    n, m = math.ceil(radius_px), math.ceil(radius_px * across)
    off = (np.arange(sub) + 0.5) / sub - 0.5
    k = np.zeros((2 * n + 1, 2 * m + 1))
    for i in range(-n, n + 1):
        for j in range(-m, m + 1):
            yy, xx = np.meshgrid(i + off, (j + off) / across, indexing="ij")
            k[i + n, j + m] = np.count_nonzero(xx * xx + yy * yy <= radius_px * radius_px)
    return (k / k.sum()).astype(np.float32)


def disc_defocus_scene(radius_px: float, angle_deg: float, seed: int = 0,
                       levels: tuple[float, float] = (200.0, 60.0), gauss_px: float = 0.0,
                       jpeg_quality: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A 260 x 160 px holder at ``angle_deg`` in a 1280 x 720 frame (``levels``: disc and
    holder DN) seen through a lens out of focus: blurred by a disc of ``radius_px``
    (:func:`disc_kernel`), not the Gaussian the random corpus uses, then by a Gaussian of
    ``gauss_px`` (0: none), noise 1 DN, and a JPEG round trip at ``jpeg_quality`` (None:
    none). The 8-bit frame and the holder's corners."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    disc, body = levels
    held = rectangle((640.3, 360.7), 260.0, 160.0, angle_deg)
    sharp = np.full((h, w), disc, np.float32)
    sharp += (body - sharp) * coverage(Polygon(held), ras, (0, 0, w, h)).astype(np.float32)
    out = _drawn_8bit(cv2.filter2D(sharp, -1, disc_kernel(radius_px)), gauss_px, 1.0, seed)
    return (out if jpeg_quality is None else mjpeg(out, jpeg_quality)), held


def plate_scene(insets_px: tuple[float, float, float, float], angle_deg: float,
                levels: tuple[float, float, float] = (60.0, 170.0, 230.0), seed: int = 0,
                k1: float = 0.0, centre_px: tuple[float, float] = (640.4, 360.1)
                ) -> tuple[np.ndarray, np.ndarray]:
    """A 303 x 193 px holder in a 1280 x 720 frame carrying a sample plate whose edges lie
    ``insets_px`` inside the holder's (the sides facing -v, +u, +v, -u of the holder's
    frame, u along its long side at ``angle_deg``); ``levels``: floor, holder, plate DN;
    blur 0.8 px, noise 1 DN. A plate a few px inside a side puts a second step in that
    side's edge windows (docs/vision.md, "A second step beside a side"). Not in the random
    corpus, whose labels keep 18 px clear. ``k1``: radial lens distortion (focal 1000 px,
    principal point the frame's centre: ``alignd.vision.lens.Lens(1000, (640, 360), k1)``);
    ``centre_px``: the holder's centre in the ideal image. The 8-bit frame and the
    holder's corners (in the frame)."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), k1)
    floor, body, plate = levels
    ctr = np.asarray(centre_px, float)
    t = math.radians(angle_deg)
    u, v = np.array([math.cos(t), math.sin(t)]), np.array([-math.sin(t), math.cos(t)])
    a, b, c, d = insets_px
    held = rectangle(ctr, 303.2, 193.0, angle_deg)
    inner = rectangle(ctr + u * (d - b) / 2 + v * (a - c) / 2, 303.2 - b - d, 193.0 - a - c,
                      angle_deg)
    box = (0, 0, w, h)
    img = np.full((h, w), float(floor))
    img += (body - img) * coverage(Polygon(held), ras, box)
    img += (plate - img) * coverage(Polygon(inner), ras, box)
    return _drawn_8bit(img, 0.8, 1.0, seed), ras.distort(held)


def sample_beside_scene(width_px: float, angle_deg: float,
                        levels: tuple[float, float, float] = (60.0, 150.0, 240.0),
                        seed: int = 0, blur_px: float = 0.8,
                        size_px: tuple[float, float] = (303.2, 193.0)
                        ) -> tuple[np.ndarray, np.ndarray]:
    """A holder of ``size_px`` (303 x 193 px) in a 1280 x 720 frame with a sample
    ``width_px`` wide along its first long side (-v of the holder's frame, u along its long
    side at ``angle_deg``); ``levels``: disc, holder, sample DN, the holder between the
    other two where the random corpus never puts it (its samples contrast the other way
    from the disc against the holder): a grey holder on a dark turntable with a white
    sample, and the like. Blur ``blur_px``, noise 1.5 DN. The 8-bit frame and the holder's
    corners."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    disc, body, sample = levels
    t = math.radians(angle_deg)
    v = np.array([-math.sin(t), math.cos(t)])
    held = rectangle((640.4, 380.1), size_px[0], size_px[1], angle_deg)
    strip = np.array([held[0], held[1], held[1] - width_px * v, held[0] - width_px * v])
    if float(np.dot(strip[2] - held[2], v)) > 0:  # corner 0 -> 1 is the +v side: flip
        strip = np.array([held[2], held[3], held[3] + width_px * v, held[2] + width_px * v])
    box = (0, 0, w, h)
    ch, cs = coverage(Polygon(held), ras, box), coverage(Polygon(strip), ras, box)
    img = disc * np.clip(1.0 - ch - cs, 0.0, 1.0) + body * ch + sample * cs
    return _drawn_8bit(img, blur_px, 1.5, seed), held


def cable_cut_scene(sag_px: float = 2.0, seed: int = 0, with_holder: bool = True
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 190 x 130 px light holder and, beside it, a light 190 x 320 px rectangle that a
    dark cable crosses so that the part above the cable is the holder's size; the cable
    bows by ``sag_px`` over the rectangle's width. Floor 60, holder and rectangle 200,
    cable 30 DN (9 px wide); blur 0.8 px, noise 1 DN, 1280 x 720 (new corpora drew such
    cuts: a rectangle 30 % off the holder's size cut to it by a cable). The 8-bit frame,
    the holder's corners and the cut part's (its lower side the cable's upper edge at the
    rectangle's ends). ``with_holder``: False leaves the holder out."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    held = rectangle((330.0, 260.0), 190.0, 130.0, 15.0)
    other = rectangle((880.0, 400.0), 320.0, 190.0, 90.0)  # its long side upright
    img = np.full((h, w), 60.0)
    for poly in (held, other) if with_holder else (other,):
        img += (200.0 - img) * coverage(Polygon(poly), ras, (0, 0, w, h))
    # the cable's upper edge 130 px below the rectangle's top at its ends, bowing down
    top, half = 400.0 - 160.0, 95.0
    xs = np.linspace(0.0, w - 1.0, 400)
    ys = top + 130.0 + 4.5 + sag_px * (1.0 - ((xs - 880.0) / half) ** 2)
    pts = np.round(np.column_stack([xs, ys]) * 16).astype(np.int32).reshape(-1, 1, 2)

    def draw(m: np.ndarray, s: int) -> None:
        cv2.polylines(m, [pts * s], False, 255, thickness=9 * s, lineType=cv2.LINE_AA,
                      shift=4)
    img += (30.0 - img) * _aa_mask((h, w), draw)
    frame = _drawn_8bit(img, 0.8, 1.0, seed)
    edge = top + 130.0  # the cable's upper edge at the rectangle's ends
    cut = np.array([[785.0, top], [975.0, top], [975.0, edge], [785.0, edge]])
    return frame, held, cut


def hole_beside_scene(angle_deg: float, short_side: bool, overlap: float, radius_px: float,
                      seed: int = 0, levels: tuple[float, float, float] = (165.0, 15.0, 50.0)
                      ) -> tuple[np.ndarray, np.ndarray]:
    """A 196 x 85 px dark holder at ``angle_deg`` in a 1280 x 720 frame on a light floor with
    a dark hole (a breadboard's tapped hole, ``radius_px``) beside the middle of a short
    side (else a long one), under the holder by ``overlap`` of its radius: the side
    passes the hole along part of its length, its step there a fraction of the rest (the
    corpus' breadboard floors, seed 2124 #767). ``levels``: floor, holder, hole DN. Blur
    1 px, noise 2 DN. The 8-bit frame and the holder's corners."""
    w, h = 1280, 720
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    floor, body, hole = levels
    held = rectangle((640.3, 360.7), 196.0, 85.0, angle_deg)
    a, b = (held[1], held[2]) if short_side else (held[0], held[1])
    mid = (a + b) / 2
    out = (mid - held.mean(axis=0)) / float(np.linalg.norm(mid - held.mean(axis=0)))
    centre = mid + out * radius_px * (1.0 - overlap)
    box = (0, 0, w, h)
    in_hole = coverage(Conic(ellipse_conic((float(centre[0]), float(centre[1])), radius_px,
                                           radius_px, 0.0)), ras, box)
    img = floor + (hole - floor) * in_hole
    img = img + (body - img) * coverage(Polygon(held), ras, box)
    return _drawn_8bit(img, 1.0, 2.0, seed), held


def strip_under_scene(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grey 347 x 195 px holder (95 DN) on a dark disc (35 DN) with a light label (165 DN,
    175 x 102 px) on it and a light strip (205 DN, 181 px wide) passing under it, from
    17 px below the frame's top to past its bottom. The strip's top end, its two sides
    above the holder and the label's lower edge frame a quadrilateral of about the
    holder's size (363-366 x 181 px; corpus #890 of seed 71100 at 800 x 600 drew such a
    scene and returned that quadrilateral ok, 233 px off). Blur 1 px, noise 1 DN,
    800 x 600. The 8-bit frame, the holder's corners and the quadrilateral's."""
    w, h = 800, 600
    ras = Raster((w, h), 1000.0, (w / 2, h / 2), 0.0)
    held = rectangle((330.4, 335.2), 347.0, 195.0, 1.0)
    strip = rectangle((290.3, 350.0), 660.0, 181.0, 92.0)
    label = rectangle((332.5, 334.1), 175.0, 102.0, 1.0)
    img = np.full((h, w), 35.0)
    for poly, level in ((strip, 205.0), (held, 95.0), (label, 165.0)):
        img += (level - img) * coverage(Polygon(poly), ras, (0, 0, w, h))
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 1.0)
    img += np.random.default_rng(seed).normal(0, 1.0, img.shape).astype(np.float32)
    by_y = strip[np.argsort(strip[:, 1])]
    top, low = by_y[:2], by_y[2:]
    lb = label[np.argsort(label[:, 1])[2:]]  # the label's lower edge
    ends = []
    for p in top:  # where the strip's sides meet the label's lower edge
        q = low[np.argmin(np.linalg.norm(low - p, axis=1))]
        t = np.linalg.solve(np.array([q - p, lb[0] - lb[1]]).T, lb[0] - p)[0]
        ends.append(p + t * (q - p))
    quad = np.array([top[0], top[1], ends[1], ends[0]])
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), held, quad


def _holder_furniture(rng: np.random.Generator, img: np.ndarray, holder: np.ndarray,
                      Lp: float, Sp: float, angle: float, hold: float,
                      params: dict[str, object]) -> None:
    """Screws near the holder's corners and a label with text, inside its face: clear of
    its sides by at least 18 px and 15 % of the short side."""
    inset = max(18.0, 0.15 * Sp)
    ctr = holder.mean(axis=0)
    t = math.radians(angle)
    u = np.array([math.cos(t), math.sin(t)])
    v = np.array([-math.sin(t), math.cos(t)])
    r = min(max(0.05 * Sp, 3.0), inset * 0.6)
    screws = [ctr + su * u * (Lp / 2 - inset) + sv * v * (Sp / 2 - inset)
              for su in (-1, 1) for sv in (-1, 1)]
    n = int(rng.integers(0, 5))
    if n:
        lv = float(rng.choice([rng.uniform(5, 40), rng.uniform(170, 240)]))
        _draw_circles(img, np.array(screws[:n]), np.full(n, r), np.full(n, lv))
    if rng.random() < 0.7 and Lp - 2 * inset > 30 and Sp - 2 * inset > 20:
        lw = (Lp - 2 * inset - 2 * r - 8) * rng.uniform(0.5, 0.9)
        lh = (Sp - 2 * inset) * rng.uniform(0.4, 0.8)
        lab = rectangle(ctr, max(lw, 10), lh, angle)
        label_lv = float(np.clip(hold + rng.choice([-1, 1]) * rng.uniform(40, 150), 5, 250))
        h, w = img.shape
        mask = np.zeros((h, w), np.float32)
        cv2.fillConvexPoly(mask, np.round(lab * 16).astype(np.int32), 1.0, cv2.LINE_AA, 4)
        img += (np.float32(label_lv) - img) * mask
        text = "".join(rng.choice(list("ABCDEFGHJKLMNPRSTUVWXYZ0123456789- /"), 8))
        scale = max(lh / 40.0, 0.3)
        box = np.zeros((int(lh * 1.5) + 4, int(max(lw, 10) * 1.5) + 4), np.uint8)
        cv2.putText(box, text, (2, int(lh * 0.9)), cv2.FONT_HERSHEY_SIMPLEX, scale, 255,
                    max(1, int(scale * 2)), cv2.LINE_AA)
        # put the text box into the label, rotated with the holder
        M = cv2.getRotationMatrix2D((box.shape[1] / 2, box.shape[0] / 2), -angle, 1.0)
        M[:, 2] += ctr - np.array([box.shape[1] / 2, box.shape[0] / 2])
        tm = cv2.warpAffine(box, M, (w, h)).astype(np.float32) / 255.0
        tm *= mask > 0.999
        text_lv = float(np.clip(label_lv + (-1 if label_lv > 128 else 1) * 100, 0, 255))
        img += (np.float32(text_lv) - img) * tm
        params["label"] = text


# ---- side camera ------------------------------------------------------------------------
_SIDE_SS = 4  # sub-columns per pixel column while drawing a side scene


def _stretch(img: np.ndarray, ss: int) -> np.ndarray:
    """A smooth map (texture, light) at ss x the width, interpolated."""
    h, w = img.shape
    return cv2.resize(img, (w * ss, h), interpolation=cv2.INTER_LINEAR)


def _wide(poly: np.ndarray, ss: int) -> Polygon:
    """A polygon (pixel coordinates) on the ss x wider drawing grid: exact area fractions
    of each sub-column (the map is linear). Pixel k spans [k - 1/2, k + 1/2) and is the mean
    of sub-columns ss k .. ss k + ss - 1, each spanning its index +- 1/2: x maps to
    ss x + (ss - 1) / 2 (without the offset every outline sat 0.375 px left of its truth)."""
    return Polygon(poly * np.array([float(ss), 1.0]) + np.array([(ss - 1) / 2, 0.0]))


def _polished_pole(rng: np.random.Generator, shape: tuple[int, int], ss: int,
                   top_left: np.ndarray, angle_deg: float, width_px: float, level: float
                   ) -> tuple[np.ndarray, dict[str, object]]:
    """A polished rod's levels on the ss x wider drawing grid: ``level`` shaded across it
    as a cylinder lit from one side (up to 40 % darker at one edge) plus a highlight, a
    Gaussian 0.5-2.5 px wide, 60-200 DN strong (short of full scale), its centre 8-92 % of
    the way across (a lamp beside the camera puts it mid-rod, one far off to the side near
    an edge)."""
    h, wss = shape
    x = (np.arange(wss) - (ss - 1) / 2) / ss  # pixel coordinates of the sub-columns
    y = np.arange(h, dtype=np.float64)[:, None]
    ta = math.tan(math.radians(angle_deg))
    u = (x[None, :] - (top_left[0] - (y - top_left[1]) * ta)) / width_px  # 0..1 across
    at = float(rng.uniform(0.08, 0.92))
    wide = float(rng.uniform(0.5, 2.5))
    amp = min(float(rng.uniform(60, 200)), max(240.0 - level, 30.0))  # short of full scale
    shade = float(rng.uniform(-0.4, 0.4))  # darker toward the edge away from the light
    lv = level * (1.0 - np.where(shade > 0, shade * np.clip(u, 0, 1),
                                 -shade * (1 - np.clip(u, 0, 1)))) + amp * np.exp(
        -0.5 * ((u - at) * width_px / wide) ** 2)
    info: dict[str, object] = {"highlight_at": at, "highlight_px": wide,
                               "highlight_dn": amp, "pole_shade": shade}
    return lv.astype(np.float32), info


def random_side_scene(rng: np.random.Generator, category: str | None = None,
                      size_px: tuple[int, int] = (1280, 720), frames: int = 1,
                      gamma: ToneCurve = 1.0, polished: bool = False,
                      defocus: Defocus = "gaussian") -> SideSceneSample:
    """One randomised side-camera view (see the module docstring); ``frames`` > 1 adds
    further frames of the same view with independent noise, as a camera streams them
    (``SideSceneSample.frames``). ``gamma``: the camera's tone curve, applied before the
    coding (:class:`Encoding`; the same draws as without it). ``polished``: the pole is a
    polished metal rod, as the thesis' was: a cylinder's shading across it and a specular
    highlight along it, anywhere across it (:func:`_polished_pole`; its draws come from a
    generator of its own, so the view's geometry, levels and first frame are, outside the
    pole, those drawn without it; its further frames' noise differs). ``defocus``: the
    blur's shape, a Gaussian of the drawn blur or a lens out of focus, a disc of twice
    that radius (the same draws, so the same views)."""
    cat = str(category or SIDE_CATEGORIES[int(rng.integers(len(SIDE_CATEGORIES)))])
    w, h = size_px
    enc = Encoding(8, False, int(rng.integers(60, 96))) if cat == "jpeg" else (
        Encoding(12, bool(rng.random() < 0.5)) if cat == "12-bit" else Encoding())
    enc = replace(enc, gamma=gamma)
    full = cat == "full-height sample" or (cat != "sample on holder" and rng.random() < 0.4)
    bg = float(rng.uniform(40, 220))
    roll = float(rng.uniform(-1.0, 1.0))
    pole_ang = float(rng.uniform(-0.3, 0.3)) + roll
    tilt = float(rng.uniform(-0.5, 0.5))
    samp_ang = pole_ang + tilt
    wp = float(rng.uniform(14, 50))  # the area method needs ~12 px between two edges
    ws = float(rng.uniform(max(3 * wp, 60), 350))
    gap = float(rng.uniform(2 * wp + 20, 350))
    total = wp + gap + ws
    if total > w - 120:  # a narrow frame (under about 870 px): the gap and the sample
        k = (0.9 * (w - 120) - wp) / (gap + ws)  # shrink (a 1280 px frame always fits)
        gap, ws = gap * k, ws * k
        total = wp + gap + ws
    x_left = float(rng.uniform(60, w - 60 - total))
    pole_left = rng.random() < 0.5
    if pole_left:
        pole_c, s_near = x_left + wp / 2, x_left + wp + gap
        s_far = s_near + ws
    else:
        s_far, s_near = x_left, x_left + ws
        pole_c = s_near + gap + wp / 2

    def level_vs(ref: float, lo: float = 40) -> float:
        for _ in range(100):
            v = float(rng.choice([rng.uniform(5, 250)]))
            if abs(v - ref) >= lo:
                return v
        return ref + lo if ref < 128 else ref - lo

    pole_lv = level_vs(bg, 60)
    samp_lv = level_vs(bg, 60)
    # drawn at _SIDE_SS x the resolution across (the measured edges are near vertical), so
    # that the defocus acts before the pixels integrate the light, as a lens does; blurring
    # the pixel image instead makes an edge's profile depend on its sub-pixel phase
    ss = _SIDE_SS
    img = np.full((h, w), bg, np.float32) + _texture(rng, (h, w), rng.uniform(50, 300),
                                                     rng.uniform(0, 5))
    img = _stretch(img, ss)
    ras = Raster((w * ss, h), 1.0, (0.0, 0.0), 0.0)
    ym = (h - 1) / 2

    def slanted(x_mid: float, ang: float, y_at: float, y0: float, y1: float,
                width: float) -> np.ndarray:
        """Quad with left side through (x_mid, y_at) leaning by ang (top toward +x)."""
        ta = math.tan(math.radians(ang))
        xl0, xl1 = x_mid - (y0 - y_at) * ta, x_mid - (y1 - y_at) * ta
        return np.array([[xl0, y0], [xl0 + width, y0], [xl1 + width, y1], [xl1, y1]])

    big = 4.0 * h
    pole = slanted(pole_c - wp / 2, pole_ang, ym, -big, h + big, wp)
    if full:
        y_top, y_bot = -big, h + big
        rows = (0, h - 1)
    else:
        y_top = float(rng.uniform(0.03, 0.25) * h)
        y_bot = float(y_top + rng.uniform(0.55, 0.97 - y_top / h) * h)
        y_bot = min(y_bot, h - 40.0)
        rows = (math.ceil(y_top), math.floor(y_bot))
    y_mid = (max(y_top, 0) + min(y_bot, h - 1)) / 2
    s_left = min(s_near, s_far)
    # x of the sample's left edge at y_mid: the edges are parallel, leaning by samp_ang
    slab = slanted(s_left, samp_ang, y_mid, y_top, y_bot, ws)
    params: dict[str, object] = {"full_height": full, "pole_left": pole_left, "wp": wp,
                                 "ws": ws, "gap": gap, "tilt": tilt}
    if polished:
        shine, info = _polished_pole(rng.spawn(1)[0], img.shape, ss, pole[0], pole_ang, wp,
                                     pole_lv)
        _paint(img, _wide(pole, ss), ras, shine)
        params.update(info)
    else:
        _paint(img, _wide(pole, ss), ras, pole_lv)
    if not full:
        # the holder and the platform below the sample, wider, their own small angles
        hh = float(rng.uniform(25, 70))
        hold_lv = level_vs(samp_lv, 25)
        room = gap - 15
        ext_near = float(rng.uniform(5, max(room * 0.6, 6)))
        ext_far = float(rng.uniform(5, 80))
        if pole_left:
            hx0, hx1 = s_left - ext_near, s_left + ws + ext_far
        else:
            hx0, hx1 = s_left - ext_far, s_left + ws + ext_near
        ha = pole_ang + float(rng.uniform(-1, 1))
        holder = slanted(hx0, ha, y_bot, y_bot, y_bot + hh, hx1 - hx0)
        _paint(img, _wide(holder, ss), ras, hold_lv)
        plat_lv = level_vs(hold_lv, 25)
        ext2 = float(rng.uniform(2, max(room * 0.6 - ext_near, 3)))
        px0 = hx0 - (ext2 if pole_left else rng.uniform(5, 100))
        px1 = hx1 + (rng.uniform(5, 100) if pole_left else ext2)
        pa = pole_ang + float(rng.uniform(-1, 1))
        plat = slanted(px0, pa, y_bot + hh, y_bot + hh, h + big, px1 - px0)
        _paint(img, _wide(plat, ss), ras, plat_lv)
        params["holder_px"] = hh
    _paint(img, _wide(slab, ss), ras, samp_lv)
    uneven = cat == "uneven light" or rng.random() < 0.3
    light, info = _light(rng, (h, w), gradient=0.5 if uneven else 0.15,
                         vignetting=float(rng.uniform(0.1, 0.4)) if uneven else 0.0,
                         shadow=uneven and rng.random() < 0.6)
    params.update(info)
    img *= _stretch(light, ss)
    blur = float(rng.uniform(0.4, 1.5))
    if defocus == "disc":
        img = cv2.filter2D(img, -1, disc_kernel(2.0 * blur, across=ss),
                           borderType=cv2.BORDER_REFLECT)
    else:
        img = cv2.GaussianBlur(img, (0, 0), sigmaX=blur * ss, sigmaY=blur,
                               borderType=cv2.BORDER_REFLECT)
    img = img.reshape(h, w, ss).mean(axis=2)
    params["blur_px"] = blur
    noise = {"read_noise": float(rng.uniform(0.5, 2.0)),
             "electrons_per_dn": float(rng.uniform(40, 150))}
    params.update(read_noise_dn=noise["read_noise"], electrons_per_dn=noise["electrons_per_dn"])
    out = _finish(img, rng, blur=0.0, enc=enc, **noise)
    # more frames of the same view: their own noise (and coding) from child generators,
    # so that the scenes drawn after this one do not depend on how many frames were asked;
    # the last child seeds the frames asked for later
    children = rng.spawn(frames)
    more = tuple(_finish(img, child, blur=0.0, enc=enc, **noise) for child in children[:-1])
    root = int(children[-1].integers(2 ** 62))

    def further(j: int) -> np.ndarray:
        return _finish(img, np.random.default_rng([root, j]), blur=0.0, enc=enc, **noise)
    ta = math.tan(math.radians(samp_ang))
    x_left_mid = float(slab[0, 0] - (y_mid - y_top) * ta)
    xs = (x_left_mid, x_left_mid + ws)
    near = xs[0] if pole_left else xs[1]
    tp = math.tan(math.radians(pole_ang))
    pole_mid = float(pole[0, 0] - (ym - pole[0, 1]) * tp) + wp / 2
    # the regions a config would give: the pole's column over the full height; a window
    # around the sample's near edge over the sample's rows
    pr = (max(int(pole_mid - wp / 2 - 30), 0), 0, min(int(pole_mid + wp / 2 + 31), w), h)
    half = int(min(40, ws / 2 - 5, gap / 2))
    sr = (max(int(near - half), 0), max(rows[0] + 10, 0), min(int(near + half + 1), w),
          min(rows[1] - 10, h))
    return SideSceneSample(out, cat, samp_ang, pole_ang, xs, near, pole_mid, rows, pr, sr,
                           enc, params, more, further)


# ---- rim ---------------------------------------------------------------------------------
def random_rim_scene(rng: np.random.Generator, category: str | None = None,
                     size_px: tuple[int, int] = (1280, 720), frames: int = 1,
                     turn_deg: float = 0.0) -> RimSceneSample:
    """One randomised frame of the turntable rim, in view, e 0.01-0.2 (see the docstring);
    ``frames`` > 1 adds further frames of the same view with independent noise and coding
    (``RimSceneSample.frames``), as the pre-check grabs them. ``turn_deg``: frame k shows
    the turntable turned by k * turn_deg about its axis: the disc's texture and the holder
    (with its shadow) turn with it, drawn in the disc's plane (the rim's ellipse maps onto
    itself); the floor, the light and the cables stay. 0 (default): a still view, and the
    same scenes as before the option for a given generator."""
    cat = str(category or RIM_CATEGORIES[int(rng.integers(len(RIM_CATEGORIES)))])
    w, h = size_px
    enc = Encoding(8, False, int(rng.integers(80, 96))) if cat == "jpeg" else Encoding()
    e = float(rng.uniform(0.01, 0.2))
    ang = float(rng.uniform(-90, 90))
    a = float(rng.uniform(180, 0.5 * h - 15))
    b = a * math.sqrt(1 - e * e)
    c = (float(w / 2 + rng.uniform(-(w / 2 - a - 15), w / 2 - a - 15)),
         float(h / 2 + rng.uniform(-(h / 2 - a - 12), h / 2 - a - 12)))
    dark = cat == "dark disc" or rng.random() < 0.3
    for _ in range(100):
        floor = float(rng.uniform(20, 235))
        disc = floor + (-1 if dark else 1) * float(rng.uniform(40, 140))
        if 10 <= disc <= 240:
            break
    ras = Raster(size_px, float(w), (w / 2, h / 2), 0.0)
    ground = np.full((h, w), floor, np.float32) + _texture(rng, (h, w), rng.uniform(40, 200),
                                                           rng.uniform(0, 6))
    disc_tex = _texture(rng, (h, w), rng.uniform(2, 30), rng.uniform(0.5, 3))
    disc_cov = coverage(Conic(ellipse_conic(c, a, b, ang)), ras, (0, 0, w, h))
    occluded = cat == "occluded" or (cat != "clear" and rng.random() < 0.4)
    params: dict[str, object] = {"dark_disc": dark, "occluded": occluded}
    holder: tuple[np.ndarray, np.ndarray, float, float] | None = None
    cables: list[tuple[np.ndarray, float]] = []

    def compose(turn: float) -> np.ndarray:
        """The view before light and noise with the turntable turned by ``turn``."""
        img = ground.copy()
        tex = disc_tex if turn == 0.0 else _turned(disc_tex, c, (a, b), ang, turn)
        img += (disc + tex - img) * disc_cov  # as _paint: the disc's exact coverage
        if holder is not None:
            hr, off, depth, level = holder
            if turn != 0.0:
                hr = _turn_points(hr, c, (a, b), ang, turn)
            mask = np.zeros((h, w), np.float32)
            cv2.fillConvexPoly(mask, np.round((hr + off) * 16).astype(np.int32), 1.0,
                               cv2.LINE_AA, 4)
            img *= 1.0 - np.float32(depth) * cv2.GaussianBlur(mask, (0, 0), 5)
            _paint(img, Polygon(hr), ras, level)
        for m, lv in cables:
            img += (np.float32(lv) - img) * m
        return img

    if occluded:
        # a holder overlapping the rim (it stands on the turntable), its shadow, cables
        t = float(rng.uniform(0, 2 * math.pi))
        L = float(rng.uniform(60, 160))
        p = np.array(c) + np.array([a * math.cos(t), b * math.sin(t)]) * 0.95
        hr = rectangle(p, L, L / rng.uniform(1, 2.5), float(rng.uniform(-90, 90)))
        off = rng.uniform(-15, 15, 2)
        depth = float(rng.uniform(0.1, 0.4))
        holder = (hr, off, depth, float(rng.uniform(5, 250)))
        img = compose(0.0)
        params["cables"] = _draw_cables(rng, img, int(rng.integers(1, 3)), [], 0.0, cables)
    else:
        img = compose(0.0)
    light, info = _light(rng, (h, w), gradient=0.3, vignetting=float(rng.uniform(0, 0.3)),
                         shadow=occluded and rng.random() < 0.5)
    params.update(info)
    img *= light
    finish = {"blur": float(rng.uniform(0.4, 1.5)), "read_noise": float(rng.uniform(0.5, 2.5)),
              "electrons_per_dn": float(rng.uniform(20, 80))}
    out = _finish(img, rng, enc=enc, **finish)
    if turn_deg:
        params["turn_deg"] = float(turn_deg)
    # as for side views: a child generator per further frame keeps later scenes unchanged
    more = tuple(_finish(compose(k * turn_deg) * light if turn_deg else img, child, enc=enc,
                         **finish)
                 for k, child in enumerate(rng.spawn(frames - 1) if frames > 1 else [],
                                           start=1))
    return RimSceneSample(out, cat, c, (a, b), ang, e, enc, params, more)


def _plane_turn(center: tuple[float, float], axes: tuple[float, float], angle_deg: float,
                turn_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(A, t): x -> A x + t is the turntable's turn by ``turn_deg`` as the image shows it,
    the affine view of the plane's rotation that maps the rim's ellipse (centre, semi-axes,
    major axis direction) onto itself."""
    t, r = math.radians(angle_deg), math.radians(turn_deg)
    Rt = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    M = Rt @ np.diag(axes)  # unit circle in the plane -> the ellipse
    Rr = np.array([[math.cos(r), -math.sin(r)], [math.sin(r), math.cos(r)]])
    A = M @ Rr @ np.linalg.inv(M)
    ctr = np.asarray(center, float)
    return A, ctr - A @ ctr


def _turn_points(pts: np.ndarray, center: tuple[float, float], axes: tuple[float, float],
                 angle_deg: float, turn_deg: float) -> np.ndarray:
    """Image points on the turntable after it turned by ``turn_deg``."""
    A, t = _plane_turn(center, axes, angle_deg, turn_deg)
    return np.asarray(pts, float) @ A.T + t


def _turned(tex: np.ndarray, center: tuple[float, float], axes: tuple[float, float],
            angle_deg: float, turn_deg: float) -> np.ndarray:
    """``tex`` on the disc turned by ``turn_deg`` about the turntable's axis, as the image
    shows it (:func:`_plane_turn`)."""
    A, t = _plane_turn(center, axes, angle_deg, -turn_deg)  # output pixel -> its source
    h, w = tex.shape
    return cv2.warpAffine(tex, np.column_stack([A, t]), (w, h),
                          flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)
