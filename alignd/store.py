"""Run history in SQLite, and frames as files named by their SHA-256 hash.

Why this shape: the history is the lab's record of what the instrument did, so nothing may
be half-written after a crash or a power cut. SQLite in WAL mode with ``synchronous=FULL``
makes every committed transaction durable, and each record (a run's start, a sweep, an
iteration, an event, a run's end) is one transaction. Frames are files written to a
temporary name, fsynced and renamed into place, then referenced from the database, so a
crash leaves at worst an unreferenced frame file, never a reference to a partial one.

One writer: the daemon owns one write connection (serialised by a lock); readers (the API
threads) open short-lived read-only connections and see a consistent WAL snapshot.
A run found still ``running`` when the daemon starts was cut off by a crash or SIGKILL and
is marked ``interrupted``; nothing restarts it.

A full disk must not cost a run its outcome: the store keeps ``reserve`` (a file of
``reserve_bytes`` of allocated blocks) and gives it up only when a record that ends a run
(its verdict and reason, or "interrupted") cannot be written otherwise. A new run is
refused until there is room for a whole run again (``min_free_bytes``, derived from the
configured sweep by ``alignd.config.run_footprint``) and the reserve is back.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import logging
import math
import os
import sqlite3
import tempfile
import threading
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from alignd.errors import AligndError
from alignd.procedures.recorder import image_hash

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
DB_NAME = "history.sqlite3"
FRAMES_DIR = "frames"
RUN_KINDS = ("align", "check")
# room a run needs, when no config says better (the daemon uses alignd.config.run_footprint)
MIN_FREE_BYTES = 64 * 1024 * 1024
RESERVE_NAME = "reserve"
RESERVE_BYTES = 4 * 1024 * 1024  # kept allocated to record a run's end on a full disk
INTERRUPTED_REASON = "daemon stopped before the run finished (crash, SIGKILL or power loss)"

_SCHEMA = """
CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL CHECK (kind IN ('align', 'check')),
    status TEXT NOT NULL CHECK (status IN ('running', 'finished', 'interrupted')),
    started_at TEXT NOT NULL,
    ended_at TEXT,
    started_by TEXT NOT NULL,
    user TEXT,
    uid INTEGER,
    software_version TEXT NOT NULL,
    config_hash TEXT NOT NULL,
    config_json TEXT NOT NULL,
    devices_json TEXT,
    verdict TEXT,
    reason TEXT,
    result_json TEXT,
    details_json TEXT
);
CREATE TABLE sweeps (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    t TEXT NOT NULL,
    kind TEXT NOT NULL,
    iteration INTEGER,
    sweep_json TEXT NOT NULL,
    commanded_json TEXT,
    readback_json TEXT
);
CREATE TABLE iterations (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    t TEXT NOT NULL,
    n INTEGER NOT NULL,
    record_json TEXT NOT NULL
);
CREATE TABLE events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id INTEGER REFERENCES runs(id) ON DELETE CASCADE,
    t TEXT NOT NULL,
    level TEXT NOT NULL,
    msg TEXT NOT NULL
);
CREATE TABLE frames (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id INTEGER NOT NULL REFERENCES runs(id) ON DELETE CASCADE,
    t TEXT NOT NULL,
    label TEXT NOT NULL,
    hash TEXT NOT NULL,
    width INTEGER,
    height INTEGER
);
CREATE INDEX sweeps_run ON sweeps(run_id);
CREATE INDEX iterations_run ON iterations(run_id);
CREATE INDEX events_run ON events(run_id);
CREATE INDEX frames_run ON frames(run_id);
CREATE INDEX runs_status ON runs(status);
"""


class StoreError(AligndError):
    """The history cannot be read or written (names the database file and the operation)."""

    disk_full = False  # the write failed for lack of space


def _is_full(exc: BaseException) -> bool:
    if isinstance(exc, sqlite3.Error):
        return exc.sqlite_errorcode == sqlite3.SQLITE_FULL or "disk is full" in str(exc)
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT)


def utc_now() -> str:
    """ISO 8601 UTC with milliseconds: sortable as text and readable in the sqlite3 shell."""
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def jsonable(obj: Any) -> Any:
    """Plain JSON types from numpy values, dataclasses, tuples and paths; NaN/inf -> None.

    Records come from the procedures with numpy scalars and arrays inside; strict JSON (no
    NaN) keeps every stored document readable by any JSON parser.
    """
    if obj is None or isinstance(obj, (bool, str, int)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [jsonable(v) for v in obj]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(dataclasses.asdict(obj))
    if isinstance(obj, Path):
        return str(obj)
    for attr in ("to_dict", "model_dump"):
        fn = getattr(obj, attr, None)
        if callable(fn):
            return jsonable(fn())
    return str(obj)


def dumps(obj: Any) -> str:
    return json.dumps(jsonable(obj), allow_nan=False, separators=(",", ":"))


def _loads(text: str | None) -> Any:
    return None if text is None else json.loads(text)


def fsync_dir(path: Path) -> None:
    """Make a rename in ``path`` durable (the directory entry itself must reach the disk)."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Write ``data`` to ``path`` so a reader or a crash sees the old file or the new, never
    a mixture: temp file in the same directory, fsync, rename, fsync the directory."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    fsync_dir(path.parent)


def _allocate(fd: int, size: int) -> None:
    """Real blocks for ``size`` bytes (not a sparse file that would need them later)."""
    try:
        os.posix_fallocate(fd, 0, size)
        return
    except OSError as exc:
        if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
            raise
    chunk = b"\0" * (1 << 20)
    for offset in range(0, size, len(chunk)):
        os.write(fd, chunk[: size - offset])


def encode_png(image: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise StoreError(f"cannot encode a frame of shape {image.shape} as PNG")
    return buf.tobytes()


class Store:
    """The run history of one instrument: ``<state_dir>/history.sqlite3`` + ``frames/``."""

    def __init__(self, state_dir: str | Path, min_free_bytes: int = MIN_FREE_BYTES,
                 reserve_bytes: int = RESERVE_BYTES) -> None:
        self.state_dir = Path(state_dir)
        self.min_free_bytes = min_free_bytes
        self.space_note = ""  # how min_free_bytes was reckoned (shown in messages)
        self.reserve_bytes = reserve_bytes
        self.db_path = self.state_dir / DB_NAME
        self.frames_dir = self.state_dir / FRAMES_DIR
        self.reserve_path = self.state_dir / RESERVE_NAME
        self._lock = threading.RLock()
        self._conn: sqlite3.Connection | None = None

    # ---- lifecycle --------------------------------------------------------------------
    def open(self) -> Store:
        """Open (creating or migrating) the database; raise ``StoreError`` if unusable."""
        try:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            self.frames_dir.mkdir(exist_ok=True)
            conn = sqlite3.connect(self.db_path, isolation_level=None, check_same_thread=False,
                                   timeout=10.0)
        except (OSError, sqlite3.Error) as exc:
            raise StoreError(f"{self.db_path}: cannot open the history database: {exc}") from None
        try:
            mode = conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StoreError(f"{self.db_path}: cannot switch to WAL mode (got {mode!r})")
            conn.execute("PRAGMA synchronous=FULL")
            conn.execute("PRAGMA foreign_keys=ON")
            self._conn = conn
            self._migrate()
            self._keep_reserve()
        except sqlite3.Error as exc:
            conn.close()
            self._conn = None
            raise StoreError(f"{self.db_path}: cannot open the history database: {exc}") from None
        except BaseException:
            conn.close()
            self._conn = None
            raise
        return self

    def close(self) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None

    def __enter__(self) -> Store:
        return self.open() if self._conn is None else self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _migrate(self) -> None:
        conn = self._require()
        version = conn.execute("PRAGMA user_version").fetchone()[0]
        if version == SCHEMA_VERSION:
            return
        if version > SCHEMA_VERSION:
            raise StoreError(f"{self.db_path}: schema version {version} is newer than this "
                             f"alignd understands ({SCHEMA_VERSION}); upgrade alignd")
        if version == 0:
            with self._tx() as c:
                # executescript would COMMIT on its own; run statement by statement instead
                for stmt in _SCHEMA.split(";"):
                    if stmt.strip():
                        c.execute(stmt)
                c.execute("INSERT INTO meta(key, value) VALUES ('created_at', ?)", (utc_now(),))
                c.execute(f"PRAGMA user_version={SCHEMA_VERSION}")
            log.info("created history database %s (schema %d)", self.db_path, SCHEMA_VERSION)

    def _require(self) -> sqlite3.Connection:
        if self._conn is None:
            raise StoreError(f"{self.db_path}: the history database is not open")
        return self._conn

    @contextlib.contextmanager
    def _tx(self) -> Iterator[sqlite3.Connection]:
        """One write transaction (BEGIN IMMEDIATE .. COMMIT); rolled back on any error."""
        with self._lock:
            conn = self._require()
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                with contextlib.suppress(sqlite3.Error):
                    conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def _write(self, what: str, fn: Any) -> Any:
        try:
            with self._tx() as conn:
                return fn(conn)
        except sqlite3.Error as exc:
            err = StoreError(f"{self.db_path}: cannot record {what}: {exc}")
            err.disk_full = _is_full(exc)
            raise err from None

    def _write_end(self, what: str, fn: Any) -> Any:
        """A record that ends a run: on a full disk, the reserve is given up for it."""
        try:
            return self._write(what, fn)
        except StoreError as exc:
            if not exc.disk_full or not self._release_reserve():
                raise
            log.warning("disk full: released the %.0f MiB reserve to record %s",
                        self.reserve_bytes / 2**20, what)
            return self._write(what, fn)

    # ---- the reserve ------------------------------------------------------------------
    def _keep_reserve(self) -> bool:
        """Make sure the reserve file holds ``reserve_bytes`` of allocated blocks; False if
        there is no room for it now."""
        with self._lock:
            try:
                st = self.reserve_path.stat()
                if st.st_size >= self.reserve_bytes and st.st_blocks * 512 >= self.reserve_bytes:
                    return True
            except FileNotFoundError:
                pass
            tmp = self.reserve_path.with_name(RESERVE_NAME + ".tmp")
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
                try:
                    _allocate(fd, self.reserve_bytes)
                    os.fsync(fd)
                finally:
                    os.close(fd)
                os.replace(tmp, self.reserve_path)
            except OSError as exc:
                with contextlib.suppress(OSError):
                    tmp.unlink()
                log.warning("%s: cannot keep the %.0f MiB reserve for recording a run's end: "
                            "%s", self.reserve_path, self.reserve_bytes / 2**20,
                            exc.strerror or exc)
                return False
            return True

    def _release_reserve(self) -> bool:
        with self._lock:
            try:
                self.reserve_path.unlink()
            except FileNotFoundError:
                return False
            return True

    def free_bytes(self) -> int:
        try:
            st = os.statvfs(self.state_dir)
        except OSError as exc:
            raise StoreError(f"{self.state_dir}: cannot check free space: "
                             f"{exc.strerror or exc}") from None
        return st.f_bavail * st.f_frsize

    def space_problem(self) -> str | None:
        """Why a run would be refused for lack of space now (``None``: there is room).
        Cheap (statvfs, stat); puts the reserve back once there is room for it."""
        try:
            free = self.free_bytes()
        except StoreError as exc:
            return str(exc)
        if free < self.min_free_bytes:
            note = f" ({self.space_note})" if self.space_note else ""
            return (f"{self.state_dir}: disk nearly full: {free / 2**20:.1f} MiB free, a run "
                    f"needs at least {self.min_free_bytes / 2**20:.0f} MiB{note}")
        if not self._keep_reserve():
            return (f"{self.state_dir}: disk nearly full: no room to keep the "
                    f"{self.reserve_bytes / 2**20:.0f} MiB that record a run's end")
        return None

    @contextlib.contextmanager
    def _reader(self) -> Iterator[sqlite3.Connection]:
        """A short-lived read-only connection: API threads never block the writer."""
        try:
            conn = sqlite3.connect(f"{self.db_path.resolve().as_uri()}?mode=ro", uri=True,
                                   timeout=10.0)
        except sqlite3.Error as exc:
            raise StoreError(f"{self.db_path}: cannot read the history database: {exc}") from None
        conn.row_factory = sqlite3.Row
        try:
            yield conn
        except sqlite3.Error as exc:
            raise StoreError(f"{self.db_path}: cannot read the history database: {exc}") from None
        finally:
            conn.close()

    # ---- health -----------------------------------------------------------------------
    def check_writable(self) -> None:
        """Prove a run could be recorded now: room on the disk, a committed write to the
        database and a durable file in the frames directory. Raise ``StoreError`` naming
        what failed. (SQLite reuses free pages, so only the free-space check sees a disk
        that is about to fill.)"""
        problem = self.space_problem()
        if problem:
            raise StoreError(problem)
        self._write("a write probe", lambda c: c.execute(
            "INSERT INTO meta(key, value) VALUES ('last_write_probe', ?) "
            "ON CONFLICT(key) DO UPDATE SET value = excluded.value", (utc_now(),)))
        try:
            atomic_write_bytes(self.frames_dir / ".write-probe", b"ok\n")
        except OSError as exc:
            raise StoreError(f"{self.frames_dir}: cannot write frames: "
                             f"{exc.strerror or exc}") from None

    def integrity_check(self) -> list[str]:
        """``PRAGMA integrity_check`` rows: ``["ok"]`` when the database is sound."""
        with self._reader() as conn:
            return [r[0] for r in conn.execute("PRAGMA integrity_check").fetchall()]

    # ---- writes -----------------------------------------------------------------------
    def mark_interrupted(self, reason: str = INTERRUPTED_REASON) -> list[int]:
        """Close every run left ``running`` (the previous daemon died mid-run)."""

        def fn(c: sqlite3.Connection) -> list[int]:
            ids = [r[0] for r in c.execute("SELECT id FROM runs WHERE status = 'running'")]
            now = utc_now()
            for run_id in ids:
                c.execute("UPDATE runs SET status = 'interrupted', verdict = 'interrupted', "
                          "reason = ?, ended_at = ? WHERE id = ?", (reason, now, run_id))
                c.execute("INSERT INTO events(run_id, t, level, msg) VALUES (?, ?, ?, ?)",
                          (run_id, now, "error", f"marked interrupted at start-up: {reason}"))
            return ids

        ids = self._write_end("interrupted runs", fn)
        for run_id in ids:
            log.warning("run %d was left running by a previous daemon: marked interrupted",
                        run_id)
        return ids

    def start_run(self, kind: str, *, started_by: str, software_version: str,
                  config_hash: str, config_json: str, user: str | None = None,
                  uid: int | None = None, devices: Any = None) -> int:
        if kind not in RUN_KINDS:
            raise StoreError(f"unknown run kind {kind!r} (expected one of {RUN_KINDS})")
        return self._write("the start of a run", lambda c: c.execute(
            "INSERT INTO runs(kind, status, started_at, started_by, user, uid, software_version,"
            " config_hash, config_json, devices_json) VALUES (?, 'running', ?, ?, ?, ?, ?, ?, ?,"
            " ?)", (kind, utc_now(), started_by, user, uid, software_version, config_hash,
                    config_json, None if devices is None else dumps(devices))).lastrowid)

    def set_devices(self, run_id: int, devices: Any) -> None:
        self._write("device identities", lambda c: c.execute(
            "UPDATE runs SET devices_json = ? WHERE id = ?", (dumps(devices), run_id)))

    def finish_run(self, run_id: int, *, verdict: str, reason: str | None,
                   result: Any, details: Any = None) -> None:
        """Record the outcome (``result``: the run-result contract object; ``details``: the
        procedure's full record). A run is finished once, and never after being
        interrupted."""

        def record(details: Any, reason: str | None) -> Any:
            def fn(c: sqlite3.Connection) -> None:
                cur = c.execute(
                    "UPDATE runs SET status = 'finished', ended_at = ?, verdict = ?, reason = ?,"
                    " result_json = ?, details_json = ? WHERE id = ? AND status = 'running'",
                    (utc_now(), verdict, reason, None if result is None else dumps(result),
                     None if details is None else dumps(details), run_id))
                if cur.rowcount != 1:
                    raise StoreError(f"{self.db_path}: run {run_id} is not running; "
                                     "its outcome was not recorded")
            return fn

        try:
            self._write_end(f"the end of run {run_id}", record(details, reason))
        except StoreError as exc:
            if not exc.disk_full or details is None:
                raise
            # even the reserve was not enough for the full record: keep verdict and reason
            self._write(f"the end of run {run_id}", record(
                None, f"{reason or verdict} (the run's details were not recorded: disk full)"))

    def add_sweep(self, run_id: int, kind: str, iteration: int | None, sweep: Any,
                  commanded: Any = None, readback: Any = None) -> int:
        return self._write("a sweep", lambda c: c.execute(
            "INSERT INTO sweeps(run_id, t, kind, iteration, sweep_json, commanded_json,"
            " readback_json) VALUES (?, ?, ?, ?, ?, ?, ?)",
            (run_id, utc_now(), kind, iteration, dumps(sweep),
             None if commanded is None else dumps(commanded),
             None if readback is None else dumps(readback))).lastrowid)

    def add_iteration(self, run_id: int, n: int, record: Any) -> int:
        return self._write("an iteration", lambda c: c.execute(
            "INSERT INTO iterations(run_id, t, n, record_json) VALUES (?, ?, ?, ?)",
            (run_id, utc_now(), int(n), dumps(record))).lastrowid)

    def add_event(self, run_id: int | None, msg: str, level: str = "info") -> int:
        return self._write("an event", lambda c: c.execute(
            "INSERT INTO events(run_id, t, level, msg) VALUES (?, ?, ?, ?)",
            (run_id, utc_now(), level, str(msg))).lastrowid)

    def frame_path(self, digest: str) -> Path:
        return self.frames_dir / digest[:2] / f"{digest}.png"

    def save_frame(self, run_id: int, image: np.ndarray, label: str,
                   keep_file: bool = True) -> str:
        """Store a frame as ``frames/ab/abcd....png`` and return its hash (SHA-256 of shape,
        dtype and pixels: ``image_hash``, the name every recorder gives a frame, so it does
        not depend on the PNG encoder). The file is durable before the row naming it."""
        digest = image_hash(image)
        path = self.frame_path(digest)
        try:
            if keep_file and not path.exists():
                path.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_bytes(path, encode_png(image))
        except OSError as exc:
            err = StoreError(f"{path}: cannot save a frame: {exc.strerror or exc}")
            err.disk_full = _is_full(exc)
            raise err from None
        h, w = image.shape[:2]
        self._write("a frame", lambda c: c.execute(
            "INSERT INTO frames(run_id, t, label, hash, width, height) VALUES (?, ?, ?, ?, ?, ?)",
            (run_id, utc_now(), str(label), digest, w, h)))
        return digest

    # ---- reads ------------------------------------------------------------------------
    @staticmethod
    def _summary(row: sqlite3.Row) -> dict[str, Any]:
        result = _loads(row["result_json"]) or {}
        return {
            "id": row["id"], "kind": row["kind"], "status": row["status"],
            "started_at": row["started_at"], "ended_at": row["ended_at"],
            "started_by": row["started_by"], "user": row["user"],
            "verdict": row["verdict"], "reason": row["reason"],
            "offset_norm_um": result.get("offset_norm_um"), "U_um": result.get("U_um"),
            "iterations": result.get("iterations"),
        }

    def list_runs(self, limit: int = 20) -> list[dict[str, Any]]:
        """The newest ``limit`` runs, newest first, as summaries."""
        with self._reader() as conn:
            rows = conn.execute("SELECT * FROM runs ORDER BY id DESC LIMIT ?",
                                (max(0, int(limit)),)).fetchall()
        return [self._summary(r) for r in rows]

    def get_run(self, run_id: int) -> dict[str, Any] | None:
        """Everything recorded about one run, or ``None`` if there is no such run."""
        with self._reader() as conn:
            row = conn.execute("SELECT * FROM runs WHERE id = ?", (run_id,)).fetchone()
            if row is None:
                return None
            run = self._summary(row)
            run.update({
                "software_version": row["software_version"],
                "config_hash": row["config_hash"],
                "config": _loads(row["config_json"]),
                "devices": _loads(row["devices_json"]),
                "uid": row["uid"],
                "result": _loads(row["result_json"]),
                "details": _loads(row["details_json"]),
            })
            run["sweeps"] = [
                {"id": s["id"], "t": s["t"], "kind": s["kind"], "iteration": s["iteration"],
                 "sweep": _loads(s["sweep_json"]), "commanded": _loads(s["commanded_json"]),
                 "readback": _loads(s["readback_json"])}
                for s in conn.execute("SELECT * FROM sweeps WHERE run_id = ? ORDER BY id",
                                      (run_id,))]
            run["iteration_records"] = [
                {"n": i["n"], "t": i["t"], **(_loads(i["record_json"]) or {})}
                for i in conn.execute("SELECT * FROM iterations WHERE run_id = ? ORDER BY id",
                                      (run_id,))]
            run["events"] = [dict(e) for e in conn.execute(
                "SELECT id, t, level, msg FROM events WHERE run_id = ? ORDER BY id", (run_id,))]
            run["frames"] = [dict(f) for f in conn.execute(
                "SELECT t, label, hash, width, height FROM frames WHERE run_id = ? ORDER BY id",
                (run_id,))]
        return run

    def run_status(self, run_id: int) -> tuple[str, str | None] | None:
        """(status, verdict) of a run, cheaply; ``None`` if unknown."""
        with self._reader() as conn:
            row = conn.execute("SELECT status, verdict FROM runs WHERE id = ?",
                               (run_id,)).fetchone()
        return None if row is None else (row[0], row[1])

    def result(self, run_id: int) -> Any:
        with self._reader() as conn:
            row = conn.execute("SELECT result_json FROM runs WHERE id = ?", (run_id,)).fetchone()
        return None if row is None else _loads(row[0])


class SqliteRecorder:
    """The procedures' ``RunRecorder``, writing one run's raw data into the ``Store``.

    ``on_write`` is called after each record (the daemon uses it for watchdog pings and to
    mirror events into the live progress stream).
    """

    def __init__(self, store: Store, run_id: int, *,
                 on_event: Any = None, on_write: Any = None,
                 keep_frame: Any = None) -> None:
        """``keep_frame(label) -> bool``: which frames are stored as files (default all;
        the hash of every frame is recorded regardless)."""
        self.store = store
        self.run_id = run_id
        self._keep_frame = keep_frame
        self._on_event = on_event
        self._on_write = on_write

    def _touched(self) -> None:
        if self._on_write is not None:
            self._on_write()

    def sweep(self, kind: str, iteration: int | None, sweep_json: Any, commanded: Any,
              readback: Any) -> None:
        if isinstance(sweep_json, str):
            sweep_json = json.loads(sweep_json)
        self.store.add_sweep(self.run_id, kind, iteration, sweep_json, commanded, readback)
        self._touched()

    def iteration(self, n: int, record: Any) -> None:
        self.store.add_iteration(self.run_id, n, record)
        self._touched()

    def frame(self, image: Any, label: str) -> str:
        arr = getattr(image, "image", image)  # a drivers.camera.Frame or a bare array
        keep = self._keep_frame is None or bool(self._keep_frame(label))
        digest = self.store.save_frame(self.run_id, np.asarray(arr), label, keep_file=keep)
        self._touched()
        return digest

    def event(self, msg: str, level: str = "info") -> None:
        self.store.add_event(self.run_id, msg, level)
        if self._on_event is not None:
            self._on_event(msg, level)
        self._touched()

