"""What a camera does to its frames, read from a few frames of a still view.

A lab setting up a rig has a camera whose processing it does not know: a tone curve
(gamma), sharpening, noise reduction, JPEG/MJPEG coding, hot pixels, an exposure that
clips. Each moves edges in its own way (docs/vision.md, "What a camera does to its
frames"), and most can be switched off or told to alignd. :func:`check_frames` reads them
from frames of one still view (any scene; a few distinct grey levels help), with the
temporal noise as the probe: what the camera does to the noise it does to the edges.

- The noise's **level dependence** gives the tone curve: a linear camera's noise variance
  grows with the level (shot noise) or stays flat (read noise); a curve v = 255 (L /
  255)^(1/gamma) compresses the bright levels' noise, so the variance falls as the level
  rises. The fit of var(v) = (r^2 + L / g) / (dL/dv)^2 over the levels gives gamma (the
  photon transfer method of EMVA 1288, in the coded domain), with the range of gammas
  the noise allows: flat noise is a linear camera's read noise or a gamma 2 camera's
  shot noise alike, and then the range holds both.
- The noise's **correlation between neighbouring pixels** gives the spatial processing:
  raw sensor noise is white (correlation 0), sharpening makes neighbours anti-correlated,
  noise reduction, demosaicing and JPEG make them correlated.
- Specks (pixels far above or below all 8 neighbours) at the same place in every frame
  are the sensor's defective pixels; the JPEG quality is found by coding a frame again.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import nnls
from scipy.stats import chi2

from alignd.errors import VisionError
from alignd.vision.edges import as_gray, sensor_full_scale, speck_mask
from alignd.vision.jpeg_bias import jpeg_quality

__all__ = ["CameraCheck", "Finding", "check_frames", "gamma_text"]

_CLIP_HI, _CLIP_LO = 254.5, 0.5  # 8-bit DN of full scale: clipped at or beyond these
# the share of pixels at full scale worth a note (a glint, a lamp in view), and the one
# that asks for less exposure
CLIPPED_NOTE, CLIPPED_ACT = 0.001, 0.01
# the neighbouring pixels' noise correlation (the mean of along rows and along columns)
# beyond which the camera filters its frames (raw sensor noise: within +-0.005 on the
# corpus; unsharp mask amount 1 radius 1 px: -0.09; noise reduction, JPEG: +0.4 to +0.7)
SHARPENED_CORR = -0.05
SMOOTHED_CORR = 0.15
_GAMMAS = np.round(np.arange(0.8, 3.2001, 0.01), 2)  # the tone curves tried
GAMMA_LINEAR = 1.2  # the range the noise allows wholly below this: linear; above: a curve
_BIN_DN = 4.0  # the levels' bins (8-bit DN)
_MIN_BIN_PX = 300  # pixels a bin needs to count
_LEVELS_MIN, _LEVELS_MAX = 6.0, 248.0  # the levels fitted (clipping bends the noise beyond)
_REL_FLOOR = 0.005  # a bin's variance is trusted to this share at best
MIN_LEVEL_SPAN = 60.0  # DN between the darkest and brightest level fitted, for a gamma


@dataclass(frozen=True)
class Finding:
    """One thing the check found: ``key`` which (clipped_high, clipped_low, jpeg, config_gamma,
    defective_pixels, specks, frames, sharpened, smoothed, gamma), ``level`` "ok", "note"
    (worth knowing) or "act" (change a camera setting or alignd's config), what was seen,
    and what to do."""

    key: str
    level: str
    what: str
    advice: str = ""

    def to_json(self) -> dict[str, str]:
        return {"key": self.key, "level": self.level, "what": self.what,
                "advice": self.advice}


@dataclass(frozen=True)
class CameraCheck:
    """What :func:`check_frames` read from the frames (NaN / None: not measurable, with
    the reason in ``findings``)."""

    frames: int
    size_px: tuple[int, int]  # width, height
    bits: int  # 8, or the sensor's bits in 16-bit words
    clipped_high: float  # share of pixels at full scale
    clipped_low: float  # share at zero
    jpeg_quality: int | None
    specks_per_frame: float  # pixels far above or below all 8 neighbours, a frame's mean
    defective_pixels: int  # specks at the same pixel in every frame (2 frames or more)
    noise_dn: float  # temporal noise, RMS over the frame (8-bit DN of full scale)
    noise_correlation: tuple[float, float]  # neighbours' noise correlation: along rows, columns
    gamma: float  # the tone curve fitted to the noise's level dependence
    gamma_u: float  # its standard uncertainty
    gamma_range: tuple[float, float]  # every gamma the noise allows (3 sigma)
    level_span_dn: tuple[float, float]  # the darkest and brightest levels fitted
    findings: list[Finding] = field(default_factory=list)

    def to_json(self) -> dict[str, object]:
        def num(v: float) -> float | None:
            return float(v) if math.isfinite(v) else None
        return {"frames": self.frames, "size_px": list(self.size_px), "bits": self.bits,
                "clipped_high": self.clipped_high, "clipped_low": self.clipped_low,
                "jpeg_quality": self.jpeg_quality, "specks_per_frame": self.specks_per_frame,
                "defective_pixels": self.defective_pixels, "noise_dn": num(self.noise_dn),
                "noise_correlation": [num(v) for v in self.noise_correlation],
                "gamma": num(self.gamma), "gamma_u": num(self.gamma_u),
                "gamma_range": [num(v) for v in self.gamma_range],
                "level_span_dn": [num(v) for v in self.level_span_dn],
                "findings": [f.to_json() for f in self.findings]}


def check_frames(frames: Sequence[np.ndarray]) -> CameraCheck:
    """Read what the camera does to its frames from ``frames`` of one still view (8- or
    16-bit grey or BGR, as the camera delivers them: not linearised). One frame gives
    the clipping, the specks and the JPEG quality; the noise, its correlation and the
    tone curve need two or more (8 frames of the corpus's side views, levels 100 DN and
    more apart: gamma to +-0.1 or better on about half of them, 0.03-0.04 RMS there).
    Raises VisionError on frames that are not one view's."""
    if len(frames) == 0:
        raise VisionError("camera check: no frames")
    raw = [np.asarray(f) for f in frames]
    if any(f.shape != raw[0].shape for f in raw):
        raise VisionError("camera check: the frames differ in size (not one camera's view)")
    # frame by frame, each frame's float copy made when it is read (a 5 Mpx camera's 8
    # frames as one float stack with its residuals took 0.6 GB)
    grays = _Grays(raw)
    h, w = grays[0].shape
    bits = 8 if raw[0].dtype == np.uint8 else round(math.log2(
        max(sensor_full_scale(f) for f in raw) + 1))
    quality = jpeg_quality(grays[0]) if raw[0].dtype == np.uint8 else None
    bad = np.zeros((h, w), bool)  # clipped or a speck in any frame: left out of the noise
    every = np.ones((h, w), bool)  # a speck in every frame: a defective pixel
    n_hi = n_lo = n_specks = 0
    for g in grays:
        hi, lo, sp = g >= _CLIP_HI, g <= _CLIP_LO, speck_mask(g) > 0
        n_hi, n_lo, n_specks = n_hi + int(hi.sum()), n_lo + int(lo.sum()), n_specks + int(
            sp.sum())
        bad |= hi | lo | sp
        every &= sp
    n = len(grays)
    defective = int(every.sum()) if n >= 2 else 0
    noise, corr = math.nan, (math.nan, math.nan)
    nan2 = (math.nan, math.nan)
    curve = _Curve(math.nan, math.nan, nan2, nan2)
    if n >= 2:
        noise, corr, curve = _noise(grays, ~bad, bits)
        if quality is not None:  # the coding reshapes the noise: no tone curve read from it
            curve = _Curve(math.nan, math.nan, nan2, curve.span)
    check = CameraCheck(n, (w, h), bits, n_hi / (n * h * w), n_lo / (n * h * w), quality,
                        n_specks / n, defective, noise, corr, curve.gamma, curve.u,
                        curve.allowed, curve.span)
    return replace(check, findings=_findings(check))


class _Grays(Sequence[np.ndarray]):
    """The frames in 8-bit DN of full scale (float32), each converted when read."""

    def __init__(self, raw: list[np.ndarray]) -> None:
        self.raw = raw

    def __len__(self) -> int:
        return len(self.raw)

    def __getitem__(self, k: int) -> np.ndarray:  # type: ignore[override]
        return as_gray(self.raw[k], "camera frame")


@dataclass(frozen=True)
class _Curve:
    gamma: float
    u: float
    allowed: tuple[float, float]
    span: tuple[float, float]


_FIT_PX = 1_000_000  # pixels the tone curve's fit reads at most (an even sample beyond)


def _noise(grays: Sequence[np.ndarray], keep: np.ndarray, bits: int
           ) -> tuple[float, tuple[float, float], _Curve]:
    """The temporal noise (RMS, DN), its neighbours' correlation along rows and columns,
    and the tone curve fitted to its level dependence, from frames of a still view
    (``keep``: the pixels neither clipped nor a speck in any frame)."""
    n = len(grays)
    # a flickering light scales whole frames: each frame brought to the mean frame's level
    means = np.array([float(g[keep].mean()) for g in grays])
    scale = (means.mean() / np.maximum(means, 1e-6)).astype(np.float32)
    mean = np.zeros(keep.shape, np.float32)
    for g, k in zip(grays, scale, strict=True):
        mean += g * k
    mean /= np.float32(n)
    var = np.zeros(keep.shape, np.float32)
    # the correlation of each pixel's residual with its right and its lower neighbour's
    # (the residuals about the frames' mean have the noise's correlation)
    both_r = keep[:, 1:] & keep[:, :-1]
    both_c = keep[1:, :] & keep[:-1, :]
    cr = cc = 0.0
    for g, k in zip(grays, scale, strict=True):
        r = g * k - mean
        var += r * r
        cr += float((r[:, 1:] * r[:, :-1])[both_r].sum())
        cc += float((r[1:, :] * r[:-1, :])[both_c].sum())
    n_keep = max(int(keep.sum()), 1)
    ss = float(var[keep].sum()) / n_keep
    var /= n - 1
    noise = math.sqrt(float(np.median(var[keep])) / _median_scale(n - 1))
    cr /= max(int(both_r.sum()), 1)
    cc /= max(int(both_c.sum()), 1)
    # (the rounding to whole DN adds white noise after any filter: not the camera's)
    ss -= (1.0 - 1.0 / n) * _rounding_var(bits)
    corr = (cr / ss, cc / ss) if ss > 0 else (math.nan, math.nan)
    step = max(n_keep // _FIT_PX, 1)
    levels, variances = mean[keep][::step], var[keep][::step]
    return noise, corr, _tone_curve(levels, variances, n - 1, bits)


def _rounding_var(bits: int) -> float:
    """The variance (8-bit DN^2) that rounding to the camera's whole DN adds."""
    return (255.0 / (2 ** bits - 1)) ** 2 / 12.0


def _median_scale(dof: int) -> float:
    """The median of a variance estimate with ``dof`` degrees of freedom over the
    variance (a robust level's estimate, unbiased by this factor)."""
    return float(chi2.median(dof)) / dof


def _tone_curve(level: np.ndarray, var: np.ndarray, dof: int, bits: int) -> _Curve:
    """gamma, its standard uncertainty and the range of gammas the noise allows, fitted to
    the noise variance's level dependence (per bin of levels), and the span of levels
    fitted; NaN where the levels span under MIN_LEVEL_SPAN DN."""
    nan2 = (math.nan, math.nan)
    sel = (level >= _LEVELS_MIN) & (level <= _LEVELS_MAX)
    idx = np.floor(level[sel] / _BIN_DN).astype(int)
    v = var[sel]
    order = np.argsort(idx, kind="stable")
    idx, v = idx[order], v[order]
    bins, starts, counts = np.unique(idx, return_index=True, return_counts=True)
    good = counts >= _MIN_BIN_PX
    if not good.any():
        return _Curve(math.nan, math.nan, nan2, nan2)
    # each bin's variance: the mean of its pixels' variances without the outlying ones
    # (beyond all but 1e-4 of the noise's own: an edge that moved, a flickering speck),
    # which the median alone would not need, but the median of rounded 8-bit values
    # varies with the level by 1-2 % (the sample variances lie on a lattice)
    cut = float(chi2.ppf(1.0 - 1e-4, dof)) / dof / _median_scale(dof)
    lev_s = level[sel][order]
    med = np.empty(bins.size)
    lev = np.empty(bins.size)
    for j, (s, c) in enumerate(zip(starts, counts, strict=True)):
        vb = v[s:s + c]
        med[j] = float(vb[vb <= cut * float(np.median(vb))].mean())
        lev[j] = float(lev_s[s:s + c].mean())
    med, lev, counts = med[good], lev[good], counts[good]
    span = (float(lev.min()), float(lev.max()))
    if span[1] - span[0] < MIN_LEVEL_SPAN or lev.size < 4:
        return _Curve(math.nan, math.nan, nan2, span)
    # a mean variance's standard error, var sqrt(2 / (dof n)), floored: the bins of many
    # pixels would otherwise outweigh the levels' trend (which is what gamma is) by
    # effects of a few per mille
    sd = med * np.sqrt(2.0 / (dof * counts) + _REL_FLOOR ** 2)
    quant = _rounding_var(bits)
    x = np.clip(lev / 255.0, 1e-3, 1.0)
    chi = np.empty(_GAMMAS.size)
    for k, g in enumerate(_GAMMAS):
        slope = g * x ** (g - 1.0)  # dL/dv, L = 255 x^g
        A = np.column_stack([1.0 / slope ** 2, 255.0 * x ** g / slope ** 2]) / sd[:, None]
        coef, _ = nnls(A, (med - quant) / sd)
        chi[k] = float(np.sum((A @ coef - (med - quant) / sd) ** 2))
    k = int(np.argmin(chi))
    if k in (0, _GAMMAS.size - 1):  # no curve of the range fits: not a tone curve's noise
        return _Curve(math.nan, math.nan, nan2, span)
    dof_fit = max(lev.size - 3, 1)
    scale = max(float(chi[k]) / dof_fit, 1.0)  # misfit beyond the noise widens u
    # u: a third of the half-width of the 3-sigma profile interval. The read and the shot
    # noise trade off against the curve where the view has few levels (a linear camera's
    # var = r^2 + L / g and a curved one's with little shot noise both rise with the
    # level): chi^2 then has a second, nearly as deep minimum (corpus views: 1.0 and 1.54
    # within 5 of each other), which a 1-sigma interval about the deeper one leaves out.
    # Noise that does not change with the level is the extreme case: a linear camera's
    # read noise and a gamma 2 camera's shot noise (var of L / g over (dL/dv)^2, L ~ v^2)
    # look the same, and the range then spans both
    within = _GAMMAS[chi <= chi[k] + 9.0 * scale]
    g_best = float(_GAMMAS[k])
    lo, hi = float(within.min()), float(within.max())
    u = max(max(hi - g_best, g_best - lo) / 3.0, 0.02)
    g_lo, g_hi = float(_GAMMAS[0]), float(_GAMMAS[-1])  # (the range tried bounds it)
    return _Curve(g_best, u, (max(min(lo, g_best - 3 * u), g_lo),
                              min(max(hi, g_best + 3 * u), g_hi)), span)


def gamma_text(c: CameraCheck) -> str:
    """The tone curve as measured: "gamma 2.21 +- 0.04", or the range the noise allows
    where that is wide ("gamma 0.9-2.1"), or "not measured"."""
    if not math.isfinite(c.gamma):
        return "gamma not measured"
    lo, hi = c.gamma_range
    if hi - lo > 0.6:
        return f"gamma {lo:.1f}-{hi:.1f}"
    return f"gamma {c.gamma:.2f} +- {c.gamma_u:.2f}"


def _findings(c: CameraCheck) -> list[Finding]:
    """What to tell the lab, most pressing first."""
    out: list[Finding] = []

    def add(key: str, level: str, what: str, advice: str = "") -> None:
        out.append(Finding(key, level, what, advice))

    if c.clipped_high > CLIPPED_NOTE:
        add("clipped_high", "act" if c.clipped_high > CLIPPED_ACT else "note",
            f"{100 * c.clipped_high:.2f} % of the pixels are at full "
            "scale", "lower the exposure or gain until the brightest part of the holder, "
            "disc or sample stays below full scale (a clipped edge is measured from its "
            "unclipped side only)")
    if c.clipped_low > CLIPPED_NOTE:
        add("clipped_low", "note", f"{100 * c.clipped_low:.2f} % of the pixels are at zero",
            "raise the black level or the exposure if the dark parts matter (a dark "
            "holder's face or the floor)")
    if c.jpeg_quality is not None:
        add("jpeg", "act" if c.jpeg_quality < 90 else "note", "the frames are "
            f"JPEG/MJPEG-coded at quality {c.jpeg_quality}", "choose an uncompressed format "
            "(GREY, Y16, YUYV) if the camera offers one at the frame size; below quality 80 "
            "the side camera's tilt errs by up to 0.003 deg (docs/vision.md)")
    if c.defective_pixels:
        add("defective_pixels", "note", f"{c.defective_pixels} defective pixels (hot or dead, "
            "the same in every frame)", "alignd replaces them (it also finds them in one "
            "frame); the camera's own defect-pixel correction, if it has one, is as good")
    elif c.frames < 2 and c.specks_per_frame:
        add("specks", "note", f"{c.specks_per_frame:.0f} specks (pixels far from all 8 "
            "neighbours)", "alignd replaces them")
    if c.frames < 2:
        add("frames", "note", "one frame: the noise, its correlation and the tone curve are "
            "not measured", "give 2 or more frames of the same still view (8 for the tone "
            "curve)")
        return out
    ch = 0.5 * (c.noise_correlation[0] + c.noise_correlation[1])
    # (a filter mixes neighbouring levels' noise: the tone curve's fit is rougher then)
    rough = "" if SHARPENED_CORR <= ch <= SMOOTHED_CORR else \
        " (rough: the camera filters its frames)"
    if c.jpeg_quality is None and ch < SHARPENED_CORR:
        add("sharpened", "act", f"the camera sharpens its frames (neighbouring pixels' noise "
            f"correlates {ch:+.2f})", "set its sharpness to the lowest value (v4l2-ctl -c "
            "sharpness=0 on a UVC camera): strong sharpening makes 1 in 8 holders "
            "unmeasurable")
    elif c.jpeg_quality is None and ch > SMOOTHED_CORR:
        add("smoothed", "note", f"the camera smooths its frames (neighbouring pixels' noise "
            f"correlates {ch:+.2f}: noise reduction, or a colour sensor's demosaicing)",
            "turn noise reduction off; a monochrome camera measures about 20 % better than "
            "a colour one")
    g, (lo, hi) = c.gamma, c.gamma_range
    two = "measure gamma with two exposures (docs/configure.md)"
    if c.jpeg_quality is not None:
        add("gamma", "note", "the tone curve is not read from JPEG-coded frames (the coding "
            "reshapes the noise)", two)
    elif not math.isfinite(c.level_span_dn[0]) or \
            c.level_span_dn[1] - c.level_span_dn[0] < MIN_LEVEL_SPAN:
        add("gamma", "note", f"the tone curve is not measured: the view's levels span under "
            f"{MIN_LEVEL_SPAN:.0f} DN", "point the camera at a view with dark and bright "
            "parts (the holder on the turntable)")
    elif not math.isfinite(g):
        add("gamma", "note", "the tone curve is not measured: the noise follows no curve of "
            f"gamma {_GAMMAS[0]:g}-{_GAMMAS[-1]:g} (noise reduction, or a light that flickers "
            "unevenly)", two)
    elif lo > GAMMA_LINEAR:
        add("gamma", "act", f"the camera applies a tone curve: {gamma_text(c)}{rough}",
            f"set the camera's gamma to 1 (linear) if it can, else set cameras[].gamma to "
            f"{g:.1f}, or to srgb or bt709 where the camera's documentation names its curve "
            f"(better than the number: {two})")
    elif hi < GAMMA_LINEAR:
        add("gamma", "ok", f"linear ({gamma_text(c)}){rough}")
    else:
        add("gamma", "note", f"{gamma_text(c)}{rough}: linear or a curve, not told apart "
            "(noise that hardly changes with the level is a linear camera's read noise or a "
            "gamma 2 camera's shot noise alike)", two)
    return out
