"""The sweep: feature image paths recorded while the turntable turns, and its file format.

**contract: sweep file** (DESIGN.md)::

    {"version": 1, "pixel_size_um": 160.0,
     "frames": [{"angle_deg": -10.0, "features": [[x, y], null, ...]}, ...]}

Features keep their order in every frame; ``null`` is a missed detection. Pixel
coordinates: centre of the top-left pixel at (0, 0), x right, y down. Turning the table by
+a moves points as ``p = c + R(a) (p0 - c)``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np

from alignd.errors import InputError

SWEEP_VERSION = 1

__all__ = ["SWEEP_VERSION", "Sweep", "load_sweep", "parse_sweep", "sweep_to_json"]


@dataclass(frozen=True)
class Sweep:
    """Feature paths of one sweep.

    ``points[f, k]`` is feature k in frame f (x, y in px), NaN where it was not detected;
    ``angles_deg[f]`` is the turntable readback for frame f.
    """

    angles_deg: np.ndarray
    points: np.ndarray
    pixel_size_um: float | None = None

    @property
    def n_frames(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_features(self) -> int:
        return int(self.points.shape[1])


def _is_number(v: object) -> TypeGuard[int | float]:
    return isinstance(v, int | float) and not isinstance(v, bool)


def parse_sweep(obj: Any, source: str = "<sweep>") -> Sweep:
    """Validate a decoded sweep JSON object; raise InputError naming ``source`` and the key."""
    if not isinstance(obj, dict):
        raise InputError(f"{source}: expected a JSON object at top level, got {type(obj).__name__}")
    if "version" not in obj:
        raise InputError(f"{source}: missing key 'version' (expected {SWEEP_VERSION})")
    if obj["version"] != SWEEP_VERSION:
        raise InputError(f"{source}: unsupported version {obj['version']!r} "
                         f"(this alignd reads version {SWEEP_VERSION})")
    px = obj.get("pixel_size_um")
    if px is not None and (not _is_number(px) or not math.isfinite(px) or px <= 0):
        raise InputError(f"{source}: pixel_size_um must be a positive number or null, got {px!r}")
    frames = obj.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(f"{source}: 'frames' must be a non-empty list")
    n_feat: int | None = None
    angles = np.empty(len(frames))
    rows: list[list[tuple[float, float]]] = []
    for i, fr in enumerate(frames):
        where = f"{source}: frames[{i}]"
        if not isinstance(fr, dict):
            raise InputError(f"{where}: expected an object, got {type(fr).__name__}")
        a = fr.get("angle_deg")
        if not _is_number(a) or not math.isfinite(a):
            raise InputError(f"{where}.angle_deg: expected a finite number, got {a!r}")
        feats = fr.get("features")
        if not isinstance(feats, list):
            raise InputError(f"{where}.features: expected a list, got {type(feats).__name__}")
        if n_feat is None:
            n_feat = len(feats)
            if n_feat == 0:
                raise InputError(f"{where}.features: empty (no features tracked)")
        elif len(feats) != n_feat:
            raise InputError(f"{where}.features: ragged, {len(feats)} features where frames[0] "
                             f"has {n_feat} (features keep their order; use null for a miss)")
        row = []
        for k, p in enumerate(feats):
            if p is None:
                row.append((math.nan, math.nan))
                continue
            if (not isinstance(p, list) or len(p) != 2 or not all(_is_number(v) for v in p)
                    or not all(math.isfinite(v) for v in p)):
                raise InputError(f"{where}.features[{k}]: expected [x, y] with finite numbers "
                                 f"or null, got {p!r}")
            row.append((float(p[0]), float(p[1])))
        angles[i] = float(a)
        rows.append(row)
    points = np.asarray(rows, dtype=float).reshape(len(frames), n_feat or 0, 2)
    return Sweep(angles_deg=angles, points=points,
                 pixel_size_um=None if px is None else float(px))


def load_sweep(path: str | Path) -> Sweep:
    """Read a sweep file; InputError names the file and what is wrong."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{path}: cannot read sweep file: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a UTF-8 text file ({exc.reason})") from exc

    def _no_constants(name: str) -> float:
        raise InputError(f"{path}: bad JSON: {name} is not allowed (use null for a miss)")

    try:
        obj = json.loads(text, parse_constant=_no_constants)
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: bad JSON at line {exc.lineno} column {exc.colno}: "
                         f"{exc.msg}") from exc
    return parse_sweep(obj, str(path))


def sweep_to_json(sweep: Sweep) -> dict[str, Any]:
    """The contract's JSON object for ``sweep`` (NaN points become null)."""
    frames = []
    for a, row in zip(sweep.angles_deg, sweep.points, strict=True):
        feats: list[list[float] | None] = [
            None if not np.all(np.isfinite(p)) else [float(p[0]), float(p[1])] for p in row]
        frames.append({"angle_deg": float(a), "features": feats})
    return {"version": SWEEP_VERSION, "pixel_size_um": sweep.pixel_size_um, "frames": frames}
