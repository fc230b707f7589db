"""Connection admission (issue 9): one local user cannot take the slots root needs for
``status`` and ``abort``; refusals cannot flood the log; a burst of connects is queued;
the client retries a refused connect and shows the daemon's 503 message."""

from __future__ import annotations

import logging
import os
import socket
import threading
from collections.abc import Iterator

import pytest
from daemon_fakes import Env, Holder, make_env, short_tmp, wait_until

from alignd.admission import Admission, Limits, RefusalLog
from alignd.api import ApiServer, Authoriser
from alignd.cli import main as alignctl
from alignd.client import ApiError, Client

NOBODY = 65534


# ---- the policy, deterministically ---------------------------------------------------------
def test_policy_caps_each_user_and_keeps_slots_for_privileged_peers() -> None:
    adm = Admission(Limits(total=64, reserved=16, per_uid=8))
    mine = [adm.admit(NOBODY, False) for _ in range(200)]  # one user, 200 connects
    assert sum(s is not None for s, _ in mine) == 8
    assert "uid 65534 already holds 8 connections" in mine[-1][1]
    others = [adm.admit(1000 + k // 8, False)[0] for k in range(40)]  # 5 more users fill it
    assert all(others) and adm.held() == 48
    slot, why = adm.admit(2000, False)  # a 7th observer: the shared slots are taken
    assert slot is None and "all 48 connections open to observers are in use" in why
    operator = [adm.admit(1500, True)[0] for _ in range(8)]  # an operator: the reserve
    assert all(operator) and {s.pool for s in operator if s} == {"reserved"}
    assert adm.admit(1500, True)[0] is None  # operators are capped per uid like anyone
    root = [adm.admit(0, True)[0] for _ in range(9)]  # root is not capped per uid ...
    assert sum(s is not None for s in root) == 8  # ... only by the total
    slot, why = adm.admit(0, True)
    assert slot is None and why == "all 64 connections are in use"
    for s in operator:
        assert s is not None
        adm.release(s)
    assert adm.admit(0, True)[0] is not None  # a released slot is root's again
    assert adm.admit(NOBODY, False)[0] is None  # still 8 held by uid 65534
    for s, _ in mine[:8]:
        assert s is not None
        adm.release(s)
    assert adm.held(NOBODY) == 0


def test_refusals_are_logged_at_a_bounded_rate(caplog: pytest.LogCaptureFixture) -> None:
    now = [0.0]
    rl = RefusalLog(interval_s=10.0, clock=lambda: now[0])
    with caplog.at_level(logging.WARNING, logger="alignd.admission"):
        for k in range(40000):  # 40,000 refused connects in a minute
            now[0] = k * 60.0 / 40000
            rl.refused(NOBODY, "uid 65534 already holds 8 connections")
        now[0] = 70.0
        rl.flush()
    lines = [r.getMessage() for r in caplog.records]
    assert 2 <= len(lines) <= 8, lines
    assert "refused a connection (uid 65534: 1)" in lines[0]
    counted = 1 + sum(int(ln.split()[2]) for ln in lines[1:])
    assert counted == rl.total == 40000  # every refusal is counted in some line


# ---- on a real socket ------------------------------------------------------------------------
@pytest.fixture
def small() -> Iterator[Env]:
    # a long request deadline: the held idle connections stay held however slow the machine
    yield from make_env(limits=Limits(total=12, reserved=4, per_uid=4), request_timeout_s=60.0)


@pytest.mark.skipif(os.getuid() != 0, reason="drops privileges to uid 65534")
def test_one_user_holding_connections_cannot_lock_root_out(small: Env) -> None:
    env = small
    wait_until(lambda: env.daemon.state == "idle")
    run_id = env.client.start("check")["run_id"]  # a live run, for the long polls
    idle = "GET /status HTTP/1.1\r\nHost: x\r\n"  # never finished
    poll = f"GET /runs/{run_id}/events?after=999999&wait=30 HTTP/1.1\r\n\r\n"
    holder = Holder(env.sock, [idle, poll] * 20)  # 40 connections as uid 65534
    try:
        wait_until(lambda: env.server.refusals.total == 36)
        assert env.server.admission.held(NOBODY) == 4
        # root: status and abort are answered; the run is aborted
        assert env.client.status()["state"] == "checking"
        assert env.client.abort()["aborted"] == run_id
        assert env.client.history(1)[0]["id"] == run_id
    finally:
        holder.close()
    wait_until(lambda: env.server.admission.held(NOBODY) == 0)


def test_a_burst_of_connects_waits_in_the_listen_queue() -> None:
    tmp = short_tmp()
    server = ApiServer(tmp / "s.sock", None, Authoriser(None))  # type: ignore[arg-type]
    conns = []
    try:  # nothing accepts yet: all 30 must wait in the backlog, none be refused
        for _ in range(30):
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.setblocking(False)
            s.connect(str(tmp / "s.sock"))  # BlockingIOError if the queue were full
            conns.append(s)
    finally:
        for s in conns:
            s.close()
        server.stop()


def test_client_retries_a_refused_connect_until_the_daemon_listens() -> None:
    tmp = short_tmp()
    path = tmp / "s.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))  # a socket file nobody listens on: connect is refused
    stale.close()
    tried = threading.Event()
    proceed = threading.Event()

    def sleep(_s: float) -> None:
        tried.set()
        proceed.wait(10)

    client = Client(path, timeout_s=5.0, retry_s=60.0, sleep=sleep)
    result: list[object] = []
    t = threading.Thread(target=lambda: result.append(client.history()))
    t.start()
    assert tried.wait(10)  # the first connect was refused and is being retried
    for env in make_env():
        server = ApiServer(path, env.daemon, Authoriser(None))
        server.start()
        proceed.set()
        t.join(10)
        server.stop()
    assert result == [[]]


def test_client_shows_the_daemons_503_message(capsys: pytest.CaptureFixture[str]) -> None:
    for env in make_env(limits=Limits(total=1, reserved=0)):
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as hog:
            hog.connect(env.sock)
            hog.sendall(b"GET /status HTTP/1.1\r\n")  # holds the only slot
            wait_until(lambda env=env: env.server.admission.held() == 1)
            sleeps: list[float] = []
            with pytest.raises(ApiError) as info:
                Client(env.sock, retry_s=0.5, sleep=sleeps.append).status()
            assert info.value.status == 503 and info.value.code == "overloaded"
            assert "too many connections: all 1 connections are in use" in str(info.value)
            assert len(sleeps) >= 2  # it retried before giving up
            assert alignctl(["--socket", env.sock, "status"]) == 3
            err = capsys.readouterr().err
            assert "alignctl: error: too many connections: all 1 connections are in use" in err
            assert "Traceback" not in err
