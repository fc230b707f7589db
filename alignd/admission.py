"""Who gets one of the API's connection slots, and a refusal log that cannot flood.

Why: every accepted connection holds a thread until its request is answered (a long poll
for up to half a minute), so the slots are a resource one local user could take from
everybody else. The policy, decided at accept time from the kernel's peer credentials:

- a peer that may control the instrument (root, the daemon's user, the operator group) is
  *privileged*: it may use any free slot, including ``reserved`` slots nobody else gets;
- every other peer shares the rest, at most ``per_uid`` connections per user id;
- root is never capped per uid (only by the total), so ``status`` and ``abort`` from root
  are answered however many connections other users hold.

Refusals are counted and logged at most once per ``interval_s`` (a client that reconnects
in a loop must not fill the journal).
"""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

log = logging.getLogger(__name__)

Pool = Literal["shared", "reserved"]


@dataclass(frozen=True)
class Limits:
    """Connection limits (defaults sized for a lab PC: a handful of clients at a time)."""

    total: int = 64
    reserved: int = 16  # of ``total``, only for privileged peers
    per_uid: int = 8  # connections one non-root user may hold at once

    def __post_init__(self) -> None:
        if not (self.total >= 1 and 0 <= self.reserved < self.total and self.per_uid >= 1):
            raise ValueError(f"inconsistent connection limits: {self}")


@dataclass(frozen=True)
class Slot:
    """One admitted connection (give it back with ``Admission.release``)."""

    uid: int
    pool: Pool


class Admission:
    """The connection policy (thread-safe; no I/O, no clock: tested deterministically)."""

    def __init__(self, limits: Limits | None = None) -> None:
        self.limits = limits or Limits()
        self._lock = threading.Lock()
        self._by_uid: collections.Counter[int] = collections.Counter()
        self._used: dict[Pool, int] = {"shared": 0, "reserved": 0}

    def admit(self, uid: int, privileged: bool) -> tuple[Slot | None, str]:
        """A slot, or ``(None, why)`` when the connection must be refused."""
        lim = self.limits
        with self._lock:
            if uid != 0 and self._by_uid[uid] >= lim.per_uid:
                return None, (f"uid {uid} already holds {lim.per_uid} connections (the "
                              "per-user limit); close some and retry")
            pool: Pool | None = None
            if self._used["shared"] < lim.total - lim.reserved:
                pool = "shared"
            elif privileged and self._used["reserved"] < lim.reserved:
                pool = "reserved"
            if pool is None:
                return None, (f"all {lim.total} connections are in use" if privileged else
                              f"all {lim.total - lim.reserved} connections open to observers "
                              "are in use; retry shortly")
            self._used[pool] += 1
            self._by_uid[uid] += 1
            return Slot(uid, pool), ""

    def release(self, slot: Slot) -> None:
        with self._lock:
            self._used[slot.pool] -= 1
            self._by_uid[slot.uid] -= 1
            if self._by_uid[slot.uid] <= 0:
                del self._by_uid[slot.uid]

    def held(self, uid: int | None = None) -> int:
        """Connections held by ``uid`` (all connections when ``None``)."""
        with self._lock:
            return sum(self._used.values()) if uid is None else self._by_uid[uid]


class RefusalLog:
    """Logs refused connections: the first at once, then one summary per ``interval_s``."""

    def __init__(self, interval_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.interval_s = interval_s
        self.clock = clock
        self.total = 0  # refusals since start
        self._lock = threading.Lock()
        self._pending: collections.Counter[int] = collections.Counter()
        self._last_log: float | None = None
        self._last_why = ""

    def refused(self, uid: int, why: str) -> None:
        with self._lock:
            self.total += 1
            self._pending[uid] += 1
            self._last_why = why
        self.flush()

    def flush(self) -> None:
        """Log what is pending if the interval has passed (the server calls this
        periodically, so the last burst's count is not held back until the next one)."""
        with self._lock:
            now = self.clock()
            if not self._pending or (self._last_log is not None
                                     and now - self._last_log < self.interval_s):
                return
            pending, self._pending = self._pending, collections.Counter()
            why = self._last_why
            since = None if self._last_log is None else now - self._last_log
            self._last_log = now
        n = sum(pending.values())
        who = ", ".join(f"uid {u}: {c}" for u, c in pending.most_common(5))
        if since is None or n == 1:
            log.warning("API: refused a connection (%s): %s", who, why)
        else:
            log.warning("API: refused %d connections in the last %.0f s (%s); latest: %s",
                        n, since, who, why)
