"""Where a procedure writes its raw data: the ``RunRecorder`` protocol and two simple ones.

The daemon's SQLite store implements ``RunRecorder``; ``NullRecorder`` drops everything and
``MemoryRecorder`` keeps it in lists (tests, the benchmark, offline runs).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np


def image_hash(image: np.ndarray) -> str:
    """SHA-256 of an image's shape, dtype and pixels: the name frames are stored under."""
    h = hashlib.sha256()
    h.update(f"{image.shape}|{image.dtype}".encode())
    h.update(np.ascontiguousarray(image).tobytes())
    return h.hexdigest()


@runtime_checkable
class RunRecorder(Protocol):
    """Raw data of one run, written as it happens (the store keeps it crash-safe)."""

    def sweep(self, kind: str, iteration: int, sweep_json: dict[str, Any],
              commanded: list[float], readback: list[float]) -> None:
        """One sweep: ``sweep_json`` per the sweep-file contract; positions per frame."""

    def iteration(self, n: int, record: dict[str, Any]) -> None:
        """One iteration's results (offset, uncertainty, step, clamping...)."""

    def frame(self, image: np.ndarray, label: str) -> str:
        """Keep one frame; return its content hash."""

    def event(self, msg: str) -> None:
        """A notable event in words (warnings, refusals, calibration refreshes)."""


class NullRecorder:
    """Records nothing (frames still get their hash, so records can name them)."""

    def sweep(self, kind: str, iteration: int, sweep_json: dict[str, Any],
              commanded: list[float], readback: list[float]) -> None:
        pass

    def iteration(self, n: int, record: dict[str, Any]) -> None:
        pass

    def frame(self, image: np.ndarray, label: str) -> str:
        return image_hash(image)

    def event(self, msg: str) -> None:
        pass


@dataclass
class SweepRecord:
    kind: str
    iteration: int
    sweep_json: dict[str, Any]
    commanded: list[float]
    readback: list[float]


@dataclass
class MemoryRecorder:
    """Keeps everything in memory; images only if ``keep_images`` (they are large)."""

    keep_images: bool = False
    sweeps: list[SweepRecord] = field(default_factory=list)
    iterations: list[tuple[int, dict[str, Any]]] = field(default_factory=list)
    frames: list[tuple[str, str]] = field(default_factory=list)  # (label, hash)
    images: dict[str, np.ndarray] = field(default_factory=dict)
    events: list[str] = field(default_factory=list)

    def sweep(self, kind: str, iteration: int, sweep_json: dict[str, Any],
              commanded: list[float], readback: list[float]) -> None:
        self.sweeps.append(SweepRecord(kind, iteration, sweep_json, list(commanded),
                                       list(readback)))

    def iteration(self, n: int, record: dict[str, Any]) -> None:
        self.iterations.append((n, dict(record)))

    def frame(self, image: np.ndarray, label: str) -> str:
        digest = image_hash(image)
        self.frames.append((label, digest))
        if self.keep_images:
            self.images[digest] = image.copy()
        return digest

    def event(self, msg: str) -> None:
        self.events.append(msg)
