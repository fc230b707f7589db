"""Byte transport over ``serial.serial_for_url``: the one place wire traffic is logged.

Device paths, ``socket://host:port`` (ser2net, device servers, the emulators),
``rfc2217://`` and ``spy://`` all open the same way. Ports are opened exclusively where the
platform supports it, so a second process cannot interleave bytes with ours.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from typing import Self

import serial

from drivers.errors import DeviceTimeoutError, PortBusyError, TransportError

log = logging.getLogger(__name__)

WRITE_TIMEOUT_FLOOR_S = 2.0

try:  # pyserial's POSIX backend lets termios.error (not an OSError) escape, e.g. tcdrain
    import termios  # on a pty whose other end has gone

    _IO_ERRORS: tuple[type[BaseException], ...] = (OSError, serial.SerialException,
                                                   termios.error)
except ImportError:  # pragma: no cover - Windows
    _IO_ERRORS = (OSError, serial.SerialException)
# a port closed under a blocked read can raise TypeError inside pyserial
_READ_ERRORS: tuple[type[BaseException], ...] = (*_IO_ERRORS, TypeError)


class SerialTransport:
    """A byte pipe to one controller, with timeouts and resynchronisation helpers."""

    def __init__(self, url: str, *, device: str, baudrate: int = 115200,
                 timeout_s: float = 0.5, rtscts: bool = False, xonxoff: bool = False) -> None:
        self.url = url
        self.device = device
        self.baudrate = baudrate
        self.timeout_s = timeout_s
        self.rtscts = rtscts
        self.xonxoff = xonxoff
        self._ser: serial.SerialBase | None = None
        self.lock = threading.RLock()  # one command/reply exchange at a time

    # ---- life cycle ----------------------------------------------------------------
    def open(self) -> None:
        if self._ser is not None:
            return
        # pyserial raises a write timeout when the deadline passed by the time a write
        # returns, even if every byte went out: a process descheduled for half a second on
        # a loaded machine would see a phantom timeout. A floor keeps that from happening
        # while a write really blocked (flow control held off) still ends in bounded time.
        write_timeout = max(self.timeout_s, WRITE_TIMEOUT_FLOOR_S)
        # network URLs have no flow control lines: leave pyserial's defaults there
        local = not self.url.startswith(("socket://", "rfc2217://", "loop://"))
        try:
            ser = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.timeout_s,
                                        write_timeout=write_timeout, do_not_open=True,
                                        rtscts=self.rtscts and local,
                                        xonxoff=self.xonxoff and local)
            if hasattr(ser, "exclusive") and not self.url.startswith(("socket://", "rfc2217://",
                                                                     "loop://")):
                ser.exclusive = True
            ser.open()
        except serial.SerialException as exc:
            text = str(exc)
            if "exclusive" in text.lower() or "lock" in text.lower() or "busy" in text.lower():
                raise PortBusyError("port is held by another process; close the other "
                                    "program or pick another port",
                                    device=self.device, port=self.url) from exc
            raise TransportError(f"cannot open port: {text}", device=self.device,
                                 port=self.url) from exc
        except (OSError, ValueError) as exc:
            raise TransportError(f"cannot open port: {exc}", device=self.device,
                                 port=self.url) from exc
        sock = getattr(ser, "_socket", None)  # socket://: no Nagle delay on short commands
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._ser = ser
        log.debug("%s: opened %s", self.device, self.url)

    def close(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            try:
                ser.close()
            except (OSError, serial.SerialException):
                log.debug("%s: error while closing %s", self.device, self.url, exc_info=True)
            log.debug("%s: closed %s", self.device, self.url)

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- I/O ---------------------------------------------------------------------
    def _port(self, command: str | None = None) -> serial.SerialBase:
        if self._ser is None:
            raise TransportError("port is not open", device=self.device, port=self.url,
                                 command=command)
        return self._ser

    def write(self, data: bytes, command: str | None = None) -> None:
        ser = self._port(command)
        log.debug("%s >> %r", self.device, data)
        try:
            ser.write(data)
            ser.flush()
        except _IO_ERRORS as exc:
            self.close()
            raise TransportError(f"write failed: {exc}", device=self.device, port=self.url,
                                 command=command) from exc

    def read_exact(self, n: int, timeout_s: float | None = None,
                   command: str | None = None) -> bytes:
        """Read exactly ``n`` bytes or raise ``DeviceTimeoutError`` (partial data logged)."""
        buf = bytearray()
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while len(buf) < n:
            chunk = self._read_some(n - len(buf), deadline, command)
            if chunk is None:
                log.debug("%s << %r (incomplete, wanted %d bytes)", self.device, bytes(buf), n)
                raise DeviceTimeoutError(
                    f"no complete reply: got {len(buf)} of {n} bytes",
                    device=self.device, port=self.url, command=command)
            buf += chunk
        log.debug("%s << %r", self.device, bytes(buf))
        return bytes(buf)

    def read_until(self, terminator: bytes, timeout_s: float | None = None,
                   command: str | None = None, max_len: int = 4096) -> bytes:
        """Read up to and including ``terminator`` or raise ``DeviceTimeoutError``."""
        buf = bytearray()
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while not buf.endswith(terminator):
            if len(buf) > max_len:
                raise DeviceTimeoutError(f"reply longer than {max_len} bytes without "
                                         f"terminator {terminator!r}", device=self.device,
                                         port=self.url, command=command)
            chunk = self._read_some(1, deadline, command)
            if chunk is None:
                log.debug("%s << %r (no terminator)", self.device, bytes(buf))
                what = "no reply" if not buf else f"truncated reply {bytes(buf)!r}"
                raise DeviceTimeoutError(what, device=self.device, port=self.url,
                                         command=command)
            buf += chunk
        log.debug("%s << %r", self.device, bytes(buf))
        return bytes(buf)

    def _read_some(self, n: int, deadline: float, command: str | None) -> bytes | None:
        ser = self._port(command)
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return None
        try:
            ser.timeout = min(remaining, self.timeout_s)
            waiting = ser.in_waiting if hasattr(ser, "in_waiting") else 0
            chunk = ser.read(max(1, min(n, waiting)) if waiting else 1)
        except _READ_ERRORS as exc:
            self.close()
            raise TransportError(f"read failed (port vanished?): {exc}", device=self.device,
                                 port=self.url, command=command) from exc
        if not chunk:
            return None if time.monotonic() >= deadline else b""
        return chunk

    def drain(self, quiet_s: float = 0.02) -> bytes:
        """Discard whatever is pending (late replies, garbage): resynchronise the link."""
        ser = self._port()
        junk = bytearray()
        try:
            ser.timeout = quiet_s
            while True:
                chunk = ser.read(max(1, ser.in_waiting if hasattr(ser, "in_waiting") else 1))
                if not chunk:
                    break
                junk += chunk
        except _IO_ERRORS as exc:
            self.close()
            raise TransportError(f"read failed (port vanished?): {exc}", device=self.device,
                                 port=self.url) from exc
        if junk:
            log.debug("%s << %r (discarded to resynchronise)", self.device, bytes(junk))
        return bytes(junk)
