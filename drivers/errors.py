"""The root of alignd's one exception tree, and its device branch.

``AligndError`` lives here (not in ``alignd``) because ``drivers`` must not import
``alignd``; ``alignd.errors`` re-exports it and adds the config/state/solve branches.
Every device error message names the device, the port and the command involved.
"""

from __future__ import annotations


class AligndError(Exception):
    """Root of every error alignd raises on purpose."""


class DeviceError(AligndError):
    """Something went wrong talking to or moving a device."""

    def __init__(
        self,
        message: str,
        *,
        device: str | None = None,
        port: str | None = None,
        command: str | None = None,
    ) -> None:
        self.device = device
        self.port = port
        self.command = command
        where = []
        if device:
            where.append(f"device {device}")
        if port:
            where.append(f"port {port}")
        if command:
            where.append(f"command {command!r}")
        super().__init__(f"{message} ({', '.join(where)})" if where else message)
        self.detail = message


class TransportError(DeviceError):
    """The port could not be opened, vanished, or an I/O call failed."""


class PortBusyError(TransportError):
    """The port is held by another process (exclusive open failed)."""


class ProtocolError(DeviceError):
    """A reply was malformed, truncated, had a bad checksum or did not match the command."""


class DeviceTimeoutError(DeviceError):
    """No (complete) reply in time, or a move outlasted its computed timeout."""


class LimitError(DeviceError):
    """A target outside the soft limits (or not finite), or a hardware limit switch hit."""


class DeviceFault(DeviceError):
    """The controller reports a fault: stall, following error, rejected command, not homed."""


class ConfigMismatchError(DeviceError):
    """The controller disagrees with the config in a way that changes units or travel."""


class MissedTargetError(DeviceFault):
    """The read-back position stayed outside the deadband after all retries."""


class CameraError(DeviceError):
    """No frame, a stale frame, or a source that cannot be opened."""


class Cancelled(AligndError):
    """A wait (a move, homing) ended because the caller's cancel event was set.

    Not a ``DeviceError``: the device is fine, the caller asked to stop waiting (and stops
    the axes itself)."""

    def __init__(self, message: str, *, device: str | None = None, port: str | None = None,
                 command: str | None = None) -> None:
        self.device, self.port, self.command = device, port, command
        super().__init__(f"{message} (device {device})" if device else message)
