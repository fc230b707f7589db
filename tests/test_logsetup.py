"""Issue 14: log lines under journald carry the syslog priority; elsewhere a timestamp;
identical warnings are rate-limited."""

from __future__ import annotations

import io
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

from alignd.logsetup import JournalFormatter, RepeatFilter, configure_logging, under_journald


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _record(msg: str, level: int = logging.WARNING, *args: object) -> logging.LogRecord:
    return logging.LogRecord("alignd.x", level, __file__, 1, msg, args, None)


def test_journal_lines_carry_the_priority_on_every_line() -> None:
    f = JournalFormatter()
    assert f.format(_record("cam %s late", logging.WARNING, "top")) == "<4>alignd.x: cam top late"
    assert f.format(_record("x", logging.ERROR)).startswith("<3>")
    assert f.format(_record("x", logging.INFO)).startswith("<6>")
    assert f.format(_record("x", logging.DEBUG)).startswith("<7>")
    assert f.format(_record("x", logging.CRITICAL)).startswith("<2>")
    try:
        raise ValueError("boom")
    except ValueError:
        rec = _record("failed", logging.ERROR)
        rec.exc_info = sys.exc_info()
    lines = f.format(rec).splitlines()
    assert len(lines) > 3 and all(ln.startswith("<3>") for ln in lines), lines


def test_journald_is_recognised_only_for_the_announced_stream(tmp_path: Path) -> None:
    with open(tmp_path / "log", "w") as stream:
        st = os.fstat(stream.fileno())
        assert under_journald(stream, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"})
        assert not under_journald(stream, {"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"})
        assert not under_journald(stream, {"JOURNAL_STREAM": "garbage"})
        assert not under_journald(stream, {})


def test_repeated_warnings_are_held_back_then_counted() -> None:
    clock = Clock()
    flt = RepeatFilter(window_s=60.0, clock=clock)
    assert flt.filter(_record("camera top: timeout"))
    clock.t = 1.0
    assert [flt.filter(_record("camera top: timeout")) for _ in range(5)] == [False] * 5
    assert flt.filter(_record("camera side: timeout"))  # another text is not held
    assert flt.filter(_record("camera top: timeout", logging.INFO))  # info is never held
    clock.t = 61.0
    rec = _record("camera top: timeout")
    assert flt.filter(rec)
    assert rec.getMessage() == "camera top: timeout (and 5 more like it in the last 60 s)"


def test_the_daemon_logs_priorities_under_systemd_and_timestamps_elsewhere(
        tmp_path: Path) -> None:
    script = ("import logging, sys; from alignd.logsetup import configure_logging; "
              "configure_logging(logging.INFO); log = logging.getLogger('alignd.t'); "
              "[log.warning('camera %s timed out', 'top') for _ in range(50)]; "
              "log.info('ready')")
    path = tmp_path / "err"
    with open(path, "w") as err:
        st = os.fstat(err.fileno())
        env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
        subprocess.run([sys.executable, "-c", script], stderr=err, env=env, check=True)
    assert path.read_text().splitlines() == ["<4>alignd.t: camera top timed out",
                                             "<6>alignd.t: ready"]
    env = {k: v for k, v in os.environ.items() if k != "JOURNAL_STREAM"}
    out = subprocess.run([sys.executable, "-c", script], stderr=subprocess.PIPE, env=env,
                         text=True, check=True).stderr.splitlines()
    assert len(out) == 2
    assert re.match(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} WARNING alignd.t: camera top", out[0])


def test_configure_twice_keeps_one_handler_and_others_alone() -> None:
    root = logging.getLogger()
    other = logging.StreamHandler(io.StringIO())
    root.addHandler(other)
    try:
        h1 = configure_logging(logging.INFO, stream=io.StringIO(), env={})
        h2 = configure_logging(logging.INFO, stream=io.StringIO(), env={})
        assert h1 not in root.handlers and h2 in root.handlers and other in root.handlers
    finally:
        root.removeHandler(other)
        root.removeHandler(h2)
