"""Issue 6, scenario 13: the camera fails mid-run (no frame, a stale frame, a blank or
saturated frame, the holder not found); no stage moves on the strength of it.

The direct simulated rig (ManualClock, non-rendering scene camera) with the stand-in
tracker for good frames; a blank or saturated frame goes to the real ``alignd.vision``."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from procedures_support import commanded, scene_rig, sim_config, standin_tools

from alignd.procedures import MemoryRecorder, ProgressEvent, run_alignment
from alignd.procedures.tools import Corners, as_corners
from drivers.camera import Camera, Frame
from drivers.errors import CameraError

TRANSLATIONS = ("x", "y", "z", "translator")


class FaultyCamera(Camera):
    """Wraps a camera; once ``armed``, every grab fails in the chosen way."""

    def __init__(self, inner: Camera, kind: str) -> None:
        super().__init__(inner.name, inner.source)
        self.inner = inner
        self.clock = inner.clock  # its frames are stamped on the inner camera's clock
        self.kind = kind
        self.armed = False

    def open(self) -> None:
        self.inner.open()

    def close(self) -> None:
        self.inner.close()

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        if not self.armed:
            return self.inner.grab(after, timeout_s)
        if self.kind == "no_frame":
            raise CameraError(f"no fresh frame within {timeout_s:.1f} s", device=self.name,
                              port=self.source)
        f = self.inner.grab(after, timeout_s)
        if self.kind == "stale":  # an old buffer: exposed before the stage settled
            return Frame(f.image, (after or self.clock.now()) - 0.5, f.seq, f.metadata)
        if self.kind == "holder_lost":  # the frame is fine, the holder is not in it
            return Frame(f.image, f.timestamp, f.seq, {"source": self.source})
        level = 0 if self.kind == "blank" else 255
        return Frame(np.full((720, 1280), level, np.uint8), self.clock.now(), f.seq, {})


def tracker(seed: int) -> Any:
    """Stand-in corners for scene frames; anything else goes to the real vision."""
    base = standin_tools(seed).track

    def track(frame: Frame) -> Corners:
        if "corners_px" in frame.metadata:
            return base(frame)
        if frame.image.shape == (720, 1280):
            from alignd.vision import track_holder

            return as_corners(track_holder(frame.gray))
        return Corners(np.full((4, 2), np.nan), False, 0.0, "holder not found")

    return track


@pytest.mark.parametrize(("kind", "why"), [
    ("no_frame", "no fresh frame"),
    ("stale", "stale frame"),
    ("blank", "blank image"),
    ("saturated", "blank image"),  # no contrast either way
    ("holder_lost", "holder tracked in only"),
])
def test_camera_fault_mid_run_moves_nothing_on_it(kind: str, why: str) -> None:
    cfg = sim_config(sweep_steps=7)
    rig, _ = scene_rig(cfg, 21)
    cam = FaultyCamera(rig.cameras["top"], kind)
    rig.cameras["top"] = cam
    before: dict[str, int] = {}

    def progress(ev: ProgressEvent) -> None:
        # after calibration, at the third frame of the first measuring sweep
        if ev.phase == "sweep" and ev.step == 3 and ev.iteration == 1 and not before \
                and ev.message.startswith("align"):
            before.update({r: len(commanded(rig, r)) for r in TRANSLATIONS})
            cam.armed = True

    rec = MemoryRecorder()
    res = run_alignment(rig, cfg, tools=standin_tools(21, track=tracker(21)), recorder=rec,
                        progress=progress)
    assert before, "the fault was never armed"
    assert res.verdict == "fault" and res.exit_code == 3
    assert why in res.reason, res.reason
    assert res.reason.startswith(("device error", "measurement failed")), res.reason
    # no translation stage was commanded after the bad frame (the turntable may sweep on)
    assert {r: len(commanded(rig, r)) for r in TRANSLATIONS} == before
    assert not [r for _, r in rec.iterations if r.get("action") == "move"]
    assert not any(a.moving for a in rig.sim_parts.sim_axes.values())  # type: ignore


def test_holder_not_found_at_the_start_moves_nothing_at_all() -> None:
    cfg = sim_config(sweep_steps=7)
    rig, _ = scene_rig(cfg, 22)
    cam = FaultyCamera(rig.cameras["top"], "blank")
    cam.armed = True
    rig.cameras["top"] = cam
    res = run_alignment(rig, cfg, tools=standin_tools(22, track=tracker(22)))
    assert res.verdict == "fault" and "blank image" in res.reason
    for role in (*TRANSLATIONS, "turntable"):
        assert commanded(rig, role) == [], role
