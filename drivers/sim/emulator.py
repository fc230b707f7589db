"""What every emulated controller offers the server that puts it on a port.

An emulator is a byte-level state machine with its own parser (never a driver's codec).
The server feeds it whatever bytes the host wrote and sends back what it returns; between
reads it calls ``poll`` for unsolicited output (APT MOVE_COMPLETED, Zaber alerts...).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from drivers.sim.clock import Clock
from drivers.sim.kinematics import SimAxis


class Emulator(ABC):
    """Emulated controller firmware behind one serial port."""

    protocol: str = ""

    def __init__(self, name: str, axes: dict[int, SimAxis], clock: Clock) -> None:
        """``axes`` maps the protocol's address (SMC100 address, Zaber device number,
        APT channel) to the simulated axis it drives."""
        self.name = name
        self.axes = axes
        self.clock = clock
        self.commands_seen = 0  # complete commands parsed so far (fault injection counts)

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
