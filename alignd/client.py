"""Client for the daemon's control API (HTTP/JSON over its Unix socket).

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
import os
import socket
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

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
    """One request per connection; every method returns the decoded JSON reply."""

    def __init__(self, socket_path: str | Path, timeout_s: float = 10.0, retry_s: float = 2.0,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.socket_path = str(socket_path)
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
