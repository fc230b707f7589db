"""The run report's side-camera panel: the tilt pre-check's first frame with the pole and
the sample edge drawn on it, beside the pre-check's numbers.

The record holds the pre-check's mean tilt and every side frame's hash, not each frame's
fitted lines, so the first frame is measured again here, as the pre-check measured it
(in the configured regions, the side camera's tone curve undone), to show where the edges
were found.
"""

from __future__ import annotations

import logging
from typing import Any

import cv2
import numpy as np

from alignd.config import SIDE_FIRST_LABEL, SIDE_FRAME_PREFIX
from alignd.errors import AligndError
from alignd.textfmt import wrap_words
from alignd.vision.edges import linearise
from alignd.vision.side import SIGN_CONVENTION, SideMeasurement, measure_tilt
from drivers.config import ToneCurve

__all__ = ["draw_side_panel", "measure_again", "side_frame_hash"]

log = logging.getLogger(__name__)

FONT = cv2.FONT_HERSHEY_SIMPLEX
SAMPLE_INK = (0, 0, 230)  # red, as alignctl analyze side draws it
POLE_INK = (0, 170, 0)  # green
REGION_INK = (0, 200, 255)
PAPER = (245, 245, 245)


def side_frame_hash(run: dict[str, Any]) -> str | None:
    """The hash of the tilt pre-check's first side frame, or None (none recorded)."""
    for f in run.get("frames") or []:
        if isinstance(f, dict) and f.get("label") == SIDE_FIRST_LABEL and f.get("hash"):
            return str(f["hash"])
    return None


Region = tuple[int, int, int, int]


def _region(box: object) -> Region | None:
    if isinstance(box, list | tuple) and len(box) == 4 and all(
            isinstance(v, int | float) for v in box):
        return int(box[0]), int(box[1]), int(box[2]), int(box[3])
    return None


def _regions(run: dict[str, Any]) -> tuple[Region | None, Region | None]:
    """The configured pole and sample regions of the run's config (None: automatic)."""
    side = ((run.get("config") or {}).get("side_camera") or {})
    return _region(side.get("pole_roi_px")), _region(side.get("sample_roi_px"))


def _tone_curve(run: dict[str, Any]) -> ToneCurve:
    """The run config's side camera's ``gamma`` (1: none configured)."""
    for cam in (run.get("config") or {}).get("cameras") or []:
        if isinstance(cam, dict) and cam.get("role") == "side":
            gamma = cam.get("gamma")
            if gamma == "srgb" or gamma == "bt709":
                return gamma
            return float(gamma) if isinstance(gamma, int | float) else 1.0
    return 1.0


def measure_again(run: dict[str, Any], image: np.ndarray
                  ) -> tuple[SideMeasurement | None, str]:
    """The side frame ``image`` of ``run`` measured as its pre-check measured it (the run
    config's regions and the side camera's tone curve), or None and why not."""
    regions = _regions(run)
    try:
        return measure_tilt(linearise(image, _tone_curve(run)), pole_roi_px=regions[0],
                            sample_roi_px=regions[1]), ""
    except AligndError as exc:
        log.info("report: the side frame measured again: %s", exc)
        return None, str(exc)


def draw_side_panel(run: dict[str, Any], image: np.ndarray, width: int) -> np.ndarray:
    """The panel (BGR, ``width`` wide): the frame at half the width with the edges found
    in it (the sample's red, the pole's green; the configured regions as boxes), and the
    pre-check's tilt beside it."""
    gray = np.asarray(image)
    regions = _regions(run)
    m, why = measure_again(run, gray)
    shown = gray if gray.dtype == np.uint8 else (  # 12 bits in 16: scaled to its peak
        255.0 * gray / max(float(gray.max()), 1.0)).astype(np.uint8)
    view_w = width // 2
    scale = view_w / shown.shape[1]
    view = cv2.resize(shown, (view_w, round(shown.shape[0] * scale)),
                      interpolation=cv2.INTER_AREA)
    view = cv2.cvtColor(view, cv2.COLOR_GRAY2BGR) if view.ndim == 2 else view[:, :, :3].copy()
    for box in regions:
        if box is not None:
            cv2.rectangle(view, (round(box[0] * scale), round(box[1] * scale)),
                          (round(box[2] * scale), round(box[3] * scale)), REGION_INK, 1)
    if m is not None:
        for edges, ink in ((m.sample_edges, SAMPLE_INK), (m.pole_edges, POLE_INK)):
            for e in edges:
                ends = [(float(e.line.minor_at(y)) * scale, y * scale) for y in e.rows]
                cv2.line(view, (round(ends[0][0]), round(ends[0][1])),
                         (round(ends[1][0]), round(ends[1][1])), ink, 2, cv2.LINE_AA)
    panel = np.full((max(view.shape[0], 200), width, 3), PAPER, np.uint8)
    panel[:view.shape[0], :view_w] = view
    res = run.get("result") or {}
    n = sum(1 for f in run.get("frames") or []
            if isinstance(f, dict) and str(f.get("label", "")).startswith(SIDE_FRAME_PREFIX))
    lines = ["side camera: the tilt pre-check's first frame"]
    tilt, u = res.get("tilt_deg"), res.get("tilt_u_deg")
    if isinstance(tilt, int | float):
        pm = f" +/- {u:.4f}" if isinstance(u, int | float) else ""
        lines.append(f"tilt {tilt:+.4f}{pm} deg (mean of {n} frame{'' if n == 1 else 's'}, "
                     "u k=1)")
    if m is not None:
        lines.append(f"this frame: sample {m.sample_angle_deg:+.4f}, pole "
                     f"{m.pole_angle_deg:+.4f} deg")
        lines.append("red: the sample's edges; green: the pole's"
                     + ("; boxes: the configured regions" if any(regions) else
                        " (found automatically)"))
    else:
        lines.append(f"edges not found in this frame: {why}")
    lines.append(SIGN_CONVENTION)
    x, y, text_w = view_w + 12, 22, width - view_w - 20
    for k, line in enumerate(lines):
        for part in wrap_words(line, text_w // 8):  # about 8 px a character at 0.45
            if y > panel.shape[0] - 6:
                return panel
            cv2.putText(panel, part, (x, y), FONT, 0.5 if k == 0 else 0.45, (30, 30, 30), 1,
                        cv2.LINE_AA)
            y += 19
        y += 4
    return panel
