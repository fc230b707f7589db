"""alignd's one exception tree. The root and the device branch live in ``drivers.errors``
(drivers must not import alignd); this module re-exports them and adds the rest."""

from drivers.errors import (
    AligndError,
    CameraError,
    DeviceError,
    DeviceFault,
    DeviceTimeoutError,
    LimitError,
    MissedTargetError,
    PortBusyError,
    ProtocolError,
    TransportError,
)

__all__ = [
    "AligndError",
    "CameraError",
    "ConfigError",
    "DeviceError",
    "DeviceFault",
    "DeviceTimeoutError",
    "HolderFrameError",
    "InputError",
    "LimitError",
    "MissedTargetError",
    "PortBusyError",
    "ProtocolError",
    "SolveError",
    "StateError",
    "TransportError",
    "VisionError",
]


class ConfigError(AligndError):
    """A config file is missing, malformed, or inconsistent (names file and key path)."""


class HolderFrameError(ConfigError):
    """The config's holder frame disagrees with what a sweep saw (the target on the holder's
    other side, u and v swapped); ``evidence`` is what the run's picture draws: the axis and
    the targets in the top image (JSON-ready)."""

    def __init__(self, message: str, evidence: dict[str, object]) -> None:
        super().__init__(message)
        self.evidence = evidence


class InputError(AligndError):
    """A data file (sweep file, image) is malformed; the message says what and where."""


class SolveError(AligndError):
    """The data cannot determine a centre (too few frames, no angular spread, ...)."""


class VisionError(AligndError):
    """No target found in an image, or the image is unusable (blank, saturated)."""


class StateError(AligndError):
    """The request does not fit the daemon's state (busy, faulted, not connected)."""
