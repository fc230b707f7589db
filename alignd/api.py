"""The control API: HTTP/JSON over a Unix socket, authorised by peer credentials.

Why the standard library (``socketserver`` + ``http.server``) rather than aiohttp: the
daemon is built around one worker thread that owns the hardware, and the API sees a handful
of requests a minute; a thread per connection fits that model with no event loop to bridge.
Each connection's socket has a read timeout and a total deadline enforced by a reaper
thread (a client that dribbles bytes cannot hold a thread), connections are admitted by
``alignd.admission`` (per-user caps, slots kept for peers who may control, refusals logged
at a bounded rate), bodies are size- and depth-limited, and ``SO_PEERCRED`` is read straight
from the accepted socket. No extra dependency is needed on a lab PC or a Raspberry Pi.

Authorisation: anyone who can connect may read (status, history, runs, frames); starting,
aborting or resetting needs root, the daemon's own user, or membership of
``daemon.operator_group`` (``null``: nobody else). Group membership is the connecting
process's own groups as the kernel has them (``SO_PEERGROUPS``), never the group database:
a process that dropped a group has dropped its rights. If the kernel cannot say, only the
primary group counts (fail closed). Control requests are authorised before their body is
read.

Endpoints (all JSON unless noted; errors are ``{"error": CODE, "message": TEXT}``):
``GET /status``, ``GET /history?limit=N``, ``GET /runs/ID``,
``GET /runs/ID/events?after=SEQ&wait=S`` (long-poll for live progress), ``GET /frames/HASH``
(image/png), ``POST /align`` and ``POST /check`` (body ``{"started_by": "user"|"timer"}``),
``POST /abort``, ``POST /reset`` (reconnect the hardware after a fault).
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import grp
import json
import logging
import os
import pwd
import re
import socket
import socketserver
import stat
import struct
import threading
import time
from dataclasses import dataclass, field
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler
from pathlib import Path
from typing import Any, Protocol
from urllib.parse import parse_qs, urlsplit

from alignd.admission import Admission, Limits, RefusalLog, Slot
from alignd.errors import AligndError, StateError

log = logging.getLogger(__name__)

MAX_BODY_BYTES = 64 * 1024
REQUEST_TIMEOUT_S = 10.0  # whole request (line, headers, body) must arrive within this
MAX_JSON_DEPTH = 8  # request bodies are flat objects; deeper nesting is refused (400)
LISTEN_BACKLOG = 128  # connects waiting for accept(); a burst must not be refused
MAX_WAIT_S = 30.0  # longest long-poll a client may ask for
SO_PEERGROUPS = getattr(socket, "SO_PEERGROUPS", 59)  # Linux >= 4.13
_PY_GETSOCKOPT_MAX = 1024  # CPython's getsockopt() accepts a buffer of at most 1024 bytes
_NGROUPS_MAX = 65536  # Linux
CONTROL_ACTIONS = {"align": "start an alignment", "check": "start a check",
                   "abort": "abort a run", "reset": "reset the daemon"}
_STARTED_BY = re.compile(r"^[a-z][a-z0-9_.-]{0,31}$")
_HASH = re.compile(r"^[0-9a-f]{64}$")


class Refused(AligndError):
    """A request the daemon declines (busy, faulted, forbidden, unknown run, ...)."""

    def __init__(self, http_status: int, code: str, message: str, **extra: Any) -> None:
        super().__init__(message)
        self.http_status = http_status
        self.code = code
        self.extra = extra

    def body(self) -> dict[str, Any]:
        return {"error": self.code, "message": str(self), **self.extra}


@dataclass(frozen=True)
class Peer:
    """Who is on the other end of a connection (from the kernel, not from the request)."""

    pid: int
    uid: int
    gid: int
    groups: frozenset[int] = field(default_factory=frozenset)
    groups_known: bool = True  # False: the kernel did not report the supplementary groups

    @property
    def user(self) -> str:
        try:
            return pwd.getpwuid(self.uid).pw_name
        except KeyError:
            return str(self.uid)

    def describe(self) -> str:
        return f"{self.user} (uid {self.uid}, pid {self.pid})"


def peer_credentials(sock: socket.socket) -> Peer:
    """The connecting process's pid/uid/gid and supplementary groups (as they were when
    it connected). Without ``SO_PEERGROUPS`` only the primary group is known: fail closed."""
    pid, uid, gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                        struct.calcsize("3i")))
    try:
        groups = peer_groups(sock)
    except OSError as exc:
        log.warning("cannot read the supplementary groups of pid %d (uid %d): %s; only its "
                    "primary group %d counts", pid, uid, exc, gid)
        return Peer(pid=pid, uid=uid, gid=gid, groups=frozenset({gid}), groups_known=False)
    return Peer(pid=pid, uid=uid, gid=gid, groups=groups | {gid})


def peer_groups(sock: socket.socket) -> frozenset[int]:
    """``SO_PEERGROUPS``: up to 256 groups through Python's ``getsockopt``; a peer in more
    (the kernel answers ERANGE) is read with libc's ``getsockopt`` and a buffer for
    NGROUPS_MAX groups. Raises ``OSError`` when the kernel cannot tell."""
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, SO_PEERGROUPS, _PY_GETSOCKOPT_MAX)
    except OSError as exc:
        if exc.errno != errno.ERANGE:
            raise
        raw = _getsockopt_bytes(sock.fileno(), SO_PEERGROUPS, 4 * _NGROUPS_MAX)
    n = len(raw) // 4
    return frozenset(struct.unpack(f"{n}I", raw[: 4 * n]))


def _getsockopt_bytes(fd: int, option: int, size: int) -> bytes:
    """libc ``getsockopt(fd, SOL_SOCKET, option)`` with a buffer of ``size`` bytes."""
    libc = ctypes.CDLL(None, use_errno=True)
    buf = ctypes.create_string_buffer(size)
    length = ctypes.c_uint32(size)  # socklen_t
    if libc.getsockopt(fd, socket.SOL_SOCKET, option, buf, ctypes.byref(length)) != 0:
        err = ctypes.get_errno()
        raise OSError(err, os.strerror(err))
    return buf.raw[: length.value]


class Authoriser:
    """Who may control the instrument: root, ``allow_uids`` and the operator group."""

    def __init__(self, operator_group: str | None, allow_uids: frozenset[int] | None = None
                 ) -> None:
        self.operator_group = operator_group
        self.allow_uids = frozenset({os.getuid()}) if allow_uids is None else allow_uids
        self.operator_gid: int | None = None
        if operator_group is not None:
            try:
                self.operator_gid = grp.getgrnam(operator_group).gr_gid
            except KeyError:
                log.warning("operator group %r does not exist: only root and uid(s) %s may "
                            "control alignd", operator_group, sorted(self.allow_uids))

    def may_control(self, peer: Peer) -> bool:
        if peer.uid == 0 or peer.uid in self.allow_uids:
            return True
        return self.operator_gid is not None and self.operator_gid in peer.groups

    def require_control(self, peer: Peer, action: str) -> None:
        if self.may_control(peer):
            return
        if self.operator_group is None:
            need = ("only root and the daemon's user may (no daemon.operator_group is "
                    "configured)")
        else:
            need = f"needs membership of the operator group {self.operator_group!r}"
            if not peer.groups_known:
                need += " (the kernel did not report the process's groups)"
        raise Refused(HTTPStatus.FORBIDDEN, "forbidden",
                      f"{peer.describe()} may not {action}: {need}")


class Controller(Protocol):
    """What the API needs from the daemon (``alignd.daemon.Daemon`` implements it)."""

    def status(self) -> dict[str, Any]: ...
    def history(self, limit: int) -> list[dict[str, Any]]: ...
    def run(self, run_id: int) -> dict[str, Any] | None: ...
    def events(self, run_id: int, after: int, wait_s: float) -> dict[str, Any] | None: ...
    def frame(self, digest: str) -> bytes | None: ...
    def start_run(self, kind: str, started_by: str, peer: Peer) -> dict[str, Any]: ...
    def abort(self, peer: Peer) -> dict[str, Any]: ...
    def reset(self, peer: Peer) -> dict[str, Any]: ...


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"
    default_request_version = "HTTP/1.0"  # error replies always carry a status line
    server_version = "alignd"
    server: ApiServer

    # ---- connection plumbing ----------------------------------------------------------
    def setup(self) -> None:
        super().setup()
        self.request.settimeout(self.server.request_timeout_s)
        self.server._deadline(self.request, self.server.request_timeout_s)

    def finish(self) -> None:
        self.server._deadline(self.request, None)
        with contextlib.suppress(OSError):
            super().finish()

    def handle(self) -> None:
        # one request per connection: no idle keep-alive connections holding threads
        self.close_connection = True
        try:
            self.handle_one_request()
        except (ConnectionError, TimeoutError, OSError) as exc:
            log.debug("API connection dropped: %s", exc)
            return
        self._lingering_close()

    def _lingering_close(self) -> None:
        """Half-close, then discard what the client still sends (briefly): closing with
        unread input makes the kernel reset the connection, and the client would lose
        the error reply (e.g. 413 for a body it was still sending)."""
        with contextlib.suppress(OSError):
            self.wfile.flush()
            self.request.shutdown(socket.SHUT_WR)
            self.request.settimeout(0.2)
            drained = 0
            while drained < (1 << 20):
                chunk = self.request.recv(65536)
                if not chunk:
                    break
                drained += len(chunk)

    def address_string(self) -> str:
        return "unix"

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("API %s", format % args)

    def send_error(self, code: int, message: str | None = None, explain: str | None = None
                   ) -> None:
        """JSON error bodies, also for the errors http.server raises while parsing."""
        with contextlib.suppress(OSError):
            phrase = HTTPStatus(code).phrase if code in HTTPStatus._value2member_map_ else ""
            self._send_json(code, {"error": phrase.lower().replace(" ", "_") or "error",
                                   "message": message or explain or phrase})
        self.close_connection = True

    def _send(self, code: int, body: bytes, ctype: str) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _send_json(self, code: int, obj: Any) -> None:
        self._send(code, (json.dumps(obj, allow_nan=False) + "\n").encode(), "application/json")

    # ---- request handling -------------------------------------------------------------
    def _read_body(self) -> dict[str, Any]:
        if self.headers.get("Transfer-Encoding"):
            raise Refused(HTTPStatus.LENGTH_REQUIRED, "length_required",
                          "chunked bodies are not accepted; send Content-Length")
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            raise Refused(HTTPStatus.BAD_REQUEST, "bad_request",
                          "Content-Length is not a number") from None
        if length < 0:
            raise Refused(HTTPStatus.BAD_REQUEST, "bad_request", "negative Content-Length")
        if length > self.server.max_body:
            raise Refused(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, "too_large",
                          f"body of {length} bytes exceeds the limit of "
                          f"{self.server.max_body} bytes")
        if length == 0:
            return {}
        try:
            data = self.rfile.read(length)
        except (TimeoutError, OSError):
            data = b""
        if len(data) != length:
            raise Refused(HTTPStatus.REQUEST_TIMEOUT, "timeout",
                          f"request body incomplete ({len(data)} of {length} bytes)")
        depth = json_depth(data)
        if depth > MAX_JSON_DEPTH:
            raise Refused(HTTPStatus.BAD_REQUEST, "bad_json",
                          f"body is nested {depth} levels deep; at most {MAX_JSON_DEPTH} "
                          "are accepted")
        try:
            body = json.loads(data)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise Refused(HTTPStatus.BAD_REQUEST, "bad_json", f"body is not JSON: {exc}"
                          ) from None
        if not isinstance(body, dict):
            raise Refused(HTTPStatus.BAD_REQUEST, "bad_json", "body must be a JSON object")
        return body

    def _dispatch(self, method: str) -> None:
        try:
            url = urlsplit(self.path)
            query = {k: v[-1] for k, v in parse_qs(url.query, max_num_fields=20).items()}
            action = CONTROL_ACTIONS.get(url.path.strip("/"))
            if method == "POST" and action is not None:  # before a byte of the body is read
                self.server.authoriser.require_control(self.server.peer(self.request), action)
            body = self._read_body() if method == "POST" else {}
            # the request has fully arrived: a long-poll may now outlast the request deadline
            self.server._deadline(self.request, None)
            self.request.settimeout(self.server.request_timeout_s + MAX_WAIT_S)
            code, payload = self.server.route(method, url.path, query, body, self.request)
        except Refused as exc:
            code, payload = exc.http_status, exc.body()
        except (ValueError, StateError) as exc:
            code, payload = HTTPStatus.BAD_REQUEST, {"error": "bad_request", "message": str(exc)}
        except Exception as exc:  # the daemon must survive any request
            log.exception("API %s %s failed", method, self.path)
            code, payload = HTTPStatus.INTERNAL_SERVER_ERROR, {
                "error": "internal", "message": f"{type(exc).__name__}: {exc}"}
        try:
            if isinstance(payload, bytes):
                self._send(code, payload, "image/png")
            else:
                self._send_json(code, payload)
        except OSError as exc:
            log.debug("API client went away before the reply: %s", exc)

    def do_GET(self) -> None:
        self._dispatch("GET")

    def do_POST(self) -> None:
        self._dispatch("POST")

    def _not_allowed(self) -> None:
        self.send_error(HTTPStatus.METHOD_NOT_ALLOWED, f"method {self.command} not allowed")

    do_PUT = do_DELETE = do_PATCH = do_HEAD = do_OPTIONS = _not_allowed  # noqa: N815


class ApiServer(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    """The Unix-socket HTTP server. ``start()`` serves in a background thread."""

    daemon_threads = True
    block_on_close = False
    allow_reuse_address = False
    request_queue_size = LISTEN_BACKLOG  # listen() backlog

    def __init__(self, path: str | Path, controller: Controller, authoriser: Authoriser, *,
                 limits: Limits | None = None,
                 request_timeout_s: float = REQUEST_TIMEOUT_S,
                 max_body: int = MAX_BODY_BYTES, mode: int = 0o666,
                 refusal_log: RefusalLog | None = None) -> None:
        self.path = Path(path)
        self.controller = controller
        self.authoriser = authoriser
        self.request_timeout_s = request_timeout_s
        self.max_body = max_body
        self.admission = Admission(limits)
        self.refusals = refusal_log or RefusalLog()
        self._conns: dict[socket.socket, tuple[Peer, Slot]] = {}
        self._conns_lock = threading.Lock()
        self._deadlines: dict[socket.socket, float] = {}
        self._dl_lock = threading.Lock()
        self._stopping = threading.Event()
        self._bg_threads: list[threading.Thread] = []
        _prepare_socket_path(self.path)
        super().__init__(str(self.path), _Handler, bind_and_activate=True)
        os.chmod(self.path, mode)  # who may connect; control rights come from peer creds

    # ---- lifecycle --------------------------------------------------------------------
    def start(self) -> None:
        def serve() -> None:
            self.serve_forever(poll_interval=0.1)  # shutdown() returns within 0.1 s

        for name, target in (("alignd-api", serve), ("alignd-api-reaper", self._reap)):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._bg_threads.append(t)
        log.info("API listening on %s", self.path)

    def stop(self) -> None:
        self._stopping.set()
        if self._bg_threads:
            self.shutdown()
        self.server_close()
        with contextlib.suppress(FileNotFoundError):
            self.path.unlink()
        for t in self._bg_threads:
            t.join(timeout=2.0)

    # ---- connection limits ------------------------------------------------------------
    def process_request(self, request: Any, client_address: Any) -> None:
        """Admit or refuse a new connection, by who is connecting (see ``alignd.admission``)."""
        try:
            peer = peer_credentials(request)
        except OSError as exc:  # no credentials: an unprivileged stranger
            log.warning("API: cannot read peer credentials: %s", exc)
            peer = Peer(pid=0, uid=-1, gid=-1, groups_known=False)
        slot, why = self.admission.admit(peer.uid, self.authoriser.may_control(peer))
        if slot is None:
            self.refusals.refused(peer.uid, why)
            self._refuse(request, f"too many connections: {why}")
            return
        with self._conns_lock:
            self._conns[request] = (peer, slot)
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._forget(request)
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._forget(request)

    def _forget(self, request: socket.socket) -> None:
        with self._conns_lock:
            entry = self._conns.pop(request, None)
        if entry is not None:
            self.admission.release(entry[1])

    def peer(self, request: socket.socket) -> Peer:
        """Who is on the other end of an admitted connection (read once, at accept)."""
        with self._conns_lock:
            entry = self._conns.get(request)
        return entry[0] if entry is not None else peer_credentials(request)

    def _refuse(self, request: socket.socket, message: str) -> None:
        """503 at once, without reading the request; never blocks the accept loop."""
        with contextlib.suppress(OSError):
            request.settimeout(0.5)
            msg = (json.dumps({"error": "overloaded", "message": message}) + "\n").encode()
            request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: "
                            b"application/json\r\nConnection: close\r\nContent-Length: "
                            + str(len(msg)).encode() + b"\r\n\r\n" + msg)
            # discard what already arrived, so closing does not reset the connection
            # before the client reads the reply
            request.setblocking(False)
            with contextlib.suppress(BlockingIOError):
                while request.recv(65536):
                    pass
        self.shutdown_request(request)

    def _deadline(self, sock: socket.socket, seconds: float | None) -> None:
        with self._dl_lock:
            if seconds is None:
                self._deadlines.pop(sock, None)
            else:
                self._deadlines[sock] = time.monotonic() + seconds

    def _reap(self) -> None:
        """Cut connections whose request has not fully arrived by its deadline."""
        while not self._stopping.wait(0.25):
            self.refusals.flush()
            now = time.monotonic()
            with self._dl_lock:
                late = [s for s, t in self._deadlines.items() if t < now]
                for s in late:
                    del self._deadlines[s]
            for s in late:
                log.info("API: request not complete within %.0f s; closing the connection",
                         self.request_timeout_s)
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    # ---- routing ----------------------------------------------------------------------
    def route(self, method: str, path: str, query: dict[str, str], body: dict[str, Any],
              sock: socket.socket) -> tuple[int, Any]:
        c = self.controller
        parts = [p for p in path.split("/") if p]
        if method == "GET":
            if parts == ["status"]:
                return HTTPStatus.OK, c.status()
            if parts == ["history"]:
                limit = _int_arg(query, "limit", 20, 1, 1000)
                return HTTPStatus.OK, {"runs": c.history(limit)}
            if len(parts) in (2, 3) and parts[0] == "runs":
                run_id = _run_id(parts[1])
                if len(parts) == 2:
                    found = c.run(run_id)
                elif parts[2] == "events":
                    found = c.events(run_id, _int_arg(query, "after", 0, 0, 2**62),
                                     _float_arg(query, "wait", 0.0, 0.0, MAX_WAIT_S))
                else:
                    raise Refused(HTTPStatus.NOT_FOUND, "not_found", f"no resource {path}")
                if found is None:
                    raise Refused(HTTPStatus.NOT_FOUND, "no_such_run", f"no run {run_id}")
                return HTTPStatus.OK, found
            if len(parts) == 2 and parts[0] == "frames":
                digest = parts[1].removesuffix(".png")
                if not _HASH.match(digest):
                    raise Refused(HTTPStatus.BAD_REQUEST, "bad_request",
                                  "a frame is named by its SHA-256 (64 hex digits)")
                data = c.frame(digest)
                if data is None:
                    raise Refused(HTTPStatus.NOT_FOUND, "no_such_frame", f"no frame {digest}")
                return HTTPStatus.OK, data
        elif method == "POST":
            if len(parts) == 1 and parts[0] in CONTROL_ACTIONS:
                peer = self.peer(sock)
                self.authoriser.require_control(peer, CONTROL_ACTIONS[parts[0]])
                if parts[0] in ("align", "check"):
                    started_by = body.get("started_by", "user")
                    if not isinstance(started_by, str) or not _STARTED_BY.match(started_by):
                        raise Refused(HTTPStatus.BAD_REQUEST, "bad_request",
                                      "started_by must be a short lower-case word "
                                      "('user' or 'timer')")
                    return HTTPStatus.ACCEPTED, c.start_run(parts[0], started_by, peer)
                if parts[0] == "abort":
                    return HTTPStatus.OK, c.abort(peer)
                return HTTPStatus.ACCEPTED, c.reset(peer)
        else:
            raise Refused(HTTPStatus.METHOD_NOT_ALLOWED, "method_not_allowed",
                          f"method {method} not allowed")
        known = {"status", "history", "runs", "frames", "align", "check", "abort", "reset"}
        if parts and parts[0] in known:
            raise Refused(HTTPStatus.METHOD_NOT_ALLOWED, "method_not_allowed",
                          f"{method} {path} is not allowed")
        raise Refused(HTTPStatus.NOT_FOUND, "not_found", f"no resource {path}")


def json_depth(data: bytes) -> int:
    """How deeply ``[`` / ``{`` nest in a JSON text (brackets inside strings do not count);
    measured before parsing, so a hostile body never reaches the recursive parser."""
    depth = deepest = 0
    in_string = escaped = False
    for byte in data:
        if in_string:
            if escaped:
                escaped = False
            elif byte == 0x5C:  # backslash
                escaped = True
            elif byte == 0x22:  # quote
                in_string = False
        elif byte == 0x22:
            in_string = True
        elif byte in (0x5B, 0x7B):  # [ {
            depth += 1
            deepest = max(deepest, depth)
        elif byte in (0x5D, 0x7D):  # ] }
            depth -= 1
    return deepest


def _int_arg(query: dict[str, str], key: str, default: int, lo: int, hi: int) -> int:
    if key not in query:
        return default
    try:
        v = int(query[key])
    except ValueError:
        raise Refused(HTTPStatus.BAD_REQUEST, "bad_request", f"{key} must be an integer"
                      ) from None
    return min(max(v, lo), hi)


def _float_arg(query: dict[str, str], key: str, default: float, lo: float, hi: float) -> float:
    if key not in query:
        return default
    try:
        v = float(query[key])
    except ValueError:
        raise Refused(HTTPStatus.BAD_REQUEST, "bad_request", f"{key} must be a number"
                      ) from None
    if v != v:  # NaN
        raise Refused(HTTPStatus.BAD_REQUEST, "bad_request", f"{key} must be a number")
    return min(max(v, lo), hi)


def _run_id(text: str) -> int:
    if not text.isdigit() or len(text) > 18:
        raise Refused(HTTPStatus.BAD_REQUEST, "bad_request", f"run id {text!r} is not a number")
    return int(text)


def _prepare_socket_path(path: Path) -> None:
    """Make room for the socket: create its directory, remove a stale socket, and refuse
    if another daemon is listening there or the path is not a socket."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StateError(f"{path}: cannot create the socket directory: "
                         f"{exc.strerror or exc}") from None
    try:
        st = path.lstat()
    except FileNotFoundError:
        return
    if not stat.S_ISSOCK(st.st_mode):
        raise StateError(f"{path}: exists and is not a socket; refusing to replace it")
    probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    probe.settimeout(1.0)
    try:
        probe.connect(str(path))
    except OSError:
        log.info("removing stale socket %s", path)
        path.unlink(missing_ok=True)
        return
    finally:
        probe.close()
    raise StateError(f"{path}: another alignd is already listening on this socket")
