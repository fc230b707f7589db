"""The closed-loop procedures against the Axis/Camera interfaces (vendor-agnostic).

``run_alignment`` / ``run_check`` take a ``Rig`` (axes and cameras by role), the instrument
config, a progress callback, an abort event and a ``RunRecorder``; they return a
``RunResult`` whose ``to_json()`` is the run-result contract.
"""

from alignd.procedures.align import run_alignment, run_check
from alignd.procedures.calibrate import Calibration, CalibrationError, calibrate
from alignd.procedures.events import ProgressCallback, ProgressEvent
from alignd.procedures.recorder import MemoryRecorder, NullRecorder, RunRecorder
from alignd.procedures.result import EXIT_CODES, VERDICTS, RunResult
from alignd.procedures.rig import AbortRequested, Rig
from alignd.procedures.tools import Corners, Tools, default_tools

__all__ = [
    "EXIT_CODES",
    "VERDICTS",
    "AbortRequested",
    "Calibration",
    "CalibrationError",
    "Corners",
    "MemoryRecorder",
    "NullRecorder",
    "ProgressCallback",
    "ProgressEvent",
    "Rig",
    "RunRecorder",
    "RunResult",
    "Tools",
    "calibrate",
    "default_tools",
    "run_alignment",
    "run_check",
]
