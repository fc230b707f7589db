"""The ``Camera`` interface and the real camera sources (contract: camera sources).

A frame is only useful if it was exposed after the last move settled: ``grab(after=t)``
discards buffered frames older than ``t`` (a ``time.monotonic()`` value) and raises
``CameraError`` rather than return a stale frame.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, Self

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Frame:
    """One grabbed image: 8-bit grey (H, W) or BGR (H, W, 3), with when and how."""

    image: np.ndarray
    timestamp: float  # time.monotonic() at exposure (best estimate)
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
