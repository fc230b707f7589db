"""The tone curves cameras encode their values with (``cameras[].gamma``): a pure power,
or a standard's curve by name, each a straight toe near black and a power above it.
Light and values are fractions of full scale (float32 arrays); the simulated cameras
encode with :func:`encode`, alignd's vision decodes with :func:`decode`."""

from __future__ import annotations

import numpy as np

from drivers.config import ToneCurve

__all__ = ["curve_text", "decode", "disagrees", "effective_powers", "encode", "is_linear"]

# (slope of the toe, the light where it ends, the power's a and exponent): above the toe
# v = (1 + a) L^exponent - a. sRGB: IEC 61966-2-1; BT.709: ITU-R BT.709-6 (its OETF)
_NAMED = {"srgb": (12.92, 0.0031308, 0.055, 1.0 / 2.4),
          "bt709": (4.5, 0.018, 0.099, 0.45)}


def is_linear(curve: ToneCurve) -> bool:
    return not isinstance(curve, str) and curve == 1.0


# the pure powers a named curve looks like over a view's levels (the noise's level
# dependence read as a power, alignd.vision.camera_check: 15 corpus views each, sRGB
# 2.06-2.23, BT.709 1.66-1.94)
_EFFECTIVE = {"srgb": (2.0, 2.3), "bt709": (1.6, 2.0)}


def effective_powers(curve: ToneCurve) -> tuple[float, float]:
    """The range of pure powers ``curve`` looks like over a view's levels."""
    if isinstance(curve, str):
        return _EFFECTIVE[curve]
    return (curve, curve)


GAMMA_SLACK = 0.1  # a configured curve this far outside what the frames allow disagrees


def disagrees(configured: ToneCurve, allowed: tuple[float, float]) -> bool:
    """Whether a configured curve lies outside the range of pure powers a camera's frames
    allow (by more than GAMMA_SLACK; a named curve counts as its range of powers)."""
    lo, hi = effective_powers(configured)
    return hi < allowed[0] - GAMMA_SLACK or lo > allowed[1] + GAMMA_SLACK


def curve_text(curve: ToneCurve) -> str:
    """How the curve is named to a person: "gamma 2.2", "sRGB", "BT.709"."""
    if isinstance(curve, str):
        return {"srgb": "sRGB", "bt709": "BT.709"}[curve]
    return f"gamma {curve:g}"


def encode(light: np.ndarray, curve: ToneCurve) -> np.ndarray:
    """The values a camera with ``curve`` gives for ``light`` (negative light, from noise,
    is taken as none)."""
    x = np.clip(np.asarray(light, np.float32), 0.0, None)
    if not isinstance(curve, str):
        return (x ** np.float32(1.0 / curve)).astype(np.float32)
    slope, toe, a, p = _NAMED[curve]
    return np.where(x < toe, slope * x, (1.0 + a) * x ** p - a).astype(np.float32)


def decode(values: np.ndarray, curve: ToneCurve) -> np.ndarray:
    """The light a camera with ``curve`` saw, from its ``values`` (the inverse of
    :func:`encode`)."""
    v = np.clip(np.asarray(values, np.float32), 0.0, None)
    if not isinstance(curve, str):
        return (v ** np.float32(curve)).astype(np.float32)
    slope, toe, a, p = _NAMED[curve]
    return np.where(v < slope * toe, v / slope,
                    ((v + a) / (1.0 + a)) ** (1.0 / p)).astype(np.float32)
