"""Issue 14: the dashboard's camera views come from the worker's own grabs (one open per
camera), previews only while someone watches, and a camera that fails is shown, not fatal."""

from __future__ import annotations

import numpy as np
import pytest

from alignd.web.frames import LiveFrames, TappedCamera, grab_previews, tap_cameras
from drivers.camera import Camera, Frame
from drivers.errors import CameraError


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


class CountingCamera(Camera):
    def __init__(self) -> None:
        super().__init__("cam", "fake")
        self.opens = self.grabs = 0
        self.broken = False

    def open(self) -> None:
        self.opens += 1

    def close(self) -> None:
        pass

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        if self.broken:
            raise CameraError("no frame within 1.0 s", device="cam", port="fake",
                              command="grab")
        self.grabs += 1
        return Frame(np.full((8, 8), self.grabs, np.uint8), 0.0, self.grabs)


def test_previews_only_while_watched_and_at_most_fps() -> None:
    clock = Clock()
    live = LiveFrames(fps=4.0, linger_s=10.0, clock=clock)
    assert not live.preview_due() and live.wait_s(1.0) == 1.0  # nobody watching
    live.watch()
    assert live.wait_s(1.0, idle=False) == 1.0  # a busy or faulted worker keeps its tick
    assert live.wait_s(1.0) == 0.01  # due now
    assert live.preview_due() and not live.preview_due()  # once per period
    clock.t += 0.1  # the grab took 0.1 s: the next one is due 0.15 s from now
    assert live.wait_s(1.0) == pytest.approx(0.15)
    clock.t += 0.15
    assert live.preview_due()
    clock.t += 10.1  # the viewer left
    assert not live.preview_due() and live.wait_s(1.0) == 1.0


def test_the_procedures_grabs_are_the_views_and_failures_are_shown() -> None:
    cam = CountingCamera()
    cameras: dict[str, Camera] = {"top": cam}
    live = LiveFrames()
    tap_cameras(cameras, live)
    tap_cameras(cameras, live)  # idempotent
    assert isinstance(cameras["top"], TappedCamera) and cameras["top"].inner is cam
    cameras["top"].open()
    frame = cameras["top"].grab()  # what a sweep does
    got = live.get("top")
    assert got is not None and got.image is not None and cam.opens == 1
    assert np.shares_memory(got.image, frame.image)  # the same frame, not a copy
    grab_previews(cameras, live)  # what the idle worker does
    assert int(live.get("top").image[0, 0]) == 2 and cam.grabs == 2  # type: ignore[union-attr, index]
    cam.broken = True
    grab_previews(cameras, live)  # must not raise
    failed = live.get("top")
    assert failed is not None and "no frame within" in str(failed.error)
    assert int(failed.image[0, 0]) == 2  # type: ignore[index]  # the last good frame stays
    assert len(live.drain_grab_seconds()) == 2 and live.drain_grab_seconds() == []


def test_the_web_cannot_write_into_the_procedures_frame() -> None:
    """The live view reads (and tracks on) the same array the procedure measures, from
    another thread, without a copy: it gets it read-only."""
    live = LiveFrames()
    tapped = TappedCamera("top", CountingCamera(), live)
    frame = tapped.grab()
    shown = live.get("top")
    assert shown is not None and shown.image is not None
    assert np.shares_memory(shown.image, frame.image)  # no copy per grab
    with pytest.raises(ValueError, match="read-only"):
        shown.image[0, 0] = 255
    assert frame.image.flags.writeable and int(frame.image[0, 0]) == 1
