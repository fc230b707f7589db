"""A run's report: one PNG and the run's JSON record.

The PNG, top to bottom: a header (verdict, offset +/- U, who, when, software); the top
camera's view at a fixed scale (the frame is always shown whole, so a millimetre is the
same length in every report of a camera) with the tracked corner paths (legend), the
centre of rotation, the target point, a scale bar in mm and the directions in which the
correction stages move the image; then, side by side, a zoom around the axis at a fixed
scale set by the tolerance (the offset of every align and verify measurement in um, with
the tolerance circle and k = 2 ellipses; measurements outside the field are arrows on its
edge) and the offset per iteration (log scale, align and verify with distinct markers,
bars U at k = 2, never clipped silently); last, a text block: the verdict's reason and,
when the run record carries them, the decision rule (``result["decision_rule"]``, text)
and the uncertainty budget (``result["budget"]``: rows with ``name`` and ``u_um`` or
``value``), which the verdict code adds.

Drawn with OpenCV only (no plotting library on an instrument PC). Both files are written
atomically (temp file, fsync, rename), so a report file is always wholly the old one or
wholly the new one, even if the writer is killed.

The report works from the run record alone (as ``GET /runs/ID`` returns it) plus one saved
frame, so any observer can produce it without access to the daemon's state directory.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from alignd.config import SIDE_FRAME_PREFIX
from alignd.store import atomic_write_bytes, jsonable
from alignd.textfmt import wrap_words
from alignd.vision.lens import Lens
from drivers.config import LensConfig

WIDTH = 960
PLOT_H = 360  # the row holding the zoom (square) and the convergence plot
HEADER_H = 70
NOTES_H = 120  # the notes panel's height, grown up to NOTES_MAX_H for more lines
NOTES_MAX_H = 260
ZOOM_FIELD_TOLERANCES = 5.0  # the zoom spans this many tolerances (fixed per config)
PATH_COLOURS = [(60, 60, 255), (60, 200, 60), (255, 140, 40), (0, 200, 255), (200, 80, 200)]
CENTRE_COLOUR = (0, 255, 255)
CENTRE_INK = (0, 120, 170)  # the centre on white paper
TARGET_COLOUR = (255, 0, 255)
ALIGN_COLOUR = (0, 0, 200)
VERIFY_COLOUR = (160, 90, 0)
TOL_COLOUR = (0, 150, 0)
AXIS_COLOUR = (255, 255, 0)
FONT = cv2.FONT_HERSHEY_SIMPLEX
HALO = [(dx, dy) for dx in (-2, -1, 0, 1, 2) for dy in (-2, -1, 0, 1, 2) if dx or dy]


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

    Returns ``{"hash", "angle_deg", "sweep"}`` or ``None`` when the run saved no frame.
    Top-camera frames only: the view is drawn at the top camera's scale (the side
    pre-check's frames, ``precheck-side-NNN``, are in the record but not drawn here)."""
    frames = [f for f in run.get("frames") or [] if isinstance(f, dict) and f.get("hash")
              and not str(f.get("label", "")).startswith(SIDE_FRAME_PREFIX)]
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
    return {"hash": last["hash"], "angle_deg": None, "sweep": sweep, "index": None,
            "label": str(last.get("label", ""))}


def decode_png(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError("not a decodable image")
    return img


def to_bgr8(image: np.ndarray) -> np.ndarray:
    """An 8-bit BGR copy of a grey or colour frame (other depths stretched min to max)."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        lo, hi = float(img.min()), float(img.max())
        img = ((img.astype(np.float64) - lo) * (255.0 / (hi - lo or 1.0))).astype(np.uint8)
    return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR) if img.ndim == 2 else img[:, :, :3].copy()


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


class Labels:
    """Places text where it overlaps nothing placed before (tries a few spots, then the
    first free row below), so labels never cover each other."""

    def __init__(self, img: np.ndarray) -> None:
        self.img = img
        self.boxes: list[tuple[int, int, int, int]] = []

    def _free(self, box: tuple[int, int, int, int]) -> bool:
        x0, y0, x1, y1 = box
        h, w = self.img.shape[:2]
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            return False
        return all(x1 <= a or x0 >= c or y1 <= b or y0 >= d for a, b, c, d in self.boxes)

    def reserve(self, box: tuple[int, int, int, int]) -> None:
        self.boxes.append(box)

    def put(self, text: str, near: tuple[int, int], colour: tuple[int, int, int],
            size: float = 0.42, shadow: bool = False) -> bool:
        (tw, th), base = cv2.getTextSize(text, FONT, size, 1)
        x, y = near
        tries = [(x + 8, y - 6), (x + 8, y + th + 8), (x - tw - 8, y - 6),
                 (x - tw - 8, y + th + 8), (x - tw // 2, y - 12), (x - tw // 2, y + th + 14)]
        tries += [(x + 8, y - 6 + k * (th + 6)) for k in range(2, 12)]
        tries += [(x + 8, y - 6 - k * (th + 6)) for k in range(2, 12)]
        for ox, oy in tries:
            box = (ox - 2, oy - th - 2, ox + tw + 2, oy + base + 2)
            if self._free(box):
                self.boxes.append(box)
                if shadow:
                    _text(self.img, text, (ox, oy), size, colour)
                else:  # a white halo keeps it legible over lines, dashes and frames
                    # (drawn at the text's own thickness, shifted: a thicker stroke has a
                    # wider glyph advance, and its halo ran past the text's end)
                    for dx, dy in HALO:
                        cv2.putText(self.img, text, (ox + dx, oy + dy), FONT, size,
                                    (255, 255, 255), 1, cv2.LINE_AA)
                    cv2.putText(self.img, text, (ox, oy), FONT, size, colour, 1, cv2.LINE_AA)
                return True
        return False


@dataclass(frozen=True)
class Measured:
    """One measurement of a run (an iteration record): what the zoom and the plot draw."""

    index: int  # position in the run
    n: int  # iteration number
    kind: str  # align | verify | check | ...
    offset_um: tuple[float, float] | None
    norm_um: float
    U_um: float | None
    cov_um2: np.ndarray | None

    @property
    def label(self) -> str:
        return f"v{self.n}" if self.kind == "verify" else str(self.n)


def _measurements(run: dict[str, Any]) -> list[Measured]:
    out = []
    for i, rec in enumerate(_records(run)):
        off = _find(rec, ("offset_um",))
        norm = _find(rec, ("offset_norm_um",))
        if off is None and norm is None:
            continue
        xy = None
        if off is not None and len(off) >= 2:
            xy = (float(off[0]), float(off[1]))
        if norm is None and xy is not None:
            norm = math.hypot(*xy)
        u = _find(rec, ("U_um",))
        cov = rec.get("cov_offset_um2")
        out.append(Measured(i, int(rec.get("iteration") or rec.get("n") or i + 1),
                            str(rec.get("kind") or run.get("kind") or "?"), xy, float(norm),
                            None if u is None else float(u),
                            None if cov is None else np.asarray(cov, float)))
    return out


def _tolerance(run: dict[str, Any]) -> float | None:
    tol = _find(run.get("config") or {}, ("tolerance_um",))
    if tol is None:
        tol = _find(run.get("details") or {}, ("tolerance_um",))
    return None if tol is None else float(tol)


def _um_per_px(run: dict[str, Any]) -> float | None:
    """Micrometres per image pixel at the holder's face (for the scale bar)."""
    scale = _find(_records(run), ("scale_px_per_mm",))
    if scale:
        return 1000.0 / float(scale)
    px = _find(run.get("details") or {}, ("pixel_size_um",))
    if px is None:
        px = _find((run.get("config") or {}).get("cameras") or [], ("pixel_size_um",))
    return None if px is None else float(px)


def _in_frame(run: dict[str, Any]) -> Callable[[np.ndarray], np.ndarray]:
    """Undistorted image points -> the frame's pixels, through the top camera's configured
    lens (the sweeps are measured undistorted; the frame drawn on is not)."""
    cams = (run.get("config") or {}).get("cameras") or []
    lens = next((c.get("lens") for c in cams if isinstance(c, dict) and c.get("role") == "top"),
                None)
    if not isinstance(lens, dict):
        return lambda p: np.asarray(p, float)
    model = Lens.of(LensConfig.model_validate(lens))
    return lambda p: model.distort(np.asarray(p, float).reshape(-1, 2)).reshape(np.shape(p))


def _nice(x: float) -> float:
    """The largest 1, 2 or 5 times a power of ten not above ``x``."""
    p = 10 ** math.floor(math.log10(x))
    return max(m * p for m in (1, 2, 5) if m * p <= x)


def _arrow(img: np.ndarray, a: tuple[int, int], b: tuple[int, int],
           colour: tuple[int, int, int], thick: int = 2) -> None:
    cv2.arrowedLine(img, (a[0] + 1, a[1] + 1), (b[0] + 1, b[1] + 1), (0, 0, 0), thick,
                    cv2.LINE_AA, tipLength=0.25)
    cv2.arrowedLine(img, a, b, colour, thick, cv2.LINE_AA, tipLength=0.25)


def draw_top_view(run: dict[str, Any], image: np.ndarray | None, width: int = WIDTH
                  ) -> np.ndarray:
    """The top-camera view, whole frame at a fixed scale: paths, centre, target, scale bar,
    stage directions."""
    pick = pick_frame(run)
    sweep = (pick or {}).get("sweep") or ((run.get("sweeps") or [None])[-1])
    if image is None:
        base: np.ndarray = np.full((720, 1280, 3), 40, np.uint8)  # the reference camera's size
        _text(base, "no saved frame", (20, 40), 1.0)
    else:
        base = to_bgr8(image)
    scale = width / base.shape[1]
    view = cv2.resize(base, (width, round(base.shape[0] * scale)),
                      interpolation=cv2.INTER_AREA)
    H = view.shape[0]

    # tracked paths (each feature keeps its index across frames; null = missed)
    to_frame = _in_frame(run)
    frames = ((sweep or {}).get("sweep") or {}).get("frames") or []
    n_feat = max((len(f.get("features") or []) for f in frames), default=0)
    for k in range(n_feat):
        colour = PATH_COLOURS[k % len(PATH_COLOURS)]
        pts = [to_frame(f["features"][k]) for f in frames
               if k < len(f.get("features") or []) and f["features"][k] is not None]
        if len(pts) >= 2:
            poly = np.array([_pt(np.asarray(p, float), scale) for p in pts], np.int32)
            cv2.polylines(view, [poly], False, colour, 1, cv2.LINE_AA)
        for p in pts:
            cv2.circle(view, _pt(np.asarray(p, float), scale), 2, colour, -1, cv2.LINE_AA)

    rec = _centre_record(run)
    if rec is not None:
        c = np.asarray(_find(rec, ("centre_px", "center_px")), float)
        cc = _pt(to_frame(c), scale)
        cv2.drawMarker(view, cc, (0, 0, 0), cv2.MARKER_CROSS, 26, 4, cv2.LINE_AA)
        cv2.drawMarker(view, cc, CENTRE_COLOUR, cv2.MARKER_CROSS, 24, 2, cv2.LINE_AA)
        target = _find(rec, ("target_px",))
        off = _find(rec, ("offset_px",))
        angle = (pick or {}).get("angle_deg") or 0.0
        if target is None and off is not None:
            target = c + _rot(angle) @ np.asarray(off, float)
        if target is not None:
            tt = _pt(to_frame(np.asarray(target, float)), scale)
            cv2.line(view, cc, tt, TARGET_COLOUR, 1, cv2.LINE_AA)
            cv2.circle(view, tt, 7, TARGET_COLOUR, 2, cv2.LINE_AA)

    refused = (run.get("details") or {}).get("holder_frame_refused")
    if rec is None and isinstance(refused, dict):
        refused_items = _draw_refused_frame(view, refused, to_frame, scale,
                                            (pick or {}).get("angle_deg") or 0.0)
    else:
        refused_items = []

    # legend (bottom left): corner paths, centre, target
    items: list[tuple[str, tuple[int, int, int], str]] = [
        (f"corner {k} path", PATH_COLOURS[k % len(PATH_COLOURS)], "dot") for k in range(n_feat)]
    if rec is not None:
        items.append(("centre of rotation", CENTRE_COLOUR, "cross"))
        items.append(("target (sample surface middle)", TARGET_COLOUR, "ring"))
    items += refused_items
    y = H - 12 - 18 * (len(items) - 1)
    for text, colour, mark in items:
        if mark == "dot":
            cv2.line(view, (12, y - 5), (28, y - 5), colour, 2, cv2.LINE_AA)
        elif mark == "cross":
            cv2.drawMarker(view, (20, y - 5), colour, cv2.MARKER_CROSS, 12, 2, cv2.LINE_AA)
        elif mark == "crossed ring":
            cv2.circle(view, (20, y - 5), 5, colour, 2, cv2.LINE_AA)
            cv2.drawMarker(view, (20, y - 5), colour, cv2.MARKER_TILTED_CROSS, 14, 2,
                           cv2.LINE_AA)
        else:
            cv2.circle(view, (20, y - 5), 5, colour, 2, cv2.LINE_AA)
        _text(view, text, (36, y), 0.45, colour)
        y += 18

    # scale bar (bottom right) and the correction stages' directions in the image
    um_px = _um_per_px(run)
    if um_px:
        px_per_mm = 1000.0 / um_px * scale
        bar_mm = _nice(120 / px_per_mm)
        L = round(bar_mm * px_per_mm)
        x1, yb = width - 16, H - 16
        cv2.rectangle(view, (x1 - L - 1, yb - 6), (x1 + 1, yb + 1), (255, 255, 255), -1)
        cv2.rectangle(view, (x1 - L, yb - 5), (x1, yb), (0, 0, 0), -1)
        label = f"{bar_mm:g} mm (at the holder face)"
        tw = cv2.getTextSize(label, FONT, 0.45, 1)[0][0]
        _text(view, label, (x1 - tw, yb - 10), 0.45)
    J = _find(run.get("details") or {}, ("J_px_per_mm",))
    if J is not None:
        J = np.asarray(J, float)
        roles = _find(run.get("details") or {}, ("roles",)) or ["x", "y"]
        o = (width - 100, H - 120)
        mean = np.zeros(2)
        for k in range(min(2, J.shape[1])):
            d = J[:, k] / (np.hypot(*J[:, k]) or 1.0)
            mean += d
            tip = (round(o[0] + 45 * d[0]), round(o[1] + 45 * d[1]))
            _arrow(view, o, tip, AXIS_COLOUR)
            _text(view, f"+{roles[k]}", (tip[0] + (6 if d[0] >= 0 else -26),
                                          tip[1] + (14 if d[1] > 0.3 else -4)), 0.5,
                  AXIS_COLOUR)
        # the label on the side the arrows leave free
        away = -mean / (np.hypot(*mean) or 1.0)
        tw = cv2.getTextSize("stage moves", FONT, 0.4, 1)[0][0]
        _text(view, "stage moves", (round(o[0] + 22 * away[0] - tw / 2 + away[0] * tw / 2),
                                    round(o[1] + 22 * away[1] + 5)), 0.4, AXIS_COLOUR)
    if pick is not None and sweep is not None:
        what = f"{sweep.get('kind')} sweep {sweep.get('iteration')}"
        if pick.get("angle_deg") is not None:
            what += f", frame at {pick['angle_deg']:+.1f} deg"
        _text(view, what, (10, 22), 0.55)
    elif pick is not None and pick.get("label"):  # a run that ended before any sweep
        _text(view, f"the last frame saved: {pick['label']}", (10, 22), 0.55)
    return view


REFUSED_STYLE = {  # a refused holder frame's targets: colour, legend, marker
    "config": (TARGET_COLOUR, "target as configured (holder.target_mm)", "crossed ring"),
    "fix": ((60, 220, 60), "target the verdict names (near the axis)", "ring"),
    "other": ((150, 150, 150), "the other target the image allows", "ring"),
}
REFUSED_INK = {"config": (170, 0, 170), "fix": (0, 120, 0), "other": (70, 70, 70)}  # labels


def _draw_refused_frame(view: np.ndarray, refused: dict[str, Any],
                        to_frame: Callable[[np.ndarray], np.ndarray], scale: float,
                        angle_deg: float) -> list[tuple[str, tuple[int, int, int], str]]:
    """A run refused on its holder frame (``details.holder_frame_refused``): the axis and
    the targets the verdict compares, each at its offset from the axis turned to the
    drawn frame's angle, labelled with its holder.target_mm; the legend's items."""
    try:
        c = np.asarray(refused["centre_px"], float).reshape(2)
        targets = [(str(t["role"]), np.asarray(t["offset_px"], float).reshape(2),
                    [float(v) for v in t["target_mm"]], float(t["offset_mm"]))
                   for t in refused["targets"]]
    except (KeyError, TypeError, ValueError):
        return []  # an old or foreign record: nothing drawn rather than a wrong mark
    cc = _pt(to_frame(c), scale)
    labels = Labels(view)
    labels.reserve((cc[0] - 13, cc[1] - 13, cc[0] + 13, cc[1] + 13))
    items: list[tuple[str, tuple[int, int, int], str]] = [
        ("centre of rotation", CENTRE_COLOUR, "cross")]
    placed = []
    for role, off, t_mm, off_mm in targets:
        colour, legend, mark = REFUSED_STYLE.get(role, REFUSED_STYLE["other"])
        tt = _pt(to_frame(c + _rot(angle_deg) @ off), scale)
        labels.reserve((tt[0] - 11, tt[1] - 11, tt[0] + 11, tt[1] + 11))
        cv2.line(view, cc, tt, colour, 1, cv2.LINE_AA)
        cv2.circle(view, tt, 9, (0, 0, 0), 4, cv2.LINE_AA)
        cv2.circle(view, tt, 9, colour, 2, cv2.LINE_AA)
        if mark == "crossed ring":
            cv2.drawMarker(view, tt, colour, cv2.MARKER_TILTED_CROSS, 20, 2, cv2.LINE_AA)
        placed.append((f"[{t_mm[0]:g}, {t_mm[1]:g}]: {off_mm:.2f} mm from the axis", tt,
                       REFUSED_INK.get(role, REFUSED_INK["other"])))
        items.append((legend, colour, mark))
    cv2.drawMarker(view, cc, (0, 0, 0), cv2.MARKER_CROSS, 26, 4, cv2.LINE_AA)
    cv2.drawMarker(view, cc, CENTRE_COLOUR, cv2.MARKER_CROSS, 24, 2, cv2.LINE_AA)
    for text, at, ink in placed:  # after every mark is reserved: no label covers one
        labels.put(text, at, ink, 0.45)
    return items


def _ellipse(img: np.ndarray, centre: tuple[float, float], cov: np.ndarray, k: float,
             px_per_unit: float, colour: tuple[int, int, int]) -> None:
    vals, vecs = np.linalg.eigh((cov + cov.T) / 2)
    semi = k * np.sqrt(np.clip(vals, 0, None)) * px_per_unit
    ang = math.degrees(math.atan2(vecs[1, 1], vecs[0, 1]))
    axes = (max(1, round(semi[1])), max(1, round(semi[0])))
    cv2.ellipse(img, (round(centre[0]), round(centre[1])), axes, ang, 0, 360, colour, 1,
                cv2.LINE_AA)


def draw_zoom(run: dict[str, Any], size: int = PLOT_H) -> np.ndarray:
    """The axis and the target up close, at a fixed scale (a field of
    ``ZOOM_FIELD_TOLERANCES`` tolerances), in um, image axes at turntable angle 0."""
    img = np.full((size, size, 3), 255, np.uint8)
    labels = Labels(img)
    cv2.putText(img, "around the axis (um, turntable at 0 deg)", (8, 18), FONT, 0.45,
                (0, 0, 0), 1, cv2.LINE_AA)
    labels.reserve((0, 0, size, 24))
    tol = _tolerance(run) or 10.0
    field = ZOOM_FIELD_TOLERANCES * tol
    top, pad = 28, 10
    plot = size - top - pad
    x0, y0 = (size - plot) // 2, top
    k = plot / field  # px per um
    cx, cy = x0 + plot / 2, y0 + plot / 2

    def at(u: tuple[float, float]) -> tuple[int, int]:
        return round(cx + u[0] * k), round(cy + u[1] * k)

    cv2.rectangle(img, (x0, y0), (x0 + plot, y0 + plot), (150, 150, 150), 1)
    grid = _nice(field / 4)
    g = grid
    while g < field / 2:
        for s in (-1, 1):
            xx, yy = round(cx + s * g * k), round(cy + s * g * k)
            cv2.line(img, (xx, y0 + 1), (xx, y0 + plot - 1), (232, 232, 232), 1)
            cv2.line(img, (x0 + 1, yy), (x0 + plot - 1, yy), (232, 232, 232), 1)
        g += grid
    # tolerance circle about the axis
    for a in range(0, 360, 12):
        cv2.ellipse(img, (round(cx), round(cy)), (round(tol * k), round(tol * k)), 0, a, a + 6,
                    TOL_COLOUR, 1, cv2.LINE_AA)
    # the axis (origin) with its k = 2 ellipse
    rec = _centre_record(run)
    cov_c = None if rec is None else _find(rec, ("cov_centre_px2", "cov_center_px2"))
    um_px = _um_per_px(run)
    cv2.drawMarker(img, (round(cx), round(cy)), CENTRE_INK, cv2.MARKER_CROSS, 16, 2,
                   cv2.LINE_AA)
    if cov_c is not None and um_px:
        _ellipse(img, (cx, cy), np.asarray(cov_c, float) * um_px**2, 2.0, k, CENTRE_INK)
    labels.reserve((round(cx) - 9, round(cy) - 9, round(cx) + 9, round(cy) + 9))
    # each measurement's offset; the last one with its k = 2 ellipse
    ms = [m for m in _measurements(run) if m.offset_um is not None]
    prev = None
    inside = []
    outside: list[tuple[str, tuple[int, int], tuple[int, int, int]]] = []
    for m in ms:
        assert m.offset_um is not None
        p = at(m.offset_um)
        colour = VERIFY_COLOUR if m.kind == "verify" else ALIGN_COLOUR
        if x0 <= p[0] <= x0 + plot and y0 <= p[1] <= y0 + plot:
            inside.append((m, p, colour))
            if prev is not None:
                cv2.line(img, prev, p, (180, 180, 180), 1, cv2.LINE_AA)
            prev = p
        else:  # outside the field: an arrow on the edge pointing to it
            d = np.asarray(m.offset_um) / (np.hypot(*m.offset_um) or 1.0)
            reach = (plot / 2 - 4) / max(abs(d[0]), abs(d[1]))
            tip = (round(cx + d[0] * reach), round(cy + d[1] * reach))
            tail = (round(tip[0] - d[0] * 26), round(tip[1] - d[1] * 26))
            cv2.arrowedLine(img, tail, tip, colour, 2, cv2.LINE_AA, tipLength=0.35)
            labels.reserve((min(tip[0], tail[0]) - 3, min(tip[1], tail[1]) - 3,
                            max(tip[0], tail[0]) + 3, max(tip[1], tail[1]) + 3))
            outside.append((f"{m.label}: {m.norm_um:.0f} um", tail, colour))
            prev = None
    if inside and inside[-1][0].cov_um2 is not None:
        m, p, colour = inside[-1]
        _ellipse(img, p, m.cov_um2, 2.0, k, colour)  # type: ignore[arg-type]
    for m, p, colour in inside:
        if m.kind == "verify":
            cv2.drawMarker(img, p, colour, cv2.MARKER_DIAMOND, 12, 2, cv2.LINE_AA)
        else:
            cv2.circle(img, p, 5, colour, -1, cv2.LINE_AA)
        labels.reserve((p[0] - 6, p[1] - 6, p[0] + 6, p[1] + 6))
    # scale bar
    bar = grid
    bx, by = x0 + 8, y0 + plot - 10
    cv2.line(img, (bx, by), (bx + round(bar * k), by), (0, 0, 0), 2)
    labels.reserve((bx - 2, by - 18, bx + round(bar * k) + 2, by + 3))
    cv2.putText(img, f"{bar:g} um", (bx, by - 6), FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    # labels last, so none is drawn over by a marker or another label
    for text, at_, colour in outside:
        labels.put(text, at_, colour)
    for m, p, colour in inside:
        labels.put(m.label, p, colour)
    # legend (bottom right): the axis and the ellipses
    lx, ly = x0 + plot - 118, y0 + plot - 12
    cv2.drawMarker(img, (lx, ly - 4), CENTRE_INK, cv2.MARKER_CROSS, 12, 2, cv2.LINE_AA)
    cv2.putText(img, "axis; ellipses k = 2", (lx + 10, ly), FONT, 0.38, (60, 60, 60), 1,
                cv2.LINE_AA)
    labels.put(f"tolerance {tol:g} um", (round(cx + tol * k * 0.71), round(cy - tol * k * 0.71)),
               TOL_COLOUR)
    return img


def draw_convergence(run: dict[str, Any], width: int = WIDTH - PLOT_H, height: int = PLOT_H
                     ) -> np.ndarray:
    """|offset| per measurement with its k = 2 uncertainty, log scale, tolerance line.
    Align measurements are filled circles, verify measurements diamonds; a bar whose lower
    end would be at or below zero (U larger than the offset) ends in an arrow."""
    img = np.full((height, width, 3), 255, np.uint8)
    labels = Labels(img)
    ms = _measurements(run)
    tol = _tolerance(run)
    left, right, top, bottom = 58, 16, 54, 42
    x0, x1, y0, y1 = left, width - right, top, height - bottom
    cv2.putText(img, "|offset| per measurement (um, log; bars U, k = 2)", (8, 18), FONT, 0.45,
                (0, 0, 0), 1, cv2.LINE_AA)
    labels.reserve((0, 0, width, 24))
    if not ms:
        cv2.putText(img, "no iterations recorded", (left, height // 2), FONT, 0.6,
                    (80, 80, 80), 1, cv2.LINE_AA)
        return img
    # legend
    lx = 10
    sweep_kinds = sorted({m.kind for m in ms if m.kind != "verify"})
    cv2.circle(img, (lx + 5, 33), 5, ALIGN_COLOUR, -1, cv2.LINE_AA)
    name = "/".join(sweep_kinds) or "align"
    cv2.putText(img, name, (lx + 14, 37), FONT, 0.4, ALIGN_COLOUR, 1, cv2.LINE_AA)
    lx += 30 + cv2.getTextSize(name, FONT, 0.4, 1)[0][0]
    if any(m.kind == "verify" for m in ms):
        cv2.drawMarker(img, (lx + 5, 33), VERIFY_COLOUR, cv2.MARKER_DIAMOND, 11, 2, cv2.LINE_AA)
        cv2.putText(img, "verify", (lx + 15, 37), FONT, 0.4, VERIFY_COLOUR, 1, cv2.LINE_AA)
    labels.reserve((0, 24, lx + 70, 42))
    tops = [m.norm_um + (m.U_um or 0.0) for m in ms] + ([tol] if tol else [])
    lows = [m.norm_um for m in ms if m.norm_um > 0] + ([tol] if tol else [])
    lows += [m.norm_um - m.U_um for m in ms if m.U_um and m.norm_um - m.U_um > 0]
    lo = 10 ** math.floor(math.log10(min(lows or [1.0])))
    hi = 10 ** math.ceil(math.log10(max(tops) * 1.05))
    if hi <= lo:
        hi = lo * 10
    n = len(ms)

    def px_x(i: int) -> int:
        return round(x0 + (i + 0.5) / n * (x1 - x0))

    def px_y(v: float) -> int:
        v = max(v, lo)
        return round(y1 - (math.log10(v) - math.log10(lo)) /
                     (math.log10(hi) - math.log10(lo)) * (y1 - y0))

    cv2.rectangle(img, (x0, y0), (x1, y1), (0, 0, 0), 1)
    dec = lo
    while dec <= hi * 1.0001:
        y = px_y(dec)
        cv2.line(img, (x0, y), (x1, y), (225, 225, 225), 1)
        txt = f"{dec:g}"
        tw = cv2.getTextSize(txt, FONT, 0.42, 1)[0][0]
        cv2.putText(img, txt, (x0 - 6 - tw, y + 4), FONT, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        dec *= 10
    for i, m in enumerate(ms):
        txt = m.label
        tw = cv2.getTextSize(txt, FONT, 0.42, 1)[0][0]
        cv2.putText(img, txt, (px_x(i) - tw // 2, y1 + 16), FONT, 0.42, (0, 0, 0), 1,
                    cv2.LINE_AA)
    cv2.putText(img, "sweep (v: verify)", ((x0 + x1) // 2 - 60, height - 8), FONT, 0.42,
                (0, 0, 0), 1, cv2.LINE_AA)
    labels.reserve((0, y1 + 1, width, height))
    if tol:
        y = px_y(tol)
        for xs in range(x0, x1, 12):
            cv2.line(img, (xs, y), (min(xs + 6, x1), y), TOL_COLOUR, 1)
    pts = []
    for i, m in enumerate(ms):
        p = (px_x(i), px_y(m.norm_um))
        pts.append(p)
        if m.U_um:
            ytop = px_y(m.norm_um + m.U_um)
            low = m.norm_um - m.U_um
            ybot = px_y(low) if low > lo else y1
            cv2.line(img, (p[0], ytop), (p[0], ybot), (200, 80, 0), 1)
            cv2.line(img, (p[0] - 5, ytop), (p[0] + 5, ytop), (200, 80, 0), 1)
            if low > lo:
                cv2.line(img, (p[0] - 5, ybot), (p[0] + 5, ybot), (200, 80, 0), 1)
            else:  # reaches zero: off a log axis; say so with an arrow
                cv2.arrowedLine(img, (p[0], ybot - 14), (p[0], ybot - 1), (200, 80, 0), 1,
                                cv2.LINE_AA, tipLength=0.5)
            labels.reserve((p[0] - 6, ytop - 1, p[0] + 6, ybot + 1))
    cv2.polylines(img, [np.array(pts, np.int32)], False, (120, 120, 120), 1, cv2.LINE_AA)
    for m, p in zip(ms, pts, strict=True):
        if m.kind == "verify":
            cv2.drawMarker(img, p, VERIFY_COLOUR, cv2.MARKER_DIAMOND, 12, 2, cv2.LINE_AA)
        else:
            cv2.circle(img, p, 5, ALIGN_COLOUR, -1, cv2.LINE_AA)
        labels.reserve((p[0] - 7, p[1] - 7, p[0] + 7, p[1] + 7))
    if tol:
        labels.put(f"tolerance {tol:g} um", (x1 - 150, px_y(tol)), TOL_COLOUR)
    for m, p in zip(ms, pts, strict=True):
        labels.put(f"{m.norm_um:.3g}", p, (0, 0, 0))
    if any(m.U_um and m.norm_um - m.U_um <= lo for m in ms):
        labels.put("arrow: U > offset (bar reaches 0)", (x0 + 4, y1 - 4), (200, 80, 0))
    return img


def precheck_note(result: dict[str, Any]) -> str | None:
    """The pre-checks' readings in one line (the side camera's tilt with its standard
    uncertainty, the top camera's rim eccentricity with its own), or None when neither ran."""
    bits = []
    tilt, u = result.get("tilt_deg"), result.get("tilt_u_deg")
    if isinstance(tilt, (int, float)):
        unc = f" +/- {u:.4f}" if isinstance(u, (int, float)) else ""
        bits.append(f"sample tilt {tilt:+.4f}{unc} deg (u, k=1)" if unc
                    else f"sample tilt {tilt:+.4f} deg")
    e, ue = result.get("eccentricity"), result.get("eccentricity_u")
    if isinstance(e, (int, float)):
        bits.append(f"top-camera rim eccentricity {e:.4f} +/- {ue:.4f} (u, k=1)"
                    if isinstance(ue, (int, float)) else f"top-camera rim eccentricity {e:.4f}")
    return f"pre-checks: {'; '.join(bits)}" if bits else None


def report_notes(run: dict[str, Any]) -> list[str]:
    """The text block's lines: the verdict's reason, the pre-checks' readings and the run's
    warnings, which often say why a run could not decide (the decision rule and the
    uncertainty budget have their own panel, ``draw_verdict``)."""
    result = run.get("result") or {}
    reason = run.get("reason") or result.get("reason")
    lines = [f"verdict: {run.get('verdict') or result.get('verdict')}: {reason}"] if reason else []
    pre = precheck_note(result)
    if pre:
        lines.append(pre)
    warnings = (run.get("details") or {}).get("warnings") or []
    return [*lines, *(f"warning: {w}" for w in warnings if isinstance(w, str))]


def _wrap(text: str, width_px: int, size: float) -> list[str]:
    out, cur = [], ""
    for word in text.split():
        trial = f"{cur} {word}".strip()
        if cur and cv2.getTextSize(trial, FONT, size, 1)[0][0] > width_px:
            out.append(cur)
            cur = word
        else:
            cur = trial
    return [*out, cur] if cur else out


def draw_notes(run: dict[str, Any], width: int = WIDTH) -> np.ndarray:
    """The notes (:func:`report_notes`), wrapped; the panel is NOTES_H high and grows for
    more lines up to NOTES_MAX_H, past which the JSON has the rest."""
    parts = [part for line in report_notes(run)
             for part in _wrap(line.replace("±", "+/-"), width - 20, 0.45)]
    height = min(max(NOTES_H, 20 + 19 * len(parts)), NOTES_MAX_H)
    img = np.full((height, width, 3), 246, np.uint8)
    cv2.line(img, (0, 0), (width, 0), (200, 200, 200), 1)
    y = 20
    for part in parts:
        if y > height - 6:
            cv2.putText(img, "... (see the JSON)", (width - 160, height - 6), FONT, 0.42,
                        (80, 80, 80), 1, cv2.LINE_AA)
            return img
        cv2.putText(img, part, (10, y), FONT, 0.45, (30, 30, 30), 1, cv2.LINE_AA)
        y += 19
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
        moves = int(result["iterations"])
        sweeps = result.get("sweeps")
        bits.append(f"{moves} move{'s' if moves != 1 else ''}"
                    + (f", {sweeps} sweep{'s' if sweeps != 1 else ''}"
                       if sweeps is not None else ""))
    bits.append(f"started {str(run.get('started_at', ''))[:19].replace('T', ' ')} UTC by "
                f"{run.get('user') or '?'}/{run.get('started_by')}")
    bits.append(f"alignd {run.get('software_version', '?')}, config "
                f"{str(run.get('config_hash', ''))[:12]}")
    _text(img, ", ".join(bits[:2]), (10, 48), 0.45)
    _text(img, "; ".join(bits[2:]),  # the reason: the notes at the bottom
          (10, 64), 0.42, (200, 200, 200))
    return img


VERDICT_H = 250
ZONE_COLOURS = {"accept": (120, 200, 120), "undecided": (80, 200, 240),
                "reject": (120, 120, 230)}


def draw_verdict(run: dict[str, Any], width: int = WIDTH, height: int = VERDICT_H
                 ) -> np.ndarray:
    """The decision rule and the uncertainty budget: the zones of the rule on a distance
    axis (acceptance, undecided, rejection) with the measured offset and its U, the
    operator's line, and the budget table (standard uncertainties, combined, U at k=2)."""
    img = np.full((height, width, 3), 255, np.uint8)
    result = run.get("result") or {}
    dec = result.get("decision")
    budget = result.get("budget")
    black = (0, 0, 0)
    if not isinstance(dec, dict):
        cv2.putText(img, "no decision recorded (run ended before a measurement)", (10, 30),
                    FONT, 0.5, (80, 80, 80), 1, cv2.LINE_AA)
        return img
    tol = float(dec["tolerance_um"])
    off = float(dec["offset_um"])
    u = float(dec["U_um"])
    lo_acc = float(dec["accept_below_um"])
    hi_rej = float(dec["reject_above_um"])
    cv2.putText(img, "decision: " + str(dec.get("rule_name", dec.get("rule"))), (10, 20), FONT,
                0.5, black, 1, cv2.LINE_AA)
    # the zones on a distance axis from 0 to beyond the rejection limit and the measurement
    x0, x1, yb = 20, width - 20, 60
    top = max(hi_rej, off + u, tol) * 1.15

    def px(v: float) -> int:
        return round(x0 + max(min(v, top), 0.0) / top * (x1 - x0))

    zones = [(0.0, max(lo_acc, 0.0), "accept"), (max(lo_acc, 0.0), hi_rej, "undecided"),
             (hi_rej, top, "reject")]
    for a, b, name in zones:
        if b > a:
            cv2.rectangle(img, (px(a), yb - 14), (px(b), yb + 14), ZONE_COLOURS[name], -1)
            if px(b) - px(a) > 90:
                cv2.putText(img, {"accept": "within (accept)", "undecided": "cannot decide",
                                  "reject": "beyond (reject)"}[name],
                            (px(a) + 6, yb + 5), FONT, 0.45, black, 1, cv2.LINE_AA)
    cv2.line(img, (px(tol), yb - 22), (px(tol), yb + 22), black, 2)
    cv2.putText(img, f"tolerance {tol:g} um", (px(tol) - 60, yb - 26), FONT, 0.45, black, 1,
                cv2.LINE_AA)
    if dec.get("rule") == "guarded":
        cv2.putText(img, f"guard band U = {float(dec['guard_band_um']):.1f} um",
                    (px(max(lo_acc, 0.0)), yb + 32), FONT, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    ym = yb + 48
    cv2.line(img, (px(off - u), ym), (px(off + u), ym), (200, 80, 0), 2)
    for v in (off - u, off + u):
        cv2.line(img, (px(v), ym - 6), (px(v), ym + 6), (200, 80, 0), 2)
    cv2.circle(img, (px(off), ym), 6, (0, 0, 200), -1, cv2.LINE_AA)
    final = (run.get("details") or {}).get("final") or {}
    what = ("predicted after the last move" if isinstance(final, dict)
            and final.get("predicted") else "measured")
    cv2.putText(img, f"{what} {off:.1f} um, U {u:.1f} um (k=2)", (px(off) + 10, ym + 18),
                FONT, 0.45, black, 1, cv2.LINE_AA)
    y = ym + 40
    for line in wrap_words(str(dec.get("text", "")), 110)[:2]:
        cv2.putText(img, line, (10, y), FONT, 0.42, black, 1, cv2.LINE_AA)
        y += 17
    cv2.putText(img, "offset: the target's distance from the mean axis of rotation (the axis "
                "averaged over a turn)", (10, y), FONT, 0.42, (60, 60, 60), 1, cv2.LINE_AA)
    y += 20
    if isinstance(budget, dict):
        rows = [(str(c["name"]), float(c["u_um"] or 0.0), str(c.get("type", "")))
                for c in budget.get("contributions", [])]
        cv2.putText(img, "uncertainty budget (standard uncertainty, um, both axes)", (10, y),
                    FONT, 0.45, black, 1, cv2.LINE_AA)
        y += 4
        col_w = (width - 20) // 4
        items = [*(f"{n} {v:.2f} ({t})" for n, v, t in rows),
                 f"combined {float(budget['combined_um']):.2f}",
                 f"U (k={float(budget['k']):g}) {float(budget['U_um']):.2f}"]
        for i, text in enumerate(items):
            cx, cy = 10 + (i % 4) * col_w, y + 17 * (1 + i // 4)
            cv2.putText(img, text, (cx, cy), FONT, 0.42, black, 1, cv2.LINE_AA)
    return img


def render_report(run: dict[str, Any], image: np.ndarray | None,
                  side_image: np.ndarray | None = None) -> np.ndarray:
    """The report image (BGR): header, top view, the decision and its budget, the zoom
    beside the convergence plot, the side camera's pre-check frame (``side_image``, when
    given: :mod:`alignd.report_side`), notes; for a commission run, its own picture
    (``alignd.commission_report``)."""
    if run.get("kind") == "commission":
        from alignd.commission_report import render_commission

        return render_commission(run, image)
    lower = np.hstack([draw_zoom(run), draw_convergence(run)])
    parts = [draw_header(run), draw_top_view(run, image), draw_verdict(run), lower]
    if side_image is not None:
        from alignd.report_side import draw_side_panel

        parts.append(draw_side_panel(run, side_image, WIDTH))
    return np.vstack([*parts, draw_notes(run)])


def write_report(run: dict[str, Any], out_dir: Path, image: np.ndarray | None,
                 side_image: np.ndarray | None = None) -> dict[str, Path]:
    """Write ``run-ID.png`` and ``run-ID.json`` into ``out_dir``, each atomically, the
    JSON last: a report whose JSON is there is complete (a kill in between leaves at most
    a new picture beside the old record)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    png = out_dir / f"run-{run['id']}.png"
    js = out_dir / f"run-{run['id']}.json"
    ok, buf = cv2.imencode(".png", render_report(run, image, side_image))
    if not ok:
        raise ValueError(f"cannot encode the report image for run {run.get('id')}")
    atomic_write_bytes(png, buf.tobytes())
    atomic_write_bytes(js, (json.dumps(jsonable(run), indent=1, allow_nan=False) + "\n"
                            ).encode())
    return {"png": png, "json": js}
