"""The read-only web dashboard and ``/metrics``, on TCP (``alignd --web HOST:PORT``).

Why read-only: control needs the peer's credentials, which only the Unix socket gives
(``SO_PEERCRED``); a TCP port reachable from the lab network must not start, abort or
change anything. Every method but GET/HEAD is answered 405 with where control lives.

Why the standard library's ``ThreadingHTTPServer``: the pages are a handful of files and
JSON views polled by one or two browsers; the same thread-per-request model as the control
API, no event loop, no extra dependency. The pages are plain HTML/CSS/JS shipped in the
package (``alignd/web/static``), with no build step and nothing fetched from elsewhere.

Routes: ``/`` (state, progress, live cameras), ``/history`` (runs, trend chart),
``/run/ID`` (one run) and their JSON: ``/api/status``, ``/api/history?limit=N``,
``/api/runs/ID``, ``/api/runs/ID/events?after=SEQ``; ``/live/ROLE.jpg`` (latest frame
with overlays), ``/runs/ID/report.png``, ``/runs/ID.json``, ``/runs/ID.csv``, ``/metrics``.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import math
import re
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from typing import Any, Protocol
from urllib.parse import parse_qs, urlsplit

from alignd.config import AligndConfig
from alignd.errors import ConfigError
from alignd.store import Store, jsonable
from alignd.web.frames import LiveFrames
from alignd.web.live import LiveView
from alignd.web.metrics import CONTENT_TYPE as METRICS_TYPE
from alignd.web.metrics import Metrics

log = logging.getLogger(__name__)

MAX_CONNECTIONS = 16  # browsers open a few each; more is someone misbehaving
REQUEST_TIMEOUT_S = 10.0

READ_ONLY = ("this dashboard is read-only: start, abort or reset runs with alignctl on the "
             "control socket (Unix socket, peer credentials)")
STATIC_TYPES = {".html": "text/html; charset=utf-8", ".css": "text/css; charset=utf-8",
                ".js": "text/javascript; charset=utf-8", ".svg": "image/svg+xml"}
PAGES = {"": "index.html", "history": "history.html"}
_RUN_PAGE = re.compile(r"^/run/(\d{1,18})$")
_RUN_FILE = re.compile(r"^/runs/(\d{1,18})(\.json|\.csv|/report\.png)$")
_STATIC = re.compile(r"^/static/([a-z0-9_-]+\.(?:html|css|js|svg))$")
_RUN_EVENTS = re.compile(r"^/api/runs/(\d{1,18})/events$")
_LIVE = re.compile(r"^/live/([a-z0-9_-]{1,32})\.jpg$")


class WebSource(Protocol):
    """What the dashboard reads from the daemon (``alignd.daemon.Daemon``)."""

    cfg: AligndConfig
    store: Store
    live: LiveFrames
    faults: int

    def status(self) -> dict[str, Any]: ...
    def history(self, limit: int) -> list[dict[str, Any]]: ...
    def run(self, run_id: int) -> dict[str, Any] | None: ...
    def frame(self, digest: str) -> bytes | None: ...
    def events(self, run_id: int, after: int, wait_s: float) -> dict[str, Any] | None: ...


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT`` or ``PORT`` (host 127.0.0.1); ``[::1]:PORT`` for IPv6."""
    host, sep, port = text.strip().rpartition(":")
    if not sep:
        host, port = "", text.strip()
    host = host.strip("[]") or "127.0.0.1"
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ConfigError(f"web address {text!r}: expected HOST:PORT with a port 0-65535 "
                          "(e.g. 127.0.0.1:8080)")
    return host, int(port)


class _Handler(BaseHTTPRequestHandler):
    server: WebServer
    protocol_version = "HTTP/1.1"
    server_version = "alignd-web"
    timeout = REQUEST_TIMEOUT_S  # a client that stops sending is dropped

    def log_message(self, format: str, *args: Any) -> None:
        log.debug("web %s %s", self.address_string(), format % args)

    def _send(self, code: int, body: bytes, ctype: str, extra: dict[str, str] | None = None
              ) -> None:
        self.send_response(code)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, code: int, obj: Any) -> None:
        self._send(code, (json.dumps(jsonable(obj), allow_nan=False) + "\n").encode(),
                   "application/json")

    def _error(self, code: int, error: str, message: str) -> None:
        self._json(code, {"error": error, "message": message})

    def do_GET(self) -> None:
        try:
            self.server.route(self)
        except (ConnectionError, TimeoutError):
            pass
        except Exception as exc:  # the daemon must survive any request
            log.exception("web GET %s failed", self.path)
            with contextlib.suppress(OSError):
                self._error(500, "internal", f"{type(exc).__name__}: {exc}")

    do_HEAD = do_GET  # noqa: N815

    def _read_only(self) -> None:
        self.close_connection = True
        self.send_response(HTTPStatus.METHOD_NOT_ALLOWED)
        body = (json.dumps({"error": "read_only", "message": READ_ONLY}) + "\n").encode()
        self.send_header("Allow", "GET, HEAD")
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Connection", "close")
        self.end_headers()
        self.wfile.write(body)

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _read_only  # noqa: N815


class WebServer(ThreadingHTTPServer):
    """The dashboard's HTTP server; ``start()`` serves in a background thread."""

    daemon_threads = True
    block_on_close = False

    def __init__(self, address: tuple[str, int], source: WebSource,
                 max_connections: int = MAX_CONNECTIONS) -> None:
        self.source = source
        self._slots = threading.BoundedSemaphore(max_connections)
        self.view = LiveView(source)
        self.metrics = Metrics(source)
        self._report_cache: dict[int, tuple[str, bytes]] = {}
        self._report_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        if ":" in address[0]:
            import socket

            self.address_family = socket.AF_INET6
        super().__init__(address, _Handler)

    @property
    def url(self) -> str:
        addr, port = self.server_address[:2]
        host = addr.decode() if isinstance(addr, bytes) else str(addr)
        return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"

    def start(self) -> None:
        self._thread = threading.Thread(target=self.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="alignd-web", daemon=True)
        self._thread.start()
        log.info("web dashboard (read-only) and /metrics on %s", self.url)

    def stop(self) -> None:
        if self._thread is not None:
            self.shutdown()
            self._thread.join(timeout=2.0)
        self.server_close()

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):  # never let the dashboard eat threads
            log.warning("web: too many connections; refusing one from %s", client_address)
            with contextlib.suppress(OSError):
                request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n"
                                b"Connection: close\r\n\r\n")
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._slots.release()
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._slots.release()

    # ---- routing ------------------------------------------------------------------------
    def route(self, h: _Handler) -> None:
        url = urlsplit(h.path)
        path = url.path.rstrip("/") if url.path != "/" else "/"
        query = {k: v[-1] for k, v in parse_qs(url.query, max_num_fields=10).items()}
        src = self.source
        if path.lstrip("/") in PAGES:
            return self._static(h, PAGES[path.lstrip("/")])
        if _RUN_PAGE.match(path):
            return self._static(h, "run.html")
        if m := _STATIC.match(path):
            return self._static(h, m.group(1))
        if path == "/api/status":
            return h._json(200, self.status())
        if path == "/api/history":
            try:
                limit = min(max(int(query.get("limit", "200")), 1), 5000)
            except ValueError:
                return h._error(400, "bad_request", "limit must be an integer")
            return h._json(200, {"runs": src.history(limit),
                                 "tolerance_um": src.cfg.procedure.tolerance_um})
        if m := _RUN_EVENTS.match(path):
            try:
                after = max(int(query.get("after", "0")), 0)
            except ValueError:
                return h._error(400, "bad_request", "after must be an integer")
            found = src.events(int(m.group(1)), after, 0.0)
            if found is None:
                return h._error(404, "no_such_run", f"no run {m.group(1)}")
            return h._json(200, found)
        if path.startswith("/api/runs/") and path[10:].isdigit() and len(path) < 30:
            run = src.run(int(path[10:]))
            if run is None:
                return h._error(404, "no_such_run", f"no run {path[10:]}")
            return h._json(200, run)
        if m := _LIVE.match(path):
            return self._live(h, m.group(1))
        if m := _RUN_FILE.match(path):
            return self._run_file(h, int(m.group(1)), m.group(2))
        if path == "/metrics":
            return h._send(200, self.metrics.render(), METRICS_TYPE)
        return h._error(404, "not_found", f"no page {url.path}")

    def _static(self, h: _Handler, name: str) -> None:
        try:
            data = resources.files("alignd.web").joinpath("static", name).read_bytes()
        except (FileNotFoundError, IsADirectoryError):
            return h._error(404, "not_found", f"no file {name}")
        h._send(200, data, STATIC_TYPES["." + name.rsplit(".", 1)[-1]])

    def status(self) -> dict[str, Any]:
        """The daemon's status plus what the dashboard shows about the cameras."""
        st = dict(self.source.status())
        live = self.source.live
        cams: dict[str, Any] = {}
        for cam in self.source.cfg.cameras:
            f = live.get(cam.role)
            cams[cam.role] = {"seq": f.seq if f else None, "error": f.error if f else None,
                              "has_frame": bool(f and f.image is not None)}
        st["dashboard"] = {"read_only": True, "note": READ_ONLY, "cameras": cams,
                     "cameras_unavailable": live.unavailable,
                     "tolerance_um": self.source.cfg.procedure.tolerance_um}
        return st

    def _live(self, h: _Handler, role: str) -> None:
        if self.source.cfg.camera(role) is None:
            return h._error(404, "no_such_camera", f"no camera with role {role!r}")
        got = self.view.view(role)
        if got is None:
            why = self.source.live.unavailable or "no frame grabbed yet"
            return h._error(503, "no_frame", f"{role} camera: {why}")
        jpeg, info = got
        h._send(200, jpeg, "image/jpeg", {"X-Alignd-View": json.dumps(info)})

    def _run_file(self, h: _Handler, run_id: int, what: str) -> None:
        run = self.source.run(run_id)
        if run is None:
            return h._error(404, "no_such_run", f"no run {run_id}")
        if what == ".json":
            body = (json.dumps(jsonable(run), indent=1, allow_nan=False) + "\n").encode()
            return h._send(200, body, "application/json", _download(f"run-{run_id}.json"))
        if what == ".csv":
            return h._send(200, run_csv(run).encode(), "text/csv; charset=utf-8",
                           _download(f"run-{run_id}.csv"))
        return h._send(200, self._report_png(run), "image/png")

    def _report_png(self, run: dict[str, Any]) -> bytes:
        """The report figure, rendered once per run state (a running run re-renders)."""
        import cv2

        from alignd import report
        from alignd.report_side import side_frame_hash

        run_id = int(run["id"])
        key = f"{run.get('status')}:{len(run.get('iteration_records') or [])}"
        with self._report_lock:
            hit = self._report_cache.get(run_id)
            if hit is not None and hit[0] == key:
                return hit[1]
        image = None
        pick = report.pick_frame(run)
        if pick is not None:
            data = self.source.frame(pick["hash"])
            if data is not None:
                with contextlib.suppress(ValueError):
                    image = report.decode_png(data)
        side_image = None
        side = side_frame_hash(run)
        if side is not None and (data := self.source.frame(side)) is not None:
            with contextlib.suppress(ValueError):
                side_image = report.decode_png(data)
        ok, buf = cv2.imencode(".png", report.render_report(run, image, side_image))
        if not ok:
            raise ValueError(f"cannot encode the report of run {run_id}")
        png = buf.tobytes()
        with self._report_lock:
            if len(self._report_cache) > 32:
                self._report_cache.clear()
            self._report_cache[run_id] = (key, png)
        return png


def _download(name: str) -> dict[str, str]:
    return {"Content-Disposition": f'attachment; filename="{name}"'}


def run_csv(run: dict[str, Any]) -> str:
    """A run's sweep data as CSV: one row per frame and tracked corner."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["run", "sweep", "kind", "iteration", "frame", "commanded_deg", "readback_deg",
                "corner", "x_px", "y_px"])
    for s_i, s in enumerate(run.get("sweeps") or []):
        frames = (s.get("sweep") or {}).get("frames") or []
        commanded = s.get("commanded") or []
        for f_i, fr in enumerate(frames):
            cmd = commanded[f_i] if f_i < len(commanded) else None
            for c_i, p in enumerate(fr.get("features") or []):
                x, y = (p if p is not None else (None, None))
                w.writerow([run.get("id"), s_i, s.get("kind"), s.get("iteration"), f_i,
                            _num(cmd), _num(fr.get("angle_deg")), c_i, _num(x), _num(y)])
    return out.getvalue()


def _num(v: Any) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return ""
    return f"{float(v):.6g}" if isinstance(v, (int, float)) else str(v)
