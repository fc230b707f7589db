"""Schema 1 -> 2: the runs table admits the kind 'commission'; old runs and their sweeps stay."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from alignd import store as store_mod
from alignd.store import Store, StoreError


def _v1_database(path: Path) -> None:
    """A history database exactly as schema 1 created it, with one align run and a sweep."""
    schema = store_mod._SCHEMA.replace("CHECK (kind IN ('align', 'check', 'commission'))",
                                       "CHECK (kind IN ('align', 'check'))")
    assert schema != store_mod._SCHEMA
    path.parent.mkdir(parents=True)
    conn = sqlite3.connect(path)
    conn.executescript(schema)
    conn.execute("INSERT INTO runs(kind, status, started_at, started_by, software_version, "
                 "config_hash, config_json, verdict) VALUES ('align', 'finished', "
                 "'2026-01-01T00:00:00.000Z', 'user', '0.1', 'abc', '{}', 'aligned')")
    conn.execute("INSERT INTO sweeps(run_id, t, kind, sweep_json) VALUES (1, 't', 'align', '{}')")
    conn.execute("PRAGMA user_version=1")
    conn.commit()
    with pytest.raises(sqlite3.IntegrityError):  # schema 1 refuses the new kind
        conn.execute("INSERT INTO runs(kind, status, started_at, started_by, software_version,"
                     " config_hash, config_json) VALUES ('commission', 'running', 't', 'user',"
                     " '0.1', 'abc', '{}')")
    conn.close()


def test_schema_1_is_migrated_keeping_runs_and_sweeps(tmp_path: Path) -> None:
    state = tmp_path / "state"
    _v1_database(state / store_mod.DB_NAME)
    st = Store(state).open()
    try:
        conn = sqlite3.connect(state / store_mod.DB_NAME)
        assert conn.execute("PRAGMA user_version").fetchone()[0] == 2
        assert conn.execute("SELECT COUNT(*) FROM sweeps WHERE run_id = 1").fetchone()[0] == 1
        assert conn.execute("PRAGMA foreign_key_check").fetchall() == []
        conn.close()
        assert st.get_run(1)["verdict"] == "aligned"
        rid = st.start_run("commission", started_by="user", software_version="0.2",
                           config_hash="abc", config_json="{}")
        assert rid == 2  # AUTOINCREMENT carried over
        st.finish_run(rid, verdict="commissioned", reason=None, result={"x": 1}, details=None)
        last = st.latest_run("commission")
        assert last is not None and last["id"] == 2 and last["result"] == {"x": 1}
        with pytest.raises(StoreError, match="unknown run kind"):
            st.start_run("calibrate", started_by="user", software_version="0.2",
                         config_hash="abc", config_json="{}")
    finally:
        st.close()
