"""Log lines that fit the host: syslog priorities under systemd, timestamps elsewhere, and
no floods of one repeated warning.

Under systemd, stderr is a stream to journald, which adds its own timestamp and reads a
``<N>`` prefix on each line as that line's syslog priority, so ``journalctl -p warning -u
alignd`` can filter. systemd sets ``$JOURNAL_STREAM`` to the stream's ``device:inode``;
the prefix is used only when stderr *is* that stream (a child whose stderr was redirected
inherits the variable, and must not write ``<4>`` into a file).

A warning that repeats (a camera that keeps timing out while idle, a flapping link) is
logged once per ``window_s``; the next time it gets through it says how many were held back.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping
from typing import TextIO

# logging level -> syslog priority (RFC 5424: 2 crit, 3 err, 4 warning, 6 info, 7 debug)
SYSLOG_PRIORITY = {logging.CRITICAL: 2, logging.ERROR: 3, logging.WARNING: 4,
                   logging.INFO: 6, logging.DEBUG: 7}
HANDLER_NAME = "alignd-stderr"
TIMESTAMPED = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def syslog_priority(levelno: int) -> int:
    for level, prio in sorted(SYSLOG_PRIORITY.items(), reverse=True):
        if levelno >= level:
            return prio
    return 7


def under_journald(stream: TextIO, env: Mapping[str, str] | None = None) -> bool:
    """True when ``stream`` is the journald stream systemd announced in ``$JOURNAL_STREAM``."""
    env = os.environ if env is None else env
    want = env.get("JOURNAL_STREAM", "")
    dev, _, ino = want.partition(":")
    if not (dev.isdigit() and ino.isdigit()):
        return False
    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    return (st.st_dev, st.st_ino) == (int(dev), int(ino))


class JournalFormatter(logging.Formatter):
    """``<priority>name: message``; every line of a multi-line record (a traceback) gets
    the prefix, since journald reads each line as its own entry."""

    def __init__(self) -> None:
        super().__init__("%(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{syslog_priority(record.levelno)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines())


class RepeatFilter(logging.Filter):
    """Hold back identical warnings (same logger, level and text) within ``window_s``."""

    def __init__(self, window_s: float = 60.0, min_level: int = logging.WARNING,
                 clock: Callable[[], float] = time.monotonic, max_keys: int = 512) -> None:
        super().__init__()
        self.window_s = window_s
        self.min_level = min_level
        self.clock = clock
        self.max_keys = max_keys
        self._seen: OrderedDict[tuple[str, int, str], list[float]] = OrderedDict()
        self._lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < self.min_level:
            return True
        key = (record.name, record.levelno, record.getMessage())
        now = self.clock()
        with self._lock:
            seen = self._seen.get(key)
            if seen is not None and now - seen[0] < self.window_s:
                seen[1] += 1
                return False
            held = int(seen[1]) if seen is not None else 0
            self._seen[key] = [now, 0]
            self._seen.move_to_end(key)
            while len(self._seen) > self.max_keys:
                self._seen.popitem(last=False)
        if held:
            record.msg = f"{record.getMessage()} (and {held} more like it in the last " \
                         f"{self.window_s:g} s)"
            record.args = None
        return True


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (a test harness may swap it)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: TextIO) -> None:
        pass


def configure_logging(level: int, stream: TextIO | None = None,
                      env: Mapping[str, str] | None = None, window_s: float = 60.0
                      ) -> logging.Handler:
    """Root logging for the daemon: one stderr handler, formatted for where it goes."""
    handler: logging.StreamHandler = (
        _StderrHandler() if stream is None else logging.StreamHandler(stream))
    stream = sys.stderr if stream is None else stream
    if under_journald(stream, env):
        handler.setFormatter(JournalFormatter())
    else:
        handler.setFormatter(logging.Formatter(TIMESTAMPED))
    handler.addFilter(RepeatFilter(window_s))
    handler.set_name(HANDLER_NAME)
    root = logging.getLogger()
    for old in [h for h in root.handlers if h.get_name() == HANDLER_NAME]:
        root.removeHandler(old)  # ours from an earlier call; others (pytest's) stay
    root.addHandler(handler)
    root.setLevel(level)
    return handler
