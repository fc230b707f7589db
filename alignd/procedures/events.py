"""Progress events: what a running procedure tells its observer (daemon status, CLI).

Procedures call a ``progress(event)`` callback; the daemon forwards events to ``alignctl``
so an operator sees the sweep step, the iteration and the latest offset live.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Literal, get_args

Phase = Literal["connect", "home", "precheck", "calibrate", "sweep", "solve", "move", "verify",
                "done",
                # commissioning's steps
                "top", "axes", "turntable"]
PHASES: tuple[Phase, ...] = get_args(Phase)


@dataclass(frozen=True)
class ProgressEvent:
    """One progress report. Fields that do not apply are None."""

    phase: Phase
    message: str
    step: int | None = None  # e.g. sweep frame 5 ...
    total: int | None = None  # ... of 21
    iteration: int | None = None
    offset_um: tuple[float, float] | None = None  # turntable frame
    offset_norm_um: float | None = None
    U_um: float | None = None
    timestamp: float = field(default_factory=time.time)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if self.offset_um is not None:
            d["offset_um"] = [float(v) for v in self.offset_um]
        return d

    def __str__(self) -> str:
        parts = [f"[{self.phase}]"]
        if self.iteration is not None:
            parts.append(f"it {self.iteration}")
        if self.step is not None and self.total is not None:
            parts.append(f"{self.step}/{self.total}")
        parts.append(self.message)
        if self.offset_norm_um is not None:
            u = f" ± {self.U_um:.1f}" if self.U_um is not None else ""
            parts.append(f"offset {self.offset_norm_um:.1f}{u} um")
        return " ".join(parts)


ProgressCallback = Callable[[ProgressEvent], None]


def no_progress(event: ProgressEvent) -> None:
    """The default callback: ignore progress."""
