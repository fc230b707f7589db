"""A run's report: one PNG (top-camera view with the tracked paths, the centre of rotation
with its uncertainty ellipse and the target point; the offset per iteration) and the run's
JSON record.

Drawn with OpenCV only (no plotting library on an instrument PC). Both files are written
atomically (temp file, fsync, rename), so a report file is always wholly the old one or
wholly the new one, even if the writer is killed.

The report works from the run record alone (as ``GET /runs/ID`` returns it) plus one saved
frame, so any observer can produce it without access to the daemon's state directory.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from alignd.store import atomic_write_bytes, jsonable

WIDTH = 960
PLOT_H = 320
HEADER_H = 70
PATH_COLOURS = [(60, 60, 255), (60, 200, 60), (255, 140, 40), (0, 200, 255), (200, 80, 200)]
CENTRE_COLOUR = (0, 255, 255)
TARGET_COLOUR = (255, 0, 255)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def _find(obj: Any, names: Iterable[str]) -> Any:
    """The first value stored under any of ``names`` in nested dicts/lists (depth first).

    Why: the iteration records are the procedure's to shape; the report looks for what it
    needs by name rather than depending on one nesting."""
    names = tuple(names)
    stack = [obj]
    while stack:
        cur = stack.pop(0)
        if isinstance(cur, dict):
            for n in names:
                if cur.get(n) is not None:
                    return cur[n]
            stack.extend(v for v in cur.values() if isinstance(v, (dict, list)))
        elif isinstance(cur, list):
            stack.extend(v for v in cur if isinstance(v, (dict, list)))
    return None


def _records(run: dict[str, Any]) -> list[dict[str, Any]]:
    recs = run.get("iteration_records")
    return [r for r in recs if isinstance(r, dict)] if isinstance(recs, list) else []


def _centre_record(run: dict[str, Any]) -> dict[str, Any] | None:
    """The last iteration record that carries a centre of rotation."""
    for rec in reversed(_records(run)):
        if _find(rec, ("centre_px", "center_px")) is not None:
            return rec
    return None


def pick_frame(run: dict[str, Any]) -> dict[str, Any] | None:
    """The saved frame to draw on: from the last sweep, the one nearest turntable angle 0.

    Returns ``{"hash", "angle_deg", "sweep"}`` or ``None`` when the run saved no frame."""
    frames = [f for f in run.get("frames") or [] if isinstance(f, dict) and f.get("hash")]
    if not frames:
        return None
    sweeps = run.get("sweeps") or []
    sweep = sweeps[-1] if sweeps else None
    if sweep is not None:
        # labels are "<kind>-<iteration>-<step>[-<frame at that step>]"
        prefix = f"{sweep.get('kind')}-{sweep.get('iteration')}-"
        by_step: dict[int, str] = {}
        for f in frames:
            label = str(f.get("label", ""))
            step = label[len(prefix):].split("-")[0] if label.startswith(prefix) else ""
            if step.isdigit():
                by_step.setdefault(int(step), f["hash"])
        sframes = (sweep.get("sweep") or {}).get("frames") or []
        if sframes:
            i = int(np.argmin([abs(float(fr.get("angle_deg") or 0.0)) for fr in sframes]))
            if i in by_step:
                return {"hash": by_step[i], "angle_deg": float(sframes[i]["angle_deg"]),
                        "sweep": sweep, "index": i}
    last = frames[-1]
    return {"hash": last["hash"], "angle_deg": None, "sweep": sweep, "index": None}


def decode_png(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("not a decodable image")
    return img


def _rot(deg: float) -> np.ndarray:
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def _pt(p: np.ndarray, scale: float) -> tuple[int, int]:
    return round(float(p[0]) * scale), round(float(p[1]) * scale)


def _text(img: np.ndarray, text: str, org: tuple[int, int], size: float = 0.5,
          colour: tuple[int, int, int] = (255, 255, 255), thick: int = 1) -> None:
    # a drop shadow keeps text legible on any image (same thickness: same glyph advance)
    cv2.putText(img, text, (org[0] + 1, org[1] + 1), FONT, size, (0, 0, 0), thick,
                cv2.LINE_AA)
    cv2.putText(img, text, org, FONT, size, colour, thick, cv2.LINE_AA)


def draw_top_view(run: dict[str, Any], image: np.ndarray | None, width: int = WIDTH
                  ) -> np.ndarray:
    """The top-camera view: frame, tracked paths, centre with its k = 2 ellipse, target."""
    pick = pick_frame(run)
    sweep = (pick or {}).get("sweep") or ((run.get("sweeps") or [None])[-1])
    if image is None:
        base: np.ndarray = np.full((720, 1280, 3), 40, np.uint8)  # the reference camera's size
        _text(base, "no saved frame", (20, 40), 1.0)
    else:
        base = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
        if base.dtype != np.uint8:
            base = cv2.normalize(base, np.empty_like(base), 0, 255,
                                     cv2.NORM_MINMAX).astype(np.uint8)
    scale = width / base.shape[1]
    view = cv2.resize(base, (width, round(base.shape[0] * scale)),
                      interpolation=cv2.INTER_AREA)

    # tracked paths (each feature keeps its index across frames; null = missed)
    frames = ((sweep or {}).get("sweep") or {}).get("frames") or []
    n_feat = max((len(f.get("features") or []) for f in frames), default=0)
    for k in range(n_feat):
        colour = PATH_COLOURS[k % len(PATH_COLOURS)]
        pts = [f["features"][k] for f in frames
               if k < len(f.get("features") or []) and f["features"][k] is not None]
        if len(pts) >= 2:
            poly = np.array([_pt(np.asarray(p, float), scale) for p in pts], np.int32)
            cv2.polylines(view, [poly], False, colour, 1, cv2.LINE_AA)
        for p in pts:
            cv2.circle(view, _pt(np.asarray(p, float), scale), 2, colour, -1, cv2.LINE_AA)

    rec = _centre_record(run)
    legend = []
    if rec is not None:
        c = np.asarray(_find(rec, ("centre_px", "center_px")), float)
        cov = _find(rec, ("cov_centre_px2", "cov_center_px2", "cov_px2"))
        cc = _pt(c, scale)
        cv2.drawMarker(view, cc, CENTRE_COLOUR, cv2.MARKER_CROSS, 24, 2, cv2.LINE_AA)
        if cov is not None:
            cov = np.asarray(cov, float)
            vals, vecs = np.linalg.eigh((cov + cov.T) / 2)
            semi = 2.0 * np.sqrt(np.clip(vals, 0, None)) * scale  # k = 2, display pixels
            mag = 1.0
            if semi.max() > 0 and semi.max() < 12:
                mag = 10 ** math.ceil(math.log10(12 / semi.max()))  # make it visible
            ang = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
            axes = (max(1, round(semi[1] * mag)), max(1, round(semi[0] * mag)))
            cv2.ellipse(view, cc, axes, ang, 0, 360, CENTRE_COLOUR, 1, cv2.LINE_AA)
            legend.append("centre of rotation, k=2 ellipse" + (f" x{mag:g}" if mag > 1 else ""))
        else:
            legend.append("centre of rotation")
        target = _find(rec, ("target_px",))
        off = _find(rec, ("offset_px",))
        angle = (pick or {}).get("angle_deg") or 0.0
        if target is None and off is not None:
            target = c + _rot(angle) @ np.asarray(off, float)
        if target is not None:
            tt = _pt(np.asarray(target, float), scale)
            cv2.line(view, cc, tt, TARGET_COLOUR, 1, cv2.LINE_AA)
            cv2.circle(view, tt, 6, TARGET_COLOUR, 2, cv2.LINE_AA)
            legend.append("target point (middle of the sample surface)")
    for i, line in enumerate(legend):
        colour = CENTRE_COLOUR if i == 0 else TARGET_COLOUR
        _text(view, line, (10, view.shape[0] - 12 - 20 * (len(legend) - 1 - i)), 0.5, colour)
    if pick is not None and sweep is not None:
        what = f"{sweep.get('kind')} sweep {sweep.get('iteration')}"
        if pick.get("angle_deg") is not None:
            what += f", frame at {pick['angle_deg']:+.1f} deg"
        _text(view, what, (10, 22), 0.55)
    return view


def _iteration_points(run: dict[str, Any]) -> list[tuple[float, float, float | None]]:
    """(iteration, |offset| um, U um) per iteration record, in order."""
    out = []
    for i, rec in enumerate(_records(run)):
        norm = _find(rec, ("offset_norm_um",))
        if norm is None:
            off = _find(rec, ("offset_um",))
            if off is None:
                continue
            norm = float(np.hypot(*np.asarray(off, float)[:2]))
        u = _find(rec, ("U_um",))
        n = rec.get("n", i + 1)
        out.append((float(n), float(norm), None if u is None else float(u)))
    return out


def draw_convergence(run: dict[str, Any], width: int = WIDTH, height: int = PLOT_H
                     ) -> np.ndarray:
    """|offset| per iteration with its k = 2 uncertainty, log scale, tolerance line."""
    img = np.full((height, width, 3), 255, np.uint8)
    pts = _iteration_points(run)
    tol = _find(run.get("config") or {}, ("tolerance_um",))
    left, right, top, bottom = 70, 20, 30, 45
    x0, x1, y0, y1 = left, width - right, top, height - bottom
    cv2.putText(img, "offset per iteration (um, log scale; bars: U, k = 2)", (left, 20), FONT,
                0.5, (0, 0, 0), 1, cv2.LINE_AA)
    if not pts:
        cv2.putText(img, "no iterations recorded", (left, height // 2), FONT, 0.7,
                    (80, 80, 80), 1, cv2.LINE_AA)
        return img
    vals = [p[1] for p in pts] + [p[1] + (p[2] or 0) for p in pts]
    vals += [max(p[1] - (p[2] or 0), 0) for p in pts]
    if tol:
        vals.append(float(tol))
    pos = [v for v in vals if v > 0] or [1.0]
    lo = 10 ** math.floor(math.log10(min(pos)))
    hi = 10 ** math.ceil(math.log10(max(pos) * 1.01))
    if hi <= lo:
        hi = lo * 10
    n_max = max(p[0] for p in pts)
    n_min = min(p[0] for p in pts)

    def px_x(n: float) -> int:
        return round(x0 + (n - n_min + 0.5) / (n_max - n_min + 1) * (x1 - x0))

    def px_y(v: float) -> int:
        v = max(v, lo)
        return round(y1 - (math.log10(v) - math.log10(lo)) /
                     (math.log10(hi) - math.log10(lo)) * (y1 - y0))

    cv2.rectangle(img, (x0, y0), (x1, y1), (0, 0, 0), 1)
    dec = lo
    while dec <= hi * 1.0001:
        y = px_y(dec)
        cv2.line(img, (x0, y), (x1, y), (225, 225, 225), 1)
        cv2.putText(img, f"{dec:g}", (8, y + 4), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        dec *= 10
    for it in range(int(n_min), int(n_max) + 1):
        cv2.putText(img, str(it), (px_x(it) - 4, y1 + 18), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "iteration", ((x0 + x1) // 2 - 30, height - 8), FONT, 0.45, (0, 0, 0), 1,
                cv2.LINE_AA)
    if tol:
        y = px_y(float(tol))
        for xs in range(x0, x1, 12):
            cv2.line(img, (xs, y), (min(xs + 6, x1), y), (0, 150, 0), 1)
        cv2.putText(img, f"tolerance {float(tol):g} um", (x1 - 170, y - 6), FONT, 0.45,
                    (0, 150, 0), 1, cv2.LINE_AA)
    prev = None
    for n, v, u in pts:
        p = (px_x(n), px_y(v))
        if u:
            cv2.line(img, (p[0], px_y(v + u)), (p[0], px_y(max(v - u, lo))), (200, 80, 0), 1)
            for yy in (px_y(v + u), px_y(max(v - u, lo))):
                cv2.line(img, (p[0] - 5, yy), (p[0] + 5, yy), (200, 80, 0), 1)
        if prev is not None:
            cv2.line(img, prev, p, (0, 0, 200), 1, cv2.LINE_AA)
        cv2.circle(img, p, 4, (0, 0, 200), -1, cv2.LINE_AA)
        cv2.putText(img, f"{v:.3g}", (p[0] + 7, p[1] - 6), FONT, 0.4, (0, 0, 0), 1,
                    cv2.LINE_AA)
        prev = p
    return img


def draw_header(run: dict[str, Any], width: int = WIDTH) -> np.ndarray:
    img = np.full((HEADER_H, width, 3), 32, np.uint8)
    result = run.get("result") or {}
    verdict = run.get("verdict") or run.get("status") or "?"
    ok = verdict in ("aligned", "within_tolerance")
    title = f"alignd run {run.get('id')} ({run.get('kind')}): {verdict}"
    _text(img, title, (10, 26), 0.7, (80, 230, 80) if ok else (80, 80, 255), 2)
    bits = []
    if result.get("offset_norm_um") is not None:
        u = result.get("U_um")
        bits.append(f"offset {result['offset_norm_um']:.1f}"
                    + (f" +/- {u:.1f}" if u is not None else "") + " um (k=2)")
    if result.get("iterations") is not None:
        bits.append(f"{result['iterations']} iterations")
    bits.append(f"started {str(run.get('started_at', ''))[:19].replace('T', ' ')} UTC by "
                f"{run.get('user') or '?'}/{run.get('started_by')}")
    bits.append(f"alignd {run.get('software_version', '?')}, config "
                f"{str(run.get('config_hash', ''))[:12]}")
    _text(img, ", ".join(bits[:2]), (10, 48), 0.45)
    _text(img, "; ".join(bits[2:]) + (f"; {run['reason']}" if run.get("reason") else ""),
          (10, 64), 0.42, (200, 200, 200))
    return img


def render_report(run: dict[str, Any], image: np.ndarray | None) -> np.ndarray:
    """The report image (BGR): header, top view, convergence plot."""
    return np.vstack([draw_header(run), draw_top_view(run, image), draw_convergence(run)])


def write_report(run: dict[str, Any], out_dir: Path, image: np.ndarray | None
                 ) -> dict[str, Path]:
    """Write ``run-ID.png`` and ``run-ID.json`` into ``out_dir``, each atomically, the
    JSON last: a report whose JSON is there is complete (a kill in between leaves at most
    a new picture beside the old record)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    png = out_dir / f"run-{run['id']}.png"
    js = out_dir / f"run-{run['id']}.json"
    ok, buf = cv2.imencode(".png", render_report(run, image))
    if not ok:
        raise ValueError(f"cannot encode the report image for run {run.get('id')}")
    atomic_write_bytes(png, buf.tobytes())
    atomic_write_bytes(js, (json.dumps(jsonable(run), indent=1, allow_nan=False) + "\n"
                            ).encode())
    return {"png": png, "json": js}
