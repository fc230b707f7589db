"""The run history: a real SQLite file, crash-safety, interrupted runs, frames by hash."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from alignd.procedures.recorder import RunRecorder, image_hash
from alignd.store import (
    INTERRUPTED_REASON,
    SCHEMA_VERSION,
    SqliteRecorder,
    Store,
    StoreError,
    atomic_write_bytes,
    jsonable,
)

CFG_JSON = '{"version": 1}'


def _start(store: Store, kind: str = "align") -> int:
    return store.start_run(kind, started_by="user", software_version="9.9", config_hash="abc",
                           config_json=CFG_JSON, user="alice", uid=1000,
                           devices={"x": {"serial": "S1"}})


@pytest.fixture
def store(tmp_path: Path) -> Store:
    s = Store(tmp_path / "state").open()
    yield s
    s.close()


def test_new_database_is_wal_full_sync_and_versioned(store: Store) -> None:
    conn = sqlite3.connect(store.db_path)
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert conn.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    conn.close()
    # synchronous is per connection: the store's own writer must use FULL (2)
    assert store._conn.execute("PRAGMA synchronous").fetchone()[0] == 2
    assert store.integrity_check() == ["ok"]


def test_run_round_trip_with_raw_data_and_frames(store: Store) -> None:
    run_id = _start(store)
    rec = SqliteRecorder(store, run_id)
    assert isinstance(rec, RunRecorder)
    sweep = {"version": 1, "pixel_size_um": 160.0,
             "frames": [{"angle_deg": -10.0, "features": [[1.5, 2.5], None]},
                        {"angle_deg": 10.0, "features": [[3.0, np.float64(4.0)], [5, 6]]}]}
    rec.sweep("measure", 1, sweep, [-10.0, 10.0], np.array([-9.999, 10.002]))
    rec.iteration(1, {"offset_um": np.array([12.5, -3.0]), "U_um": np.float32(2.5),
                      "bad": float("nan")})
    img = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
    digest = rec.frame(img, "measure-1-000")
    rec.event("homed: x")
    store.finish_run(run_id, verdict="aligned", reason=None,
                     result={"verdict": "aligned", "offset_norm_um": 4.2, "U_um": 1.1},
                     details={"calibration": [[1, 0], [0, 1]]})

    run = store.get_run(run_id)
    assert run["status"] == "finished" and run["verdict"] == "aligned"
    assert run["user"] == "alice" and run["started_by"] == "user"
    assert run["software_version"] == "9.9" and run["config_hash"] == "abc"
    assert run["config"] == {"version": 1} and run["devices"] == {"x": {"serial": "S1"}}
    assert run["sweeps"][0]["sweep"]["frames"][0]["features"] == [[1.5, 2.5], None]
    assert run["sweeps"][0]["readback"] == [-9.999, 10.002]
    assert run["iteration_records"][0]["offset_um"] == [12.5, -3.0]
    assert run["iteration_records"][0]["bad"] is None  # NaN stored as null, JSON stays strict
    assert [e["msg"] for e in run["events"]] == ["homed: x"]
    assert run["details"] == {"calibration": [[1, 0], [0, 1]]}
    assert run["frames"][0]["hash"] == digest == image_hash(img)
    # the frame file is named by its hash and holds exactly the pixels
    path = store.frame_path(digest)
    assert path.name == f"{digest}.png"
    assert np.array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), img)
    assert store.list_runs(5)[0]["offset_norm_um"] == 4.2


def test_runs_left_running_are_marked_interrupted_on_reopen(tmp_path: Path) -> None:
    s = Store(tmp_path).open()
    done = _start(s)
    s.finish_run(done, verdict="aligned", reason=None, result={"verdict": "aligned"})
    cut_off = _start(s, "check")
    s.close()  # the daemon "died" here: no finish_run for cut_off

    s2 = Store(tmp_path).open()
    assert s2.mark_interrupted() == [cut_off]
    run = s2.get_run(cut_off)
    assert run["status"] == "interrupted" and run["verdict"] == "interrupted"
    assert run["reason"] == INTERRUPTED_REASON and run["ended_at"]
    assert s2.get_run(done)["verdict"] == "aligned"
    # an interrupted run never gets a late outcome, and a second start marks nothing
    with pytest.raises(StoreError, match=f"run {cut_off} is not running"):
        s2.finish_run(cut_off, verdict="aligned", reason=None, result={})
    assert s2.mark_interrupted() == []
    s2.close()


def test_failed_record_write_leaves_nothing_behind(store: Store) -> None:
    with pytest.raises(StoreError, match="cannot record an iteration"):
        store.add_iteration(12345, 1, {"x": 1})  # no such run: foreign key violation
    conn = sqlite3.connect(store.db_path)
    assert conn.execute("SELECT COUNT(*) FROM iterations").fetchone()[0] == 0
    conn.close()


def test_full_disk_refuses_new_runs(store: Store) -> None:
    _start(store)
    pages = store._conn.execute("PRAGMA page_count").fetchone()[0]
    store._conn.execute(f"PRAGMA max_page_count={pages}")  # the database cannot grow: SQLITE_FULL
    filler = "x" * 200_000
    with pytest.raises(StoreError, match=r"history\.sqlite3.*full"):
        store.add_event(None, filler)
    with pytest.raises(StoreError, match="full"):
        store.start_run("align", started_by="user", software_version="1", config_hash="h",
                        config_json=filler)


def test_newer_schema_is_refused(tmp_path: Path) -> None:
    Store(tmp_path).open().close()
    conn = sqlite3.connect(tmp_path / "history.sqlite3")
    conn.execute(f"PRAGMA user_version={SCHEMA_VERSION + 1}")
    conn.close()
    with pytest.raises(StoreError, match="newer than this alignd"):
        Store(tmp_path).open()


def test_unwritable_state_dir_is_a_store_error(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(StoreError, match="cannot open the history database"):
        Store(blocker / "state").open()


def test_jsonable_gives_strict_json() -> None:
    obj = {"a": np.array([[1.0, np.inf]]), "b": (np.int64(3), None), "c": {1: np.bool_(True)}}
    assert json.loads(json.dumps(jsonable(obj), allow_nan=False)) == {
        "a": [[1.0, None]], "b": [3, None], "c": {"1": True}}


def test_atomic_write_replaces_whole_file(tmp_path: Path) -> None:
    target = tmp_path / "r.json"
    atomic_write_bytes(target, b"old")
    atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"new"
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temp files left


_WRITER = r"""
import sys
from alignd.store import Store, SqliteRecorder
s = Store(sys.argv[1]).open()
n = 0
while True:
    rid = s.start_run("check", started_by="timer", software_version="1", config_hash="h",
                      config_json="{}")
    rec = SqliteRecorder(s, rid)
    for i in range(5):
        rec.sweep("measure", i, {"version": 1, "frames": [{"angle_deg": 0.0,
                  "features": [[float(i), 2.0]] * 50}]}, [0.0], [0.0])
        rec.iteration(i, {"offset_um": [i, i]})
    s.finish_run(rid, verdict="within_tolerance", reason=None, result={"i": 5})
    n += 1
    if n == 3:
        print("ready", flush=True)
"""


def test_sigkill_during_writes_leaves_a_consistent_database(tmp_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp_path)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.05 + (os.getpid() % 7) / 100)  # somewhere inside the write loop
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    s = Store(tmp_path).open()
    assert s.integrity_check() == ["ok"]
    interrupted = s.mark_interrupted()
    assert len(interrupted) <= 1  # at most the run being written when killed
    for summary in s.list_runs(1000):
        run = s.get_run(summary["id"])
        if run["status"] == "finished":
            # a finished run has all of its records: each was committed before the end
            assert len(run["sweeps"]) == 5 and len(run["iteration_records"]) == 5
        else:
            assert run["id"] in interrupted
        for sw in run["sweeps"]:  # no half-written record: every document parses whole
            assert len(sw["sweep"]["frames"][0]["features"]) == 50
    s.close()


def test_nearly_full_disk_fails_the_write_probe(store: Store) -> None:
    store.check_writable()
    store.min_free_bytes = 2**62
    with pytest.raises(StoreError, match="disk nearly full"):
        store.check_writable()


@pytest.mark.parametrize(("mode", "kept"), [("all", 9), ("report", 3), ("none", 0)])
def test_keep_frames_policy_records_every_hash_but_files_per_policy(
        store: Store, mode: str, kept: int) -> None:
    import yaml

    from alignd.config import frame_keeper, parse_config

    root = Path(__file__).resolve().parent.parent
    data = yaml.safe_load((root / "configs" / "sim.yaml").read_text())
    data["daemon"]["keep_frames"] = mode
    data["procedure"].update(sweep_deg=10.0, sweep_steps=3)  # steps at -10, 0, +10 deg
    rec = SqliteRecorder(store, _start(store), keep_frame=frame_keeper(parse_config(data)))
    labels = ["precheck-side-000", "precheck-side-001", "calibration-x-001", "align-1-000-0",
              "align-1-001-0", "align-1-001-1", "align-1-002-0", "verify-2-001-0",
              "verify-2-002-0"]
    digests = []
    for i, label in enumerate(labels):
        img = np.full((8, 8), i * 10, np.uint8)
        digests.append(rec.frame(img, label))
    on_disk = [d for d in digests if store.frame_path(d).exists()]
    assert len(on_disk) == kept
    if mode == "report":  # the 0-degree frame of each sweep and the first side frame: the
        # ones the report draws on
        assert on_disk == [digests[0], digests[4], digests[7]]
    run = store.get_run(rec.run_id)
    assert [f["hash"] for f in run["frames"]] == digests  # every hash is recorded anyway
