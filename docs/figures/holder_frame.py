"""Draws docs/holder-frame.png: the holder frame on a simulated top-camera view.

Run from the repository root: ``.venv/bin/python docs/figures/holder_frame.py``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from alignd.vision.holder import order_corners  # noqa: E402
from drivers.config import SimWorldConfig  # noqa: E402
from drivers.sim.render import RenderOptions, posed_world, render_top  # noqa: E402

OUT = ROOT / "docs" / "holder-frame.png"
SCALE = 2  # drawn at twice the camera's resolution, cropped round the holder


def main() -> None:
    cfg = SimWorldConfig(holder_size_mm=(40.0, 25.0), rim_radius_mm=50.0, yaw_deg=4.0,
                         initial_offset_mm=(6.0, 3.0), top_camera_zenith_deg=0.0)
    w = posed_world(cfg, seed=1)
    scene = w.top_scene()
    img = render_top(scene, w.top_camera, RenderOptions(read_noise_dn=0.0))
    cam = w.top_camera
    corners = order_corners(cam.project(scene.holder_corners_mm))
    target = cam.project(scene.target_mm[None, :])[0]
    axis = np.array(cam.principal_px)
    pts = np.vstack([corners, [axis], [target]])
    x0, y0 = (pts.min(axis=0) - [150, 190]).astype(int)
    x1, y1 = (pts.max(axis=0) + [150, 90]).astype(int)
    crop = cv2.cvtColor(img[y0:y1, x0:x1], cv2.COLOR_GRAY2BGR)
    crop = cv2.resize(crop, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_CUBIC)

    def p(pt: np.ndarray) -> tuple[int, int]:
        return (int(round((pt[0] - x0) * SCALE)), int(round((pt[1] - y0) * SCALE)))

    font = cv2.FONT_HERSHEY_SIMPLEX
    blue, red, green, dark = (200, 90, 0), (40, 40, 220), (40, 150, 40), (30, 30, 30)
    centre = corners.mean(axis=0)
    for i, c in enumerate(corners):
        cv2.circle(crop, p(c), 9, red, 3, cv2.LINE_AA)
        off = (c - centre) / np.linalg.norm(c - centre) * 34
        cv2.putText(crop, f"corner {i}", p(c + off + np.array([-22, 6])), font, 0.8, red, 2,
                    cv2.LINE_AA)
    u = (corners[1] - corners[0]) / np.linalg.norm(corners[1] - corners[0])
    v = (corners[3] - corners[0]) / np.linalg.norm(corners[3] - corners[0])
    cv2.arrowedLine(crop, p(centre), p(centre + u * 70), blue, 3, cv2.LINE_AA, tipLength=0.2)
    cv2.arrowedLine(crop, p(centre), p(centre + v * 70), blue, 3, cv2.LINE_AA, tipLength=0.25)
    cv2.putText(crop, "+u", p(centre + u * 78 + np.array([0, 6])), font, 0.9, blue, 2,
                cv2.LINE_AA)
    cv2.putText(crop, "+v", p(centre + v * 80 + np.array([-10, 12])), font, 0.9, blue, 2,
                cv2.LINE_AA)
    cv2.circle(crop, p(centre), 5, blue, -1, cv2.LINE_AA)
    cv2.drawMarker(crop, p(target), green, cv2.MARKER_CROSS, 26, 3, cv2.LINE_AA)
    cv2.arrowedLine(crop, p(centre), p(target), green, 2, cv2.LINE_AA, tipLength=0.08)
    cv2.putText(crop, "target_mm = [0, -17.5]", p(target + np.array([14, -14])), font, 0.8,
                green, 2, cv2.LINE_AA)
    cv2.putText(crop, "(middle of the sample surface)", p(target + np.array([14, 0])), font,
                0.6, green, 2, cv2.LINE_AA)
    # the rotation axis and the turning sense of +angle (R(a), y down: clockwise on screen)
    ax = p(axis)
    cv2.drawMarker(crop, ax, dark, cv2.MARKER_TILTED_CROSS, 22, 2, cv2.LINE_AA)
    cv2.putText(crop, "axis", (ax[0] + 14, ax[1] + 30), font, 0.7, dark, 2, cv2.LINE_AA)
    r = 150
    pts = [(ax[0] + r * math.cos(math.radians(a)), ax[1] + r * math.sin(math.radians(a)))
           for a in np.linspace(200, 250, 20)]
    pts_i = np.array(pts, np.int32)  # screen clockwise = increasing angle in y-down axes
    cv2.polylines(crop, [pts_i], False, dark, 2, cv2.LINE_AA)
    cv2.arrowedLine(crop, tuple(pts_i[-2]), tuple(pts_i[-1]), dark, 2, cv2.LINE_AA,
                    tipLength=3.0)
    cv2.putText(crop, "+angle: clockwise on screen",
                (int(pts[0][0]) - 330, int(pts[0][1]) - 40), font, 0.7, dark, 2, cv2.LINE_AA)
    cv2.putText(crop, "(procedure.turntable_direction: 1)",
                (int(pts[0][0]) - 330, int(pts[0][1]) - 12), font, 0.6, dark, 2, cv2.LINE_AA)
    # the image axes
    o = np.array([30, 30])
    cv2.arrowedLine(crop, tuple(o), tuple(o + [90, 0]), dark, 2, cv2.LINE_AA, tipLength=0.2)
    cv2.arrowedLine(crop, tuple(o), tuple(o + [0, 90]), dark, 2, cv2.LINE_AA, tipLength=0.2)
    cv2.putText(crop, "image x", tuple(o + [96, 8]), font, 0.7, dark, 2, cv2.LINE_AA)
    cv2.putText(crop, "image y", tuple(o + [-10, 120]), font, 0.7, dark, 2, cv2.LINE_AA)
    cv2.putText(crop, "top camera, turntable at 0 deg; holder.size_mm = [40, 25] = [u, v]",
                (20, crop.shape[0] - 20), font, 0.75, dark, 2, cv2.LINE_AA)
    cv2.imwrite(str(OUT), crop)
    print(OUT)


if __name__ == "__main__":
    main()
