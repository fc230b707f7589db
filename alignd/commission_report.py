"""The picture of a commission run: what the rig turned out to be.

Top left, the top camera at turntable 0 with the rotation axis and the direction each
translation axis moves the holder (length: 1 mm of travel); top right, the turntable's error
motion (runout) and its periodic angle error against the angle; below, every finding with
its verdict. Drawn from the run record alone (``GET /runs/ID``) plus one saved frame, with
OpenCV, like the alignment report.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from alignd.textfmt import wrap_words

WIDTH = 1100
PANEL_H = 420
ROW_H = 19
FONT = cv2.FONT_HERSHEY_SIMPLEX
VERDICT_COLOURS = {"pass": (90, 200, 90), "warn": (40, 180, 240), "fail": (80, 80, 255)}
AXIS_COLOURS = {"x": (60, 60, 255), "y": (60, 200, 60), "translator": (255, 140, 40)}
ARROW_MM = 10.0


def _text(img: np.ndarray, text: str, org: tuple[int, int], size: float = 0.45,
          colour: tuple[int, int, int] = (235, 235, 235), thick: int = 1) -> None:
    cv2.putText(img, text, (org[0] + 1, org[1] + 1), FONT, size, (0, 0, 0), thick, cv2.LINE_AA)
    cv2.putText(img, text, org, FONT, size, colour, thick, cv2.LINE_AA)


def _header(run: dict[str, Any]) -> np.ndarray:
    img = np.full((60, WIDTH, 3), 32, np.uint8)
    res = run.get("result") or {}
    verdict = str(run.get("verdict") or "?")
    counts = res.get("counts") or {}
    colour = (80, 230, 80) if verdict == "commissioned" else (80, 80, 255)
    _text(img, f"alignd run {run.get('id')} (commission): {verdict}", (10, 24), 0.7, colour, 2)
    _text(img, f"{counts.get('pass', 0)} pass, {counts.get('warn', 0)} warn, "
          f"{counts.get('fail', 0)} fail; started "
          f"{str(run.get('started_at', ''))[:19].replace('T', ' ')} UTC; config "
          f"{str(run.get('config_hash', ''))[:12]}; alignd {run.get('software_version', '?')}",
          (10, 48), 0.45, (200, 200, 200))
    return img


def _top_panel(run: dict[str, Any], image: np.ndarray | None, w: int) -> np.ndarray:
    conv = (run.get("result") or {}).get("conventions") or {}
    if image is None:
        panel = np.full((PANEL_H, w, 3), 50, np.uint8)
        _text(panel, "no frame saved (daemon.keep_frames: none)", (10, 30))
        return panel
    img = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    h0, w0 = img.shape[:2]
    axis = conv.get("axis_px")
    # a crop round the axis (the holder and its arrows fill the panel), else the whole frame
    cw, ch = (min(w0, 620), min(h0, round(620 * PANEL_H / w))) if axis else (w0, h0)
    cx = 0 if axis is None else int(min(max(axis[0] - cw / 2, 0), w0 - cw))
    cy = 0 if axis is None else int(min(max(axis[1] - ch / 2, 0), h0 - ch))
    crop = img[cy:cy + ch, cx:cx + cw]
    s = min(w / cw, PANEL_H / ch)
    panel = np.full((PANEL_H, w, 3), 20, np.uint8)
    small = cv2.resize(crop, (int(cw * s), int(ch * s)), interpolation=cv2.INTER_AREA)
    panel[:small.shape[0], :small.shape[1]] = small

    def at(p: list[float]) -> tuple[int, int]:
        return round((p[0] - cx) * s), round((p[1] - cy) * s)

    if axis is not None:
        a = at(axis)
        for role, m in (conv.get("axes") or {}).items():
            d = m.get("image_px_per_mm")
            if not d:
                continue
            end = at([axis[0] + ARROW_MM * d[0], axis[1] + ARROW_MM * d[1]])
            colour = AXIS_COLOURS.get(role, (255, 255, 255))
            cv2.arrowedLine(panel, a, end, colour, 2, cv2.LINE_AA, tipLength=0.12)
            _text(panel, f"+{role}", (end[0] + 6, end[1] + 5), 0.55, colour, 2)
        cv2.drawMarker(panel, a, (0, 255, 255), cv2.MARKER_CROSS, 22, 2, cv2.LINE_AA)
        _text(panel, "axis", (a[0] - 40, a[1] - 10), 0.5, (0, 255, 255))
    _text(panel, f"top camera at turntable 0; arrows: {ARROW_MM:g} mm of each axis",
          (8, PANEL_H - 10), 0.48)
    return panel


def _plot_panel(run: dict[str, Any], w: int) -> np.ndarray:
    res = run.get("result") or {}
    panel = np.full((PANEL_H, w, 3), 245, np.uint8)
    ro = res.get("runout") or {}
    ang = np.asarray(ro.get("angles_deg") or [], float)
    off = np.asarray(ro.get("offset_um") or [], float).reshape(-1, 2)
    x0, x1, y0, y1 = 60, w - 15, 40, PANEL_H - 60
    cv2.rectangle(panel, (x0, y0), (x1, y1), (150, 150, 150), 1)
    dark = (40, 40, 40)
    cv2.putText(panel, "turntable error motion (runout), um", (x0, 25), FONT, 0.5, dark, 1,
                cv2.LINE_AA)
    if len(ang) >= 2:
        amax = max(1.0, float(np.abs(off).max()) * 1.15)
        lo, hi = float(ang.min()), float(ang.max())

        def px(a: np.ndarray, v: np.ndarray) -> np.ndarray:
            xs = x0 + (a - lo) / max(hi - lo, 1e-9) * (x1 - x0)
            ys = (y0 + y1) / 2 - v / amax * (y1 - y0) / 2
            return np.column_stack([xs, ys]).round().astype(np.int32)

        cv2.line(panel, (x0, (y0 + y1) // 2), (x1, (y0 + y1) // 2), (200, 200, 200), 1)
        for k, (colour, name) in enumerate((((200, 90, 0), "x"), ((40, 40, 220), "y"))):
            cv2.polylines(panel, [px(ang, off[:, k])], False, colour, 2, cv2.LINE_AA)
            cv2.putText(panel, f"{name} (image)", (x1 - 110, y0 + 18 + 18 * k), FONT, 0.45,
                        colour, 1, cv2.LINE_AA)
        for v in (-amax / 1.15, amax / 1.15):
            y = round((y0 + y1) / 2 - v / amax * (y1 - y0) / 2)
            cv2.putText(panel, f"{v:+.1f}", (8, y + 4), FONT, 0.4, dark, 1, cv2.LINE_AA)
        for a in np.linspace(lo, hi, 5):
            x = round(x0 + (a - lo) / max(hi - lo, 1e-9) * (x1 - x0))
            cv2.putText(panel, f"{a:.0f}", (x - 12, y1 + 16), FONT, 0.4, dark, 1, cv2.LINE_AA)
        cv2.putText(panel, "read-back angle, deg", ((x0 + x1) // 2 - 70, y1 + 34), FONT, 0.45,
                    dark, 1, cv2.LINE_AA)
        cv2.putText(panel, f"peak {float(ro.get('amplitude_um') or 0):.2f} um, residual "
                    f"{float(ro.get('residual_um') or 0):.2f} um (1 sigma)",
                    (x0, PANEL_H - 10), FONT, 0.45, dark, 1, cv2.LINE_AA)
    else:
        cv2.putText(panel, "not measured", (x0 + 10, y0 + 30), FONT, 0.5, dark, 1, cv2.LINE_AA)
    return panel


def _findings(run: dict[str, Any]) -> np.ndarray:
    findings = [f for f in (run.get("result") or {}).get("findings") or []
                if isinstance(f, dict)]
    width_chars = (WIDTH - 255) // 6
    rows = [(f, wrap_words(str(f.get("message", "")), width_chars)[:3]) for f in findings]
    img = np.full((sum(ROW_H * len(lines) for _f, lines in rows) + 16, WIDTH, 3), 255,
                  np.uint8)
    y = 8
    for f, lines in rows:
        y += ROW_H
        verdict = str(f.get("verdict"))
        colour = VERDICT_COLOURS.get(verdict, (0, 0, 0))
        cv2.rectangle(img, (8, y - 13), (52, y + 3), colour, -1)
        cv2.putText(img, verdict, (12, y), FONT, 0.42, (255, 255, 255), 1, cv2.LINE_AA)
        cv2.putText(img, str(f.get("item")), (60, y), FONT, 0.42, (30, 30, 30), 1, cv2.LINE_AA)
        for k, line in enumerate(lines):
            cv2.putText(img, line, (245, y + k * (ROW_H - 3)), FONT, 0.38, (60, 60, 60), 1,
                        cv2.LINE_AA)
        y += (ROW_H - 3) * (len(lines) - 1)
        cv2.line(img, (8, y + 6), (WIDTH - 8, y + 6), (225, 225, 225), 1)
    return img


def render_commission(run: dict[str, Any], image: np.ndarray | None) -> np.ndarray:
    """The commission report image (BGR)."""
    left = _top_panel(run, image, WIDTH // 2)
    right = _plot_panel(run, WIDTH - WIDTH // 2)
    return np.vstack([_header(run), np.hstack([left, right]), _findings(run)])


def runout_peak(run: dict[str, Any]) -> float:
    """The runout map's peak (um), NaN if none (for callers that summarise)."""
    ro = (run.get("result") or {}).get("runout") or {}
    v = ro.get("amplitude_um")
    return float(v) if v is not None else math.nan
