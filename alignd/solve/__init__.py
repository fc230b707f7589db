"""Centre of rotation from tracked feature paths: pure functions, arrays in, results out.

Methods (``solve_centre(sweep, method)``):

- ``rigid``: all features one rigid body turning about one centre, the frame angles
  estimated from the images (readback only a start); immune to turntable angle errors.
- ``rigid-known``: the same with the readback angles taken as exact (linear, fastest).
- ``circles``: concentric geometric circle fit, no angles used.
- ``thesis``: the thesis' bisector/intersection/geometric-median baseline.
- ``auto``: ``rigid`` when at least two features are seen, else ``rigid-known``, else
  ``circles`` when the readback has no spread.
"""

from __future__ import annotations

import logging

import numpy as np

from alignd.errors import SolveError

from .circles import fit_circles
from .common import MIN_SPREAD_DEG, check_sweep
from .result import CentreResult
from .rigid import fit_rigid
from .sweep import Sweep, load_sweep, parse_sweep, sweep_to_json
from .thesis import fit_thesis

log = logging.getLogger(__name__)

METHODS = ("auto", "rigid", "rigid-known", "circles", "thesis")

__all__ = ["METHODS", "CentreResult", "Sweep", "choose_method", "load_sweep", "parse_sweep",
           "solve_centre", "sweep_to_json"]


def choose_method(sweep: Sweep) -> str:
    """What ``auto`` resolves to for this sweep."""
    inp = check_sweep(sweep)
    seen = inp.valid.sum(axis=0) >= 3
    co_visible = int(np.count_nonzero(inp.valid[:, seen].sum(axis=1) >= 2))
    if np.count_nonzero(seen) >= 2 and co_visible >= 3:
        return "rigid"
    usable = inp.valid.any(axis=1)
    if np.rad2deg(np.ptp(inp.angles_rad[usable])) >= MIN_SPREAD_DEG:
        return "rigid-known"
    return "circles"


def solve_centre(sweep: Sweep, method: str = "auto", seed: int = 0) -> CentreResult:
    """Centre of rotation of ``sweep`` with its covariance; SolveError if undetermined.

    ``seed`` only affects ``thesis`` (its random bisector subset).
    """
    if method not in METHODS:
        raise SolveError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    inp = check_sweep(sweep)
    if method == "auto":
        method = choose_method(sweep)
    if method in ("rigid", "rigid-known"):
        res = fit_rigid(inp, estimate_angles=method == "rigid")
    elif method == "circles":
        res = fit_circles(inp)
    else:
        res = fit_thesis(inp, seed=seed)
    if not (np.all(np.isfinite(res.center_px)) and np.all(np.isfinite(res.cov_px2))):
        raise SolveError(f"{method}: centre not determined (non-finite result)")
    return res
