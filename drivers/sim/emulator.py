"""What every emulated controller offers the server that puts it on a port.

An emulator is a byte-level state machine with its own parser (never a driver's codec).
The server feeds it whatever bytes the host wrote and sends back what it returns; between
reads it calls ``poll`` for unsolicited output (APT MOVE_COMPLETED, Zaber alerts...).
"""

from __future__ import annotations

import json
import os
import threading
import time
from abc import ABC, abstractmethod
from pathlib import Path

from drivers.sim.clock import Clock
from drivers.sim.kinematics import SimAxis


class TargetLog:
    """Every target an emulated controller receives, as JSON lines in a file.

    Why a file: the safety tests check, from outside the daemon process (and after a
    SIGKILL), that no target outside the soft limits ever reached a controller. One line is
    one ``os.write`` on an ``O_APPEND`` descriptor, so lines from several emulators (and
    successive daemons) never interleave. Targets are in the controller's own units (mm or
    deg, the values the host sent); ``accepted`` is False for a move the firmware refused.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND,
                                       0o644)
        self._lock = threading.Lock()

    def write(self, **record: object) -> None:
        line = json.dumps({"t": time.time(), "pid": os.getpid(), **record},
                          allow_nan=True) + "\n"
        with self._lock:
            if self._fd is not None:
                os.write(self._fd, line.encode())

    def close(self) -> None:
        with self._lock:
            fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)


class Emulator(ABC):
    """Emulated controller firmware behind one serial port."""

    protocol: str = ""
    baudrate: int = 0  # the real device's line rate (paces the bytes when asked to)

    def __init__(self, name: str, axes: dict[int, SimAxis], clock: Clock) -> None:
        """``axes`` maps the protocol's address (SMC100 address, Zaber device number,
        APT channel) to the simulated axis it drives."""
        self.name = name
        self.axes = axes
        self.clock = clock
        self.commands_seen = 0  # complete commands parsed so far (fault injection counts)
        self._kinds: list[str] = []  # kinds of the commands parsed since take_kinds()
        self.target_log: TargetLog | None = None  # set by the rig when configured

    def note_command(self, kind: str) -> None:
        """Count one complete command and remember its kind (what ``FaultConfig.on``
        matches: the SMC100 mnemonic, the Zaber command words, the APT message id)."""
        self.commands_seen += 1
        self._kinds.append(kind)

    def take_kinds(self) -> list[str]:
        """The kinds of the commands parsed since the last call, in order."""
        kinds, self._kinds = self._kinds, []
        return kinds

    def log_target(self, axis: SimAxis, target: float, *, accepted: bool = True,
                   command: str = "move") -> None:
        """Note a target this controller received (a no-op unless a log is attached)."""
        if self.target_log is not None:
            self.target_log.write(event="target", device=self.name, axis=axis.name,
                                  target=float(target), accepted=accepted, command=command)

    def log_stop(self, axis: SimAxis) -> None:
        """Note a stop command (the tests check every axis was told to stop after a fault)."""
        if self.target_log is not None:
            self.target_log.write(event="stop", device=self.name, axis=axis.name,
                                  position=axis.motor_position())

    @abstractmethod
    def handle(self, data: bytes) -> bytes:
        """Consume host bytes (any split: partial commands are buffered); return replies."""

    def poll(self) -> bytes:
        """Unsolicited bytes due now (default: none)."""
        return b""

    def corrupt_checksum(self, reply: bytes) -> bytes:
        """The reply with a wrong checksum; protocols without one garble a byte instead."""
        if not reply:
            return reply
        i = max(0, len(reply) // 2)
        return reply[:i] + bytes([reply[i] ^ 0x5A]) + reply[i + 1:]
