"""The supported Python API for alignd (HTTP/JSON over the daemon's Unix socket).

    from alignd.client import Client

    client = Client()                       # $ALIGND_SOCKET, else /run/alignd/alignd.sock
    result = client.check()                 # waits; a RunResult
    if not result.ok:
        result = client.align(on_event=print)
    print(result.verdict, result.offset_norm_um, result.U_um)

``check``/``align`` start a run and, with ``wait=True`` (the default), follow it to its end
and return a typed ``RunResult``; ``wait=False`` returns the run id, and ``progress(run_id)``
iterates over its live ``Event``s. ``status()`` and ``history()`` return the daemon's JSON
(see docs/python-api.md for the keys). Errors: ``DaemonUnreachable`` (no daemon on the
socket), ``ApiError`` (the daemon refused: ``code`` is ``busy``, ``starting``, ``fault``,
``forbidden``, ...). Starting, aborting and resetting need the operator group (peer
credentials); reading needs only access to the socket.

Socket resolution (contract): ``--socket PATH``, else ``$ALIGND_SOCKET``, else the
configured default (``daemon.socket``, ``/run/alignd/alignd.sock`` unless a config says
otherwise).

A refused connect (no listener yet, a full listen backlog) and a 503 "overloaded" reply
(sent before the daemon reads the request, so nothing was acted upon) are retried for up to
``retry_s`` (2 s by default); after that the server's own message is shown.
"""

from __future__ import annotations

import errno
import http.client
import json
import math
import os
import socket
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, overload

from alignd.config import DaemonConfig
from alignd.errors import AligndError


class DaemonUnreachable(AligndError):
    """No daemon answers on the socket (names the socket and why)."""

    retryable = False


class _Refused(DaemonUnreachable):
    """The connect itself was refused (no listener, or its backlog is full): transient."""

    retryable = True


class ApiError(AligndError):
    """The daemon answered with an error (``code`` is its machine-readable reason)."""

    def __init__(self, status: int, code: str, message: str, body: dict[str, Any]) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.body = body


OK_VERDICTS = ("aligned", "within_tolerance")
EventType = Literal["progress", "event", "state", "end"]


def _opt_float(v: Any) -> float | None:
    return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None


def _opt_int(v: Any) -> int | None:
    return int(v) if isinstance(v, (int, float)) else None


@dataclass(frozen=True)
class RunResult:
    """The outcome of a run (the run-result contract of DESIGN.md), as the daemon recorded it.

    ``offset_um`` is the target's offset from the rotation axis in the turntable frame
    (x, y), ``U_um`` its expanded uncertainty (k = 2); ``truth`` only on a simulated rig."""

    run_id: int
    verdict: str  # aligned | within_tolerance | out_of_tolerance | not_converged | aborted | fault
    reason: str = ""
    offset_um: tuple[float, float] | None = None
    offset_norm_um: float | None = None
    U_um: float | None = None
    iterations: int = 0
    tilt_deg: float | None = None
    yaw_deg: float | None = None
    truth: dict[str, Any] | None = None
    tilt_u_deg: float | None = None  # standard uncertainty of tilt_deg (k = 1)
    eccentricity: float | None = None  # the top camera's rim pre-check (apparent e)
    eccentricity_u: float | None = None  # its standard uncertainty (k = 1)
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @property
    def ok(self) -> bool:
        """Aligned, or within tolerance."""
        return self.verdict in OK_VERDICTS

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> RunResult:
        off = d.get("offset_um")
        offset = None
        if isinstance(off, (list, tuple)) and len(off) == 2 and all(
                _opt_float(v) is not None for v in off):
            offset = (float(off[0]), float(off[1]))
        truth = d.get("truth")
        return cls(run_id=int(d.get("run_id") or 0), verdict=str(d.get("verdict") or "fault"),
                   reason=str(d.get("reason") or ""), offset_um=offset,
                   offset_norm_um=_opt_float(d.get("offset_norm_um")),
                   U_um=_opt_float(d.get("U_um")), iterations=int(d.get("iterations") or 0),
                   tilt_deg=_opt_float(d.get("tilt_deg")), yaw_deg=_opt_float(d.get("yaw_deg")),
                   truth=truth if isinstance(truth, dict) else None,
                   tilt_u_deg=_opt_float(d.get("tilt_u_deg")),
                   eccentricity=_opt_float(d.get("eccentricity")),
                   eccentricity_u=_opt_float(d.get("eccentricity_u")), raw=dict(d))


@dataclass(frozen=True)
class Event:
    """One live event of a run: ``progress`` (phase, sweep step, latest offset), ``event``
    (a note or warning, ``level``), ``state`` (started) or ``end`` (``verdict``)."""

    seq: int
    run_id: int
    type: str
    t: float
    phase: str | None = None
    message: str = ""
    step: int | None = None
    total: int | None = None
    iteration: int | None = None
    offset_norm_um: float | None = None
    U_um: float | None = None
    level: str | None = None
    verdict: str | None = None
    reason: str | None = None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Event:
        return cls(seq=int(d.get("seq") or 0), run_id=int(d.get("run_id") or 0),
                   type=str(d.get("type") or "event"), t=float(d.get("t") or 0.0),
                   phase=d.get("phase"), message=str(d.get("message") or d.get("msg") or ""),
                   step=_opt_int(d.get("step")), total=_opt_int(d.get("total")),
                   iteration=_opt_int(d.get("iteration")),
                   offset_norm_um=_opt_float(d.get("offset_norm_um")),
                   U_um=_opt_float(d.get("U_um")), level=d.get("level"),
                   verdict=d.get("verdict"), reason=d.get("reason"))

    def __str__(self) -> str:
        if self.type == "end":
            return f"[end] {self.verdict}" + (f": {self.reason}" if self.reason else "")
        if self.type != "progress":
            return f"[{self.level or self.type}] {self.message}"
        parts = [f"[{self.phase}]"]
        if self.iteration is not None:
            parts.append(f"iteration {self.iteration}")
        if self.step is not None and self.total is not None:
            parts.append(f"step {self.step}/{self.total}")
        if self.message:
            parts.append(self.message)
        return " ".join(parts)


def resolve_socket(arg: str | None = None, configured: str | None = None) -> str:
    """``arg``, else ``$ALIGND_SOCKET``, else ``configured``, else the built-in default."""
    return arg or os.environ.get("ALIGND_SOCKET") or configured or DaemonConfig().socket


class _UnixConnection(http.client.HTTPConnection):
    def __init__(self, path: str, timeout: float) -> None:
        super().__init__("localhost", timeout=timeout)
        self._path = path

    def connect(self) -> None:
        """A blocking connect that waits (up to the timeout) in the kernel's first-come
        queue for room in the daemon's listen backlog: a socket with a Python timeout is
        non-blocking and would be turned away at once whenever a burst of other clients
        fills the backlog, however briefly."""
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            if self.timeout is not None and self.timeout > 0:
                sec = int(self.timeout)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDTIMEO, struct.pack(
                    "ll", sec, int((self.timeout - sec) * 1e6)))
            sock.connect(self._path)
            sock.settimeout(self.timeout)
        except OSError:
            sock.close()
            raise
        self.sock = sock


class Client:
    """alignd's control API. One request per connection (no state between calls), so a
    ``Client`` may be shared between threads. ``socket_path`` defaults as ``alignctl``'s."""

    def __init__(self, socket_path: str | Path | None = None, timeout_s: float = 10.0,
                 retry_s: float = 2.0, sleep: Callable[[float], None] = time.sleep) -> None:
        self.socket_path = resolve_socket(str(socket_path) if socket_path else None)
        self.timeout_s = timeout_s
        self.retry_s = retry_s
        self._sleep = sleep

    def request(self, method: str, path: str, body: dict[str, Any] | None = None,
                timeout_s: float | None = None, raw: bool = False) -> Any:
        """One request; a refused connect or an "overloaded" 503 is retried briefly."""
        deadline = time.monotonic() + self.retry_s
        delay = 0.05
        while True:
            try:
                return self._request_once(method, path, body, timeout_s, raw)
            except (_Refused, ApiError) as exc:
                transient = isinstance(exc, _Refused) or (
                    exc.status == 503 and exc.code == "overloaded")
                if not transient or time.monotonic() + delay > deadline:
                    raise
            self._sleep(delay)
            delay = min(2 * delay, 0.5)

    def _request_once(self, method: str, path: str, body: dict[str, Any] | None,
                      timeout_s: float | None, raw: bool) -> Any:
        conn = _UnixConnection(self.socket_path, timeout_s or self.timeout_s)
        try:
            data = None if body is None else json.dumps(body).encode()
            headers = {"Content-Type": "application/json"} if data is not None else {}
            try:
                try:
                    conn.request(method, path, body=data, headers=headers)
                except (BrokenPipeError, ConnectionResetError):
                    if conn.sock is None:
                        raise
                    # the daemon may have refused the connection (503) and closed it before
                    # reading the request: its reply is still there to read
                resp = conn.getresponse()
                payload = resp.read()
            except BlockingIOError as exc:
                if exc.errno != errno.EAGAIN:
                    raise DaemonUnreachable(f"cannot talk to alignd at {self.socket_path}: "
                                            f"{exc}") from None
                raise _Refused(f"cannot reach alignd at {self.socket_path}: it is not "
                               "accepting connections (listen queue full)") from None
            except FileNotFoundError:
                raise DaemonUnreachable(f"cannot reach alignd at {self.socket_path}: no such "
                                        "socket (is the daemon running? see --socket, "
                                        "$ALIGND_SOCKET)") from None
            except PermissionError:
                raise DaemonUnreachable(f"cannot reach alignd at {self.socket_path}: "
                                        "permission denied") from None
            except ConnectionRefusedError:
                raise _Refused(f"cannot reach alignd at {self.socket_path}: connection "
                               "refused (is the daemon running? stale socket?)") from None
            except TimeoutError:
                raise DaemonUnreachable(f"alignd at {self.socket_path} did not answer "
                                        f"{method} {path} in time") from None
            except (OSError, http.client.HTTPException) as exc:
                raise DaemonUnreachable(f"cannot talk to alignd at {self.socket_path}: "
                                        f"{exc}") from None
        finally:
            conn.close()
        if raw and resp.status == 200:
            return payload
        try:
            decoded = json.loads(payload) if payload else {}
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise DaemonUnreachable(f"alignd at {self.socket_path} sent a reply that is not "
                                    f"JSON (HTTP {resp.status})") from None
        if resp.status >= 400:
            if not isinstance(decoded, dict):
                decoded = {}
            raise ApiError(resp.status, str(decoded.get("error", "error")),
                           str(decoded.get("message", f"HTTP {resp.status}")), decoded)
        return decoded

    def status(self) -> dict[str, Any]:
        return self.request("GET", "/status")

    def history(self, limit: int = 20) -> list[dict[str, Any]]:
        return self.request("GET", f"/history?limit={int(limit)}")["runs"]

    def run(self, run_id: int) -> dict[str, Any]:
        return self.request("GET", f"/runs/{int(run_id)}")

    def events(self, run_id: int, after: int = 0, wait_s: float = 0.0) -> dict[str, Any]:
        return self.request("GET", f"/runs/{int(run_id)}/events?after={int(after)}"
                            f"&wait={wait_s:g}", timeout_s=self.timeout_s + wait_s)

    def frame(self, digest: str) -> bytes:
        return self.request("GET", f"/frames/{digest}", raw=True)

    def start(self, kind: str, started_by: str = "user") -> dict[str, Any]:
        return self.request("POST", f"/{kind}", {"started_by": started_by})

    def abort(self) -> dict[str, Any]:
        return self.request("POST", "/abort", {})

    def reset(self) -> dict[str, Any]:
        return self.request("POST", "/reset", {})

    # ---- runs, typed ------------------------------------------------------------------
    @overload
    def check(self, wait: Literal[True] = ..., *, started_by: str = ...,
              on_event: Callable[[Event], None] | None = ..., wait_ready_s: float = ...
              ) -> RunResult: ...
    @overload
    def check(self, wait: Literal[False], *, started_by: str = ...,
              on_event: Callable[[Event], None] | None = ..., wait_ready_s: float = ...
              ) -> int: ...
    def check(self, wait: bool = True, *, started_by: str = "user",
              on_event: Callable[[Event], None] | None = None, wait_ready_s: float = 60.0
              ) -> RunResult | int:
        """Measure the offset without moving the sample; pass/fail against the tolerance.
        ``wait=True``: follow the run (``on_event`` sees its live events) and return its
        result; ``wait=False``: return the run id at once."""
        return self._run("check", wait, started_by, on_event, wait_ready_s)

    @overload
    def align(self, wait: Literal[True] = ..., *, started_by: str = ...,
              on_event: Callable[[Event], None] | None = ..., wait_ready_s: float = ...
              ) -> RunResult: ...
    @overload
    def align(self, wait: Literal[False], *, started_by: str = ...,
              on_event: Callable[[Event], None] | None = ..., wait_ready_s: float = ...
              ) -> int: ...
    def align(self, wait: bool = True, *, started_by: str = "user",
              on_event: Callable[[Event], None] | None = None, wait_ready_s: float = 60.0
              ) -> RunResult | int:
        """Closed-loop alignment of the sample onto the rotation axis (as ``check``)."""
        return self._run("align", wait, started_by, on_event, wait_ready_s)

    def _run(self, kind: str, wait: bool, started_by: str,
             on_event: Callable[[Event], None] | None, wait_ready_s: float) -> RunResult | int:
        deadline = time.monotonic() + wait_ready_s
        while True:
            try:
                run_id = int(self.start(kind, started_by)["run_id"])
                break
            except ApiError as exc:  # still connecting the hardware: wait a little
                if exc.code != "starting" or time.monotonic() >= deadline:
                    raise
                time.sleep(0.5)
        return self.wait(run_id, on_event) if wait else run_id

    def progress(self, run_id: int, poll_s: float = 10.0) -> Iterator[Event]:
        """The run's live events from its start, until its ``end`` event (long-polling)."""
        after = 0
        while True:
            reply = self.events(run_id, after=after, wait_s=poll_s)
            for ev in reply.get("events", []):
                yield Event.from_json(ev)
            after = int(reply.get("next", after))
            if reply.get("done"):
                return

    def wait(self, run_id: int, on_event: Callable[[Event], None] | None = None
             ) -> RunResult:
        """Follow a run to its end; its result (``DaemonUnreachable`` if the daemon dies)."""
        for ev in self.progress(run_id):
            if on_event is not None:
                on_event(ev)
        return self.result(run_id)

    def result(self, run_id: int) -> RunResult:
        """The recorded result of a finished run (``ApiError`` ``no_such_run``, or
        ``StateError`` while it is still running)."""
        run = self.run(run_id)
        res = run.get("result")
        if not isinstance(res, dict):
            from alignd.errors import StateError

            raise StateError(f"run {run_id} has no result yet (status {run.get('status')})")
        return RunResult.from_json({"run_id": run_id, **res})
