"""Serve an emulator on a pseudo-terminal or a loopback TCP port, with injectable faults.

The server is the emulated controller's cable: it carries bytes between a host program
(alignd's drivers, vendor software, a terminal) and the emulator's state machine. Faults
that live on the wire (no reply, truncated/garbled/bad-checksum reply, slow or late reply,
disconnect) are applied here; mechanical ones (stall, limit switch) are handed to the
emulator's simulated axes.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import socket
import threading
import time
import tty
from dataclasses import dataclass
from typing import Literal, Self

import numpy as np

from drivers.config import FaultConfig
from drivers.sim.emulator import Emulator

log = logging.getLogger(__name__)

Mode = Literal["tcp", "pty", "both"]
WIRE_FAULTS = {"no_reply", "truncated", "garbled", "bad_checksum", "slow_reply", "late_reply"}


@dataclass
class _FaultState:
    cfg: FaultConfig
    hits: int = 0
    matches: int = 0  # commands matching cfg.on seen so far
    due: bool = False  # a matching command was just read: its reply (or firing) is next
    latched: bool = False  # on + count 0: from the nth match on, every reply is hit
    fired: bool = False  # for one-shot faults (disconnect, stall, limit_switch)


def command_matches(kind: str, pattern: str) -> bool:
    """``kind`` is the command ``pattern`` names: equal, or the pattern's words first
    (``"move abs"`` matches ``"move abs 2000"``); case-insensitive."""
    k, p = kind.lower(), pattern.lower().strip()
    return k == p or k.startswith(p + " ")


class FaultInjector:
    """Decides, command by command and reply by reply, what a configured fault does.

    Faults with ``on`` are deterministic: they count matching commands (``observe``) and hit
    the ``nth`` one, whatever the number of status polls around it (with ``count`` 0, the
    nth and every reply after it, of any command: a controller gone mute). Faults with only
    ``after_commands``/``probability`` count every reply (for soak tests).
    """

    def __init__(self, faults: list[FaultConfig], seed: int = 0) -> None:
        self.faults = [_FaultState(f) for f in faults]
        self.rng = np.random.default_rng(seed)
        self.replies = 0
        self._previous = ""  # the kind of the last command read on this link

    def _allowed(self, st: _FaultState) -> bool:
        if st.cfg.count and st.hits >= st.cfg.count:
            return False
        return st.cfg.probability >= 1.0 or bool(self.rng.random() < st.cfg.probability)

    def observe(self, kinds: list[str]) -> None:
        """Note the commands just read (in order); mark the faults they make due."""
        for kind in kinds:
            for st in self.faults:
                f = st.cfg
                if f.on is None or not command_matches(kind, f.on):
                    continue
                if f.following is not None and not command_matches(self._previous,
                                                                   f.following):
                    continue
                st.matches += 1
                if st.matches >= f.nth and self._allowed(st):
                    st.due = True
                    st.latched = f.count == 0
            self._previous = kind

    def _active(self, st: _FaultState, counter: int) -> bool:
        f = st.cfg
        if f.on is not None:
            return st.due or st.latched
        if counter < f.after_commands:
            return False
        return self._allowed(st)

    def on_reply(self, reply: bytes, emulator: Emulator) -> tuple[bytes, float]:
        """The bytes to send for one reply and the delay before sending them."""
        counter = self.replies
        self.replies += 1
        delay = 0.0
        out = reply
        for st in self.faults:
            kind = st.cfg.kind
            if kind not in WIRE_FAULTS or not self._active(st, counter):
                continue
            st.due = False
            st.hits += 1
            log.info("fault %s on %s reply #%d", kind, emulator.name, counter)
            if kind == "no_reply":
                out = b""
                delay = 0.0
                break
            if kind == "truncated":
                out = out[: max(1, len(out) // 2)]
            elif kind == "garbled":
                b = bytearray(out)
                for i in self.rng.choice(len(b), size=max(1, len(b) // 3), replace=False):
                    b[i] = int(self.rng.integers(0x21, 0x7F)) ^ (b[i] & 0x80)
                out = bytes(b)
            elif kind == "bad_checksum":
                out = emulator.corrupt_checksum(out)
            else:  # slow_reply, late_reply
                delay = max(delay, st.cfg.delay_s)
        self.commands_without_reply()  # a due fault this reply did not take lapses
        return out, delay

    def commands_without_reply(self) -> None:
        """The commands just observed got no reply of their own: wire faults due on them
        lapse (a matching command that is never answered hits nothing)."""
        for st in self.faults:
            if st.cfg.kind in WIRE_FAULTS:
                st.due = False

    def mechanical(self, emulator: Emulator) -> bool:
        """Fire stall/limit faults when due; True when a disconnect is due."""
        disconnect = False
        for st in self.faults:
            f = st.cfg
            if f.kind in WIRE_FAULTS or st.fired:
                continue
            if f.on is not None:
                if not st.due:
                    continue
                st.due = False
            elif emulator.commands_seen < f.after_commands:
                continue
            if f.kind == "disconnect":
                # by count: mid-move when possible, so wait for motion once it is reached
                if (f.on is not None or f.after_commands == 0
                        or any(ax.moving for ax in emulator.axes.values())):
                    st.fired = disconnect = True
                    st.hits += 1
                continue
            targets = [ax for addr, ax in emulator.axes.items()
                       if f.axis is None or ax.name == f.axis]
            for ax in targets:
                log.info("fault %s on %s axis %s", f.kind, emulator.name, ax.name)
                if f.kind == "stall":
                    ax.inject_stall()
                elif f.kind == "limit_switch":
                    ax.inject_limit_switch("high")
            # marked fired once it is in place: a thread that waits for ``fired`` (a test
            # that then moves the clock) must find the axis already stalled (it read the
            # position between the two and saw the axis move on)
            st.hits += 1
            st.fired = True
        return disconnect


class EmulatorServer:
    """Serves one emulator; ``url`` is what a host passes to ``serial_for_url``."""

    def __init__(self, emulator: Emulator, mode: Mode = "tcp", *,
                 faults: list[FaultConfig] | None = None, host: str = "127.0.0.1",
                 port: int = 0, seed: int = 0, poll_interval_s: float = 0.002,
                 pace_serial: bool = False) -> None:
        """``pace_serial``: take as long as the bytes take on the real serial line (10 bits
        a byte at the emulator's baud rate), both ways, so round trips are realistic."""
        self.emulator = emulator
        self.mode = mode
        self.faults = FaultInjector([f for f in (faults or []) if f.device == emulator.name],
                                    seed)
        self.host, self.port = host, port
        self.poll_interval_s = poll_interval_s
        self.byte_time_s = 10.0 / emulator.baudrate if pace_serial and emulator.baudrate else 0.0
        self.url = ""
        self.pty_path: str | None = None
        self.disconnected = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._pending: list[tuple[float, bytes]] = []
        self._from_tcp = mode == "tcp"  # where the last command came from
        self.lock = threading.Lock()  # held while the emulator state changes

    # ---- life cycle --------------------------------------------------------------
    def start(self) -> Self:
        if self.mode in ("tcp", "both"):
            lst = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            lst.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            lst.bind((self.host, self.port))
            lst.listen(1)
            self._listener = lst
            self.port = lst.getsockname()[1]
            self.url = f"socket://{self.host}:{self.port}"
        if self.mode in ("pty", "both"):
            master, slave = os.openpty()
            tty.setraw(slave)
            self._master, self._slave = master, slave  # keep the slave open: no EIO on master
            self.pty_path = os.ttyname(slave)
            self.url = self.url or self.pty_path
        self._thread = threading.Thread(target=self._run, name=f"sim-{self.emulator.name}",
                                        daemon=True)
        self._thread.start()
        log.info("serving %s (%s) on %s", self.emulator.name, self.emulator.protocol, self.url)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_all()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def endpoint(self) -> dict[str, str | None]:
        """The endpoint line of the design notes (one JSON object per device)."""
        tcp = f"socket://{self.host}:{self.port}" if self.mode != "pty" else None
        return {"device": self.emulator.name, "protocol": self.emulator.protocol,
                "url": tcp, "pty": self.pty_path}

    # ---- the loop ----------------------------------------------------------------
    def _drop_connection(self) -> None:
        if self._client is not None:
            with contextlib.suppress(OSError):
                self._client.close()
            self._client = None

    def _close_all(self) -> None:
        self._drop_connection()
        for fd in (self._master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = None
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def _disconnect(self) -> None:
        """Make the port vanish, as a pulled USB cable does."""
        log.info("fault disconnect on %s", self.emulator.name)
        self.disconnected = True
        self._close_all()

    def _read_fds(self) -> list[socket.socket | int]:
        fds: list[socket.socket | int] = []
        if self._listener is not None and self._client is None:
            fds.append(self._listener)
        if self._client is not None:
            fds.append(self._client)
        if self._master is not None:
            fds.append(self._master)
        return fds

    def _send(self, data: bytes) -> None:
        """To the host that spoke last (serving both a pty and TCP, either may be it)."""
        if not data:
            return
        if self.byte_time_s:
            time.sleep(len(data) * self.byte_time_s)
        try:
            if self._client is not None and (self._from_tcp or self._master is None):
                self._client.sendall(data)
            elif self._master is not None:
                os.write(self._master, data)
        except OSError as exc:
            log.debug("%s: send failed: %s", self.emulator.name, exc)
            self._drop_connection()

    def pending_replies(self) -> int:
        """Replies held back by a slow/late-reply fault and not yet sent."""
        return len(self._pending)

    def _connected(self) -> bool:
        return self._client is not None or self._master is not None

    def _run(self) -> None:
        while not self._stop.is_set():
            fds = self._read_fds()
            if not fds:
                time.sleep(self.poll_interval_s)
                continue
            try:
                ready, _, _ = select.select(fds, [], [], self.poll_interval_s)
            except (OSError, ValueError):
                ready = []
            for fd in ready:
                if fd is self._listener and self._listener is not None:
                    conn, _ = self._listener.accept()
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    self._client = conn
                    continue
                data = self._recv(fd)
                if data:
                    self._from_tcp = isinstance(fd, socket.socket)
                    self._feed(data)
            self._tick()

    def _recv(self, fd: object) -> bytes:
        try:
            if isinstance(fd, socket.socket):
                data = fd.recv(4096)
                if not data:
                    self._drop_connection()
                return data
            return os.read(fd, 4096)  # type: ignore[arg-type]
        except OSError as exc:
            if exc.errno not in (errno.EAGAIN, errno.EIO):
                log.debug("%s: read failed: %s", self.emulator.name, exc)
            if isinstance(fd, socket.socket):
                self._drop_connection()
            return b""

    def _feed(self, data: bytes) -> None:
        if self.byte_time_s:  # the command's bytes arrive at the line rate
            time.sleep(len(data) * self.byte_time_s)
        with self.lock:
            reply = self.emulator.handle(data)
            self.faults.observe(self.emulator.take_kinds())
        if not reply:
            self.faults.commands_without_reply()
        else:
            out, delay = self.faults.on_reply(reply, self.emulator)
            if delay > 0:
                self._pending.append((time.monotonic() + delay, out))
            elif self._pending:  # keep order behind a delayed reply
                self._pending.append((self._pending[-1][0], out))
            else:
                self._send(out)

    def _tick(self) -> None:
        with self.lock:
            unsolicited = self.emulator.poll()
            disconnect = self.faults.mechanical(self.emulator)
        if disconnect:
            self._disconnect()
            return
        now = time.monotonic()
        while self._pending and self._pending[0][0] <= now:
            self._send(self._pending.pop(0)[1])
        if unsolicited and self._connected():
            self._send(unsolicited)
