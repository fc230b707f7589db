"""The live camera views: the worker's latest frame with the tracked holder, the centre of
rotation and the target drawn on it, as JPEG.

The holder is tracked here, in the web thread, on the frame the worker grabbed (cached per
frame, so a second viewer costs nothing). The centre comes from the newest run that
measured one (the current run's latest iteration while a run is in progress): the axis
stays where it is in the image as long as the camera is not moved.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np

from alignd.config import AligndConfig
from alignd.report import to_bgr8
from alignd.web.frames import LiveFrame, LiveFrames

if TYPE_CHECKING:
    from alignd.vision import HolderDetection

log = logging.getLogger(__name__)

VIEW_WIDTH = 640
HOLDER_COLOUR = (60, 220, 60)
CENTRE_COLOUR = (0, 230, 255)
TARGET_COLOUR = (255, 0, 255)


class RunSource(Protocol):
    """What the live view reads from the daemon."""

    cfg: AligndConfig
    live: LiveFrames

    def status(self) -> dict[str, Any]: ...
    def history(self, limit: int) -> list[dict[str, Any]]: ...
    def run(self, run_id: int) -> dict[str, Any] | None: ...


@dataclass(frozen=True)
class Centre:
    """A measured centre of rotation in top-camera pixels, and which run measured it."""

    px: tuple[float, float]
    cov_px2: np.ndarray | None
    run_id: int


def centre_of_run(run: dict[str, Any]) -> Centre | None:
    from alignd.report import _centre_record, _find

    rec = _centre_record(run)
    if rec is None:
        return None
    c = np.asarray(_find(rec, ("centre_px", "center_px")), float)
    cov = _find(rec, ("cov_centre_px2", "cov_center_px2", "cov_px2"))
    return Centre((float(c[0]), float(c[1])), None if cov is None else np.asarray(cov, float),
                  int(run.get("id") or 0))


class LiveView:
    """JPEG views of the latest frames, with overlays; thread-safe, cached per frame."""

    def __init__(self, source: RunSource) -> None:
        self.source = source
        self._lock = threading.Lock()
        self._cache: dict[str, tuple[tuple[Any, ...], bytes, dict[str, Any]]] = {}
        self._centre_key: tuple[Any, ...] | None = None
        self._centre: Centre | None = None
        self._hint: HolderDetection | None = None  # the previous frame's, to track from

    def centre(self) -> Centre | None:
        """The newest measured centre (re-read only when a run starts, ends or iterates)."""
        st = self.source.status()
        prog = st.get("progress") or {}
        last = st.get("last_run") or {}
        key = (st.get("run_id"), prog.get("iteration"), prog.get("phase"), last.get("id"))
        if key == self._centre_key:
            return self._centre
        found: Centre | None = None
        ids = ([st["run_id"]] if st.get("run_id") else []) + \
            [int(r["id"]) for r in self.source.history(10)]
        for run_id in dict.fromkeys(ids):
            run = self.source.run(int(run_id))
            if run is not None and (found := centre_of_run(run)) is not None:
                break
        self._centre_key, self._centre = key, found
        return found

    def view(self, role: str) -> tuple[bytes, dict[str, Any]] | None:
        """(JPEG, what is shown) for a camera role, or None if it never delivered a frame."""
        self.source.live.watch()
        frame = self.source.live.get(role)
        if frame is None or frame.image is None:
            return None
        with self._lock:
            centre = self.centre() if role == "top" else None
            key = (frame.seq, centre.run_id if centre else None,
                   centre.px if centre else None)
            hit = self._cache.get(role)
            if hit is not None and hit[0] == key:
                return hit[1], hit[2]
            jpeg, info = self._render(frame, centre)
            self._cache[role] = (key, jpeg, info)
            return jpeg, info

    def _render(self, frame: LiveFrame, centre: Centre | None) -> tuple[bytes, dict[str, Any]]:
        assert frame.image is not None
        img = frame.image
        view = to_bgr8(img)
        info: dict[str, Any] = {"role": frame.role, "seq": frame.seq,
                                "age_s": None if frame.wall_time is None
                                else round(time.time() - frame.wall_time, 1),
                                "error": frame.error}
        scale = VIEW_WIDTH / view.shape[1]
        small = cv2.resize(view, (VIEW_WIDTH, round(view.shape[0] * scale)),
                           interpolation=cv2.INTER_AREA)
        if frame.role == "top":
            info.update(self._draw_top(small, img, scale, centre))
        ok, buf = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 80])
        if not ok:
            raise ValueError(f"cannot encode the {frame.role} camera's frame as JPEG")
        return buf.tobytes(), info

    def _draw_top(self, small: np.ndarray, full: np.ndarray, scale: float,
                  centre: Centre | None) -> dict[str, Any]:
        from alignd.procedures.holder_geometry import holder_pose
        from alignd.vision import Lens, linearise, track_holder

        def pt(p: Any) -> tuple[int, int]:
            return round(float(p[0]) * scale), round(float(p[1]) * scale)

        info: dict[str, Any] = {"holder": None, "centre_px": None, "centre_run": None}
        gray = full if full.ndim == 2 else cv2.cvtColor(full, cv2.COLOR_BGR2GRAY)
        cam = self.source.cfg.camera("top")
        # a run's centre is in the undistorted image (the configured lens); drawn in the frame
        centre_here = None if centre is None else np.asarray(centre.px, float)
        if centre_here is not None and cam is not None and cam.lens is not None:
            centre_here = Lens.of(cam.lens).distort(centre_here[None])[0]
        try:
            det = track_holder(linearise(gray, cam.gamma if cam is not None else 1.0),
                               hint=self._hint)
            corners = np.asarray(det.corners_px, float).reshape(4, 2)
            if not (det.ok and np.all(np.isfinite(corners))):
                raise ValueError(getattr(det, "reason", "") or "fit failed")
        except Exception as exc:  # the view says so; tracking is the procedure's to judge
            self._hint = None
            info["holder"] = f"not found ({exc})"
            corners = None
        if corners is not None:
            self._hint = det
            info["holder"] = "tracked"
            cv2.polylines(small, [np.array([pt(c) for c in corners], np.int32)], True,
                          HOLDER_COLOUR, 2, cv2.LINE_AA)
            cv2.circle(small, pt(corners[0]), 4, HOLDER_COLOUR, -1, cv2.LINE_AA)
            target = holder_pose(corners, self.source.cfg.holder).target_px
            cv2.circle(small, pt(target), 6, TARGET_COLOUR, 2, cv2.LINE_AA)
            info["target_px"] = [round(float(v), 2) for v in target]
            if centre is not None:
                cv2.line(small, pt(centre_here), pt(target), TARGET_COLOUR, 1, cv2.LINE_AA)
        if centre is not None:
            cv2.drawMarker(small, pt(centre_here), CENTRE_COLOUR, cv2.MARKER_CROSS, 22, 2,
                           cv2.LINE_AA)
            info["centre_px"] = [round(v, 2) for v in centre.px]
            info["centre_run"] = centre.run_id
        return info
