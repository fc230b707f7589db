"""The ``Camera`` interface and the real camera sources (contract: camera sources).

A frame is only useful if it was exposed after the last move settled: ``grab(after=t)``
discards buffered frames older than ``t`` (a ``time.monotonic()`` value) and raises
``CameraError`` rather than return a stale frame.
"""

from __future__ import annotations

import logging
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Self

import numpy as np

from drivers.clock import SYSTEM_CLOCK, Clock

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Frame:
    """One grabbed image: 8-bit grey (H, W) or BGR (H, W, 3), with when and how."""

    image: np.ndarray
    timestamp: float  # the camera's clock (time.monotonic()) at mid-exposure (best estimate)
    seq: int
    metadata: dict[str, Any] = field(default_factory=dict)

    @property
    def gray(self) -> np.ndarray:
        if self.image.ndim == 2:
            return self.image
        import cv2

        return cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY)


class Camera(ABC):
    """A source of frames. Context manager; ``open``/``close`` are idempotent."""

    def __init__(self, name: str, source: str) -> None:
        self.name = name
        self.source = source
        # the clock a frame's ``timestamp`` and ``grab(after=...)`` are on: the machine's
        # monotonic clock for real cameras; a simulated rig's manual clock for its cameras
        self.clock: Clock = SYSTEM_CLOCK

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        """A frame exposed after ``after`` (monotonic seconds), or raise ``CameraError``."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _decode(data: bytes, source: str, name: str) -> np.ndarray:
    import cv2

    from drivers.errors import CameraError

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CameraError("snapshot is not a decodable PNG/JPEG image", device=name, port=source)
    return img


class OpenCVCamera(Camera):
    """A V4L2/UVC device (index or path), a video file or a stream URL, via VideoCapture.

    ``grab(after=t)`` reads and discards frames until one is read after ``t``: V4L2 keeps
    a few buffers, so the first frames after a move may have been exposed during it.
    """

    def __init__(self, name: str, source: str, *, width: int | None = None,
                 height: int | None = None, exposure: float | None = None,
                 settle_frames: int = 1) -> None:
        super().__init__(name, source)
        self.width, self.height, self.exposure = width, height, exposure
        self.settle_frames = settle_frames
        self._cap: Any = None
        self._seq = 0

    def open(self) -> None:
        if self._cap is not None:
            return
        import cv2

        from drivers.errors import CameraError

        src: int | str = int(self.source) if self.source.isdigit() else self.source
        cap = cv2.VideoCapture(src)
        if not cap.isOpened():
            raise CameraError("cannot open camera source (check the device index/path, "
                              "permissions (group 'video') or the URL)", device=self.name,
                              port=self.source)
        if self.width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.width)
        if self.height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
        if self.exposure is not None:
            cap.set(cv2.CAP_PROP_EXPOSURE, self.exposure)
        self._cap = cap

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        import cv2

        from drivers.errors import CameraError

        if self._cap is None:
            self.open()
        deadline = time.monotonic() + timeout_s
        discard = self.settle_frames if after is not None else 0
        while True:
            ok, img = self._cap.read()
            t = time.monotonic()
            if not ok or img is None:
                raise CameraError("no frame from camera (unplugged, or end of the video)",
                                  device=self.name, port=self.source)
            if after is None or (t > after and discard <= 0):
                break
            discard -= 1
            if t > deadline:
                raise CameraError(f"no fresh frame within {timeout_s:.1f} s", device=self.name,
                                  port=self.source)
        self._seq += 1
        meta: dict[str, Any] = {"source": self.source}
        for key, prop in (("exposure", cv2.CAP_PROP_EXPOSURE), ("gain", cv2.CAP_PROP_GAIN)):
            val = self._cap.get(prop)
            if val not in (0.0, -1.0):
                meta[key] = float(val)
        return Frame(img, t, self._seq, meta)


class ReplayCamera(Camera):
    """Frames from an image folder (sorted by name) or a video file, in order, once."""

    EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")

    def __init__(self, name: str, source: str) -> None:
        super().__init__(name, source)
        self._files: list[str] | None = None
        self._video: OpenCVCamera | None = None
        self._seq = 0

    def open(self) -> None:
        import os

        from drivers.errors import CameraError

        if self._files is not None or self._video is not None:
            return
        if os.path.isdir(self.source):
            self._files = sorted(os.path.join(self.source, f) for f in os.listdir(self.source)
                                 if f.lower().endswith(self.EXTENSIONS))
            if not self._files:
                raise CameraError("image folder holds no images", device=self.name,
                                  port=self.source)
        elif os.path.isfile(self.source):
            self._video = OpenCVCamera(self.name, self.source, settle_frames=0)
            self._video.open()
        else:
            raise CameraError("replay source does not exist", device=self.name,
                              port=self.source)

    def close(self) -> None:
        if self._video is not None:
            self._video.close()
        self._files = None
        self._video = None

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        import cv2

        from drivers.errors import CameraError

        self.open()
        if self._video is not None:
            return self._video.grab(None, timeout_s)
        assert self._files is not None
        if self._seq >= len(self._files):
            raise CameraError("replay exhausted: no more images", device=self.name,
                              port=self.source)
        path = self._files[self._seq]
        img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CameraError(f"cannot read image {path}", device=self.name, port=self.source)
        self._seq += 1
        return Frame(img, time.monotonic(), self._seq, {"file": path})


class SnapshotCamera(Camera):
    """An ``http(s)://`` snapshot URL fetched once per frame (PNG or JPEG)."""

    def __init__(self, name: str, source: str, *, timeout_s: float = 5.0) -> None:
        super().__init__(name, source)
        self.timeout_s = timeout_s
        self._seq = 0

    def open(self) -> None:
        """Nothing to hold open: every grab is one request."""

    def close(self) -> None:
        """Nothing to release."""

    def grab(self, after: float | None = None, timeout_s: float = 2.0) -> Frame:
        import urllib.error
        import urllib.request

        from drivers.errors import CameraError

        t = time.monotonic()  # the request starts after ``after``: the exposure does too
        try:
            with urllib.request.urlopen(self.source, timeout=max(timeout_s, 0.1)) as resp:
                data = resp.read(64 * 1024 * 1024)
        except (urllib.error.URLError, OSError, ValueError) as exc:
            raise CameraError(f"snapshot request failed: {exc}", device=self.name,
                              port=self.source) from exc
        self._seq += 1
        return Frame(_decode(data, self.source, self.name), t, self._seq, {"url": self.source})


def open_camera(name: str, source: str, *, width: int | None = None, height: int | None = None,
                exposure: float | None = None, settle_frames: int = 1) -> Camera:
    """The camera for a configured ``source`` (all but the simulator's, see drivers.sim)."""
    import os

    if source.startswith(("http://", "https://")) and not source.lower().endswith(
            (".mjpg", ".mjpeg", "mjpg", "video")):
        return SnapshotCamera(name, source)
    if os.path.isdir(source) or (os.path.isfile(source) and not source.startswith("/dev/")):
        return ReplayCamera(name, source)
    return OpenCVCamera(name, source, width=width, height=height, exposure=exposure,
                        settle_frames=settle_frames)
