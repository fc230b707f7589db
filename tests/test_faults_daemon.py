"""Issue 6, scenarios 15-22: the daemon under abort, SIGTERM and SIGKILL mid-move, kills
during database commits and report writes, a full disk or read-only database, concurrent
and hostile API clients, scheduled checks while busy or faulted, and a bounded soak.

All but two scenarios run the real ``alignd`` as a subprocess on the simulated rig
(``faults_support``); every run's end state is checked the same way."""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from daemon_fakes import as_observer
from faults_support import (
    DaemonProc,
    assert_end_state,
    log_lines,
    short_tmp,
    sim_daemon,
    soft_limit_violations,
    targets,
    thread_count,
    threads_settled,
)

from alignd.cli import main as alignctl
from alignd.client import ApiError
from alignd.store import Store, StoreError

SLOW = 10.0  # time scale at which homing the platform takes a few seconds: "mid-move"


def wait_moving(dp: DaemonProc, timeout_s: float = 20.0) -> str:
    """Wait until some simulated axis is moving; return its role."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        moving = [r for r, s in dp.snapshot().items() if s["moving"]]
        if moving:
            return moving[0]
        time.sleep(0.01)
    raise AssertionError(f"no axis started moving; daemon status: {dp.client.status()}")


# ---- 15. abort and SIGTERM mid-move; 16. SIGKILL mid-run, then restart ---------------------------
def test_abort_sigterm_and_sigkill_mid_move() -> None:
    with sim_daemon(time_scale=SLOW) as dp:
        # alignctl abort while a stage moves
        run_id = dp.client.start("align")["run_id"]
        role = wait_moving(dp)
        t0 = time.monotonic()
        assert alignctl(["--socket", str(dp.sock), "abort"]) == 0
        run = dp.wait_run(run_id)
        assert time.monotonic() - t0 < 3.0
        assert_end_state(dp, run, verdicts=["aborted"], reason_has=["aborted by root"])
        events = " ".join(e["msg"] for e in run["events"])
        assert "positions after stop" in events and f"{role}=" in events
        assert dp.client.status()["state"] == "idle"

        # SIGTERM while a stage moves: every axis stopped, recorded, exit within the timeout
        run_id = dp.client.start("align")["run_id"]
        wait_moving(dp)
        t0 = time.monotonic()
        assert dp.terminate() == 0
        assert time.monotonic() - t0 < 5.0  # --stop-timeout 5
        final = [r for r in log_lines(dp.target_log) if r["event"] == "final"
                 and r["pid"] == dp.pid]
        assert len(final) == 5 and not any(r["moving"] for r in final), final
        store = Store(dp.state)
        run = store.get_run(run_id)
        assert run["verdict"] == "aborted" and "SIGTERM" in run["reason"]
        assert store.integrity_check() == ["ok"]

        # SIGKILL mid-move, then a restart: interrupted, no motion on its own, database sound
        dp.start()
        run_id = dp.client.start("align")["run_id"]
        wait_moving(dp)
        dp.kill()
        first_pid = dp.pid
        dp.start()
        runs = dp.client.history()
        assert runs[0]["id"] == run_id and runs[0]["status"] == "interrupted"
        assert "SIGKILL" in runs[0]["reason"] or "crash" in runs[0]["reason"]
        time.sleep(0.5)  # give a wrongly resumed run the chance to move something
        assert targets(dp.target_log, dp.pid) == []  # nothing moved on its own
        assert not any(s["moving"] for s in dp.snapshot().values())
        assert Store(dp.state).integrity_check() == ["ok"]
        assert first_pid != dp.pid
        run = dp.run_and_wait("check")  # and it works normally again
        assert_end_state(dp, run, verdicts=["within_tolerance", "out_of_tolerance"])


# ---- 17. kill during a database commit or a report write ------------------------------------
_WRITER = r"""
import sys, numpy as np
from alignd.store import Store, SqliteRecorder
from alignd.report import write_report
from pathlib import Path
store = Store(sys.argv[1]).open()
out = Path(sys.argv[2])
rng = np.random.default_rng(int(sys.argv[3]))
print("ready", flush=True)
n = 0
while True:
    n += 1
    run = store.start_run("check", started_by="timer", software_version="t",
                          config_hash="h", config_json="{}")
    rec = SqliteRecorder(store, run)
    for k in range(3):
        rec.sweep("check", k, {"version": 1, "pixel_size_um": 160.0, "frames": []}, [k], [k])
        rec.frame(rng.integers(0, 255, (120, 160), dtype=np.uint8), f"f{k}")
        rec.event(f"event {k}")
    v = ["within_tolerance", "out_of_tolerance"][n % 2]
    store.finish_run(run, verdict=v, reason=None, result={"verdict": v, "n": n})
    write_report({"id": 1, "kind": "check", "verdict": v, "result": {"verdict": v}}, out,
                 rng.integers(0, 255, (360, 640), dtype=np.uint8))
"""


@pytest.mark.parametrize("seed", [1, 2])
def test_kill_during_commit_or_report_write_leaves_everything_consistent(seed: int) -> None:
    tmp = short_tmp()
    try:
        proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(tmp / "state"),
                                 str(tmp / "rep"), str(seed)], stdout=subprocess.PIPE,
                                text=True)
        (tmp / "rep").mkdir()
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.2 + random.Random(seed).random() * 0.5)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        store = Store(tmp / "state").open()
        try:
            assert store.integrity_check() == ["ok"]
            cut = store.mark_interrupted()
            assert len(cut) <= 1  # at most the run being written
            runs = store.list_runs(1000)
            assert runs and all(r["status"] in ("finished", "interrupted") for r in runs)
            for r in runs:
                full = store.get_run(r["id"])
                if r["status"] == "finished":  # a finished run has all of its records
                    assert len(full["sweeps"]) == 3 and len(full["frames"]) == 3
                    assert full["result"]["verdict"] == r["verdict"]
                for f in full["frames"]:  # no row names a frame file that is not there
                    assert store.frame_path(f["hash"]).stat().st_size > 0
        finally:
            store.close()
        png, js = tmp / "rep" / "run-1.png", tmp / "rep" / "run-1.json"
        if png.exists():  # wholly old or new
            assert png.read_bytes()[-8:] == b"IEND\xaeB`\x82"
        if js.exists():  # written last: a report with its JSON is complete
            rec = json.loads(js.read_text())
            assert rec["verdict"] in ("within_tolerance", "out_of_tolerance")
            assert png.exists()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ---- 18. a read-only database (the store on its own) -----------------------------------------
def test_read_only_database_refuses_new_runs() -> None:
    import sqlite3

    tmp = short_tmp()
    try:
        store = Store(tmp / "state").open()
        run = store.start_run("check", started_by="user", software_version="t",
                              config_hash="h", config_json="{}")
        store.finish_run(run, verdict="within_tolerance", reason=None, result={})
        store._conn.close()  # the file system was remounted read-only under the daemon
        store._conn = sqlite3.connect(f"{store.db_path.as_uri()}?mode=ro", uri=True,
                                      isolation_level=None, check_same_thread=False)
        with pytest.raises(StoreError, match="readonly"):
            store.check_writable()
        with pytest.raises(StoreError, match="cannot record the start of a run"):
            store.start_run("check", started_by="user", software_version="t",
                            config_hash="h", config_json="{}")
        assert [r["id"] for r in store.list_runs()] == [run]
        assert store.integrity_check() == ["ok"]
        store.close()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ---- 18-21 on one daemon: a full disk; concurrent, hostile and scheduled clients -----------
@pytest.fixture(scope="module")
def busy_daemon() -> Iterator[DaemonProc]:
    """A daemon whose moves take a while (time scale 10), which only root may control, with
    a short API request deadline and a disk that fills up on demand (test-only hooks)."""
    flag_dir = short_tmp()
    env = {"FAULTS_REQUEST_TIMEOUT_S": "1.0", "FAULTS_DISK_FULL_FLAG": str(flag_dir / "full")}
    with sim_daemon(time_scale=SLOW, env=env,
                    daemon={"socket": "/run/alignd/alignd.sock",
                            "operator_group": "alignd-no-such-group"}) as dp:
        dp.disk_full_flag = flag_dir / "full"  # type: ignore[attr-defined]
        yield dp
    shutil.rmtree(flag_dir, ignore_errors=True)


# ---- 18. disk full or database read-only ----------------------------------------------------
def test_full_disk_refuses_new_runs_and_nothing_moves(busy_daemon: DaemonProc,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    dp = busy_daemon
    flag: Path = dp.disk_full_flag  # type: ignore[attr-defined]
    n0, t0 = len(dp.client.history(1000)), len(targets(dp.target_log))
    flag.touch()
    try:
        assert alignctl(["--socket", str(dp.sock), "align"]) == 3
        err = capsys.readouterr().err
        assert "could not be recorded" in err and "disk nearly full" in err
        assert alignctl(["--socket", str(dp.sock), "check", "--started-by", "timer"]) == 3
        assert len(dp.client.history(1000)) == n0 and len(targets(dp.target_log)) == t0
        assert dp.client.status()["state"] == "idle"  # not faulted: the hardware is fine
    finally:
        flag.unlink()
    run = dp.run_and_wait("check")
    assert_end_state(dp, run, verdicts=["within_tolerance", "out_of_tolerance"])




def test_second_align_and_observer_control_are_refused_status_works(
        busy_daemon: DaemonProc, capsys: pytest.CaptureFixture[str]) -> None:
    dp = busy_daemon
    run_id = dp.client.start("align")["run_id"]
    wait_moving(dp)
    with pytest.raises(ApiError) as info:
        dp.client.start("align")
    assert info.value.status == 409 and info.value.code == "busy"
    assert alignctl(["--socket", str(dp.sock), "align"]) == 3
    assert f"busy: run {run_id}" in capsys.readouterr().err
    if os.getuid() == 0:  # the observer is a real other user
        (s_code, st), (a_code, a), (x_code, x), (r_code, r) = as_observer(
            dp.sock, [("GET", "/status", ""), ("POST", "/align", "{}"),
                      ("POST", "/abort", "{}"), ("POST", "/reset", "{}")])
        assert s_code == 200 and st["state"] == "aligning" and st["run_id"] == run_id
        assert (a_code, x_code, r_code) == (403, 403, 403)
        assert a["error"] == x["error"] == r["error"] == "forbidden"
    st = dp.client.status()
    assert st["state"] == "aligning" and st["run_id"] == run_id  # the run goes on
    dp.client.abort()
    run = dp.wait_run(run_id)
    assert_end_state(dp, run, verdicts=["aborted"])
    assert next(r["id"] for r in dp.client.history()) == run_id


def _fuzz_one(path: str, rng: random.Random) -> bytes:
    """One hostile request; returns what the daemon answered (b"" if it just closed)."""
    kind = rng.choice(["bytes", "line", "header", "length", "json", "method", "stall"])
    paths = ["/status", "/align", "/check", "/abort", "/reset", "/runs/1", "/history?limit=x",
             "/frames/zz", "/" + "a" * rng.randint(1, 5000), "/runs/1/events?wait=nan"]
    if kind == "bytes":
        data = bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 3000)))
    elif kind == "line":
        data = f"GET {rng.choice(paths)} HTTP/1.1\r\n\r\n".encode()  # reads only
    elif kind == "header":
        data = b"GET /status HTTP/1.1\r\nX: " + b"y" * rng.randint(70000, 200000) + b"\r\n\r\n"
    elif kind == "length":
        data = (f"POST /check HTTP/1.1\r\nContent-Length: {rng.choice([-1, 10**9, 'x'])}"
                "\r\n\r\n{}").encode()
    elif kind == "json":
        body = rng.choice([b"{", b"[]", b"\xff\xfe", b'{"started_by": "DROP TABLE"}',
                           b'{"started_by": 7}', b"null"])
        data = (f"POST {rng.choice(['/align', '/check'])} HTTP/1.1\r\nContent-Length: "
                f"{len(body)}\r\n\r\n").encode() + body
    elif kind == "method":
        data = f"{rng.choice(['PUT', 'DELETE', 'BREW', 'G ET'])} /status HTTP/1.1\r\n\r\n".encode()
    else:
        data = b"POST /align HTTP/1.1\r\nContent-Length: 100\r\n\r\n{"  # and then nothing
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(5.0)
    out = b""
    try:
        s.connect(path)
        s.sendall(data)
        while chunk := s.recv(65536):
            out += chunk
    except (ConnectionError, TimeoutError, OSError):
        pass
    finally:
        s.close()
    return out


def test_fuzzed_requests_get_errors_and_leave_the_daemon_and_its_run_alone(
        busy_daemon: DaemonProc) -> None:
    dp = busy_daemon
    threads0 = thread_count(dp.pid)
    runs0 = len(dp.client.history(1000))
    run_id = dp.client.start("check")["run_id"]
    rng = random.Random(20)
    answers: list[bytes] = []

    def fuzz(k: int) -> None:
        r = random.Random(rng.random() + k)
        for _ in range(10):
            answers.append(_fuzz_one(str(dp.sock), r))
            st = dp.client.status()  # status keeps answering throughout
            assert st["state"] in ("checking", "idle")

    workers = [threading.Thread(target=fuzz, args=(k,)) for k in range(4)]
    for w in workers:
        w.start()
    for w in workers:
        w.join(timeout=60)
    run = dp.wait_run(run_id)
    assert_end_state(dp, run, verdicts=["within_tolerance", "out_of_tolerance"])
    assert len(answers) == 40
    replied = [a for a in answers if a]
    assert replied and all(a.startswith(b"HTTP/1.") for a in replied)
    assert not [a for a in replied if a.split(b"\r\n")[0].endswith(b"500 Internal Server Error")]
    assert not [a for a in replied if a.split(b" ")[1] == b"202"]  # nothing was started
    assert len(dp.client.history(1000)) == runs0 + 1  # only the check we started
    # the cut stalled connections' threads end
    assert threads_settled(dp.pid, threads0 + 1) <= threads0 + 1


def test_scheduled_check_while_busy_is_skipped(busy_daemon: DaemonProc,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    dp = busy_daemon
    n0 = len(dp.client.history(1000))
    run_id = dp.client.start("align")["run_id"]
    wait_moving(dp)
    assert alignctl(["--socket", str(dp.sock), "check", "--started-by", "timer"]) == 75
    assert "skipped" in capsys.readouterr().err
    dp.client.abort()
    dp.wait_run(run_id)
    assert len(dp.client.history(1000)) == n0 + 1  # the skipped check left no run behind


# ---- 22. soak (bounded here; the full 200 checks are bench/soak.py) -------------------------
SOAK_FAULTS = [{"device": d, "kind": k, "probability": p, "count": 0}
               for d in ("turntable", "translator", "platform")
               for k, p in (("garbled", 0.005), ("truncated", 0.005), ("bad_checksum", 0.005),
                            ("no_reply", 0.002))]


def proc_usage(pid: int) -> dict[str, int]:
    """RSS (kB), threads and open file descriptors of a process."""
    rss = next(int(ln.split()[1]) for ln in Path(f"/proc/{pid}/status").read_text()
               .splitlines() if ln.startswith("VmRSS:"))
    return {"rss_kb": rss, "threads": len(os.listdir(f"/proc/{pid}/task")),
            "fds": len(os.listdir(f"/proc/{pid}/fd"))}


def soak(dp: DaemonProc, n: int, reasons: list[str] | None = None) -> dict[str, int]:
    """``n`` checks back to back; a fault is reset and the next check goes on. The reasons
    of faulted runs and failed resets are appended to ``reasons`` when given."""
    verdicts: dict[str, int] = {}
    for _ in range(n):
        st = dp.wait_state("idle", "fault")
        if st["state"] == "fault":
            dp.client.reset()
            dp.wait_state("idle", "fault")
            st = dp.client.status()
            if st["state"] != "idle":
                verdicts["reset_failed"] = verdicts.get("reset_failed", 0) + 1
                if reasons is not None:
                    reasons.append(f"reset: {st.get('fault')}")
                continue
        run = dp.run_and_wait("check", timeout_s=60)
        verdicts[run["verdict"]] = verdicts.get(run["verdict"], 0) + 1
        if reasons is not None and run["verdict"] == "fault":
            reasons.append(str(run["reason"]))
    return verdicts


def test_soak_checks_with_random_faults_leak_nothing_and_record_every_run() -> None:
    with sim_daemon(faults=SOAK_FAULTS, procedure={"sweep_steps": 5, "sweep_deg": 5.0,
                                                   "max_iterations": 1},
                    reply_timeout_s=0.15) as dp:
        soak(dp, 2)  # warm-up: imports, caches, first homing
        dp.wait_state("idle", "fault")
        time.sleep(0.3)  # the API thread of that status request has ended
        before = proc_usage(dp.pid)
        n = 8
        verdicts = soak(dp, n)
        dp.wait_state("idle", "fault")
        threads_settled(dp.pid, before["threads"] + 1)  # the last requests' threads end
        after = proc_usage(dp.pid)
        runs = dp.client.history(1000)
        assert len(runs) == n + 2 - verdicts.get("reset_failed", 0)
        assert all(r["status"] == "finished" and r["verdict"] for r in runs)
        assert all(r["reason"] for r in runs if r["verdict"] == "fault")
        assert after["threads"] <= before["threads"] + 1  # (+1: a request in flight)
        assert after["fds"] <= before["fds"] + 2
        assert after["rss_kb"] - before["rss_kb"] < 30_000
        assert Store(dp.state).integrity_check() == ["ok"]
        assert soft_limit_violations(dp.target_log, dp.cfg) == []
        assert sum(verdicts.values()) == n
