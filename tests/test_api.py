"""The control API on a real Unix socket: authorisation by peer credentials, busy refusal,
live progress, abort, faults, and hostile requests that must not hurt the daemon."""

from __future__ import annotations

import grp
import os
import socket
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from daemon_fakes import Env, as_observer, follow, make_env, make_procedure, wait_until

from alignd.admission import Limits
from alignd.api import Authoriser, Peer, peer_credentials
from alignd.client import ApiError
from alignd.errors import DeviceTimeoutError, PortBusyError


@pytest.fixture
def env() -> Iterator[Env]:
    yield from make_env()


def raw(path: str, data: bytes, timeout_s: float = 5.0, close_write: bool = True) -> bytes:
    """Send raw bytes, return everything the server sends before it closes."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout_s)
        s.connect(path)
        s.sendall(data)
        if close_write:
            s.shutdown(socket.SHUT_WR)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
        return out


# ---- the happy path and busy refusal --------------------------------------------------------
def test_align_runs_once_and_second_request_is_busy(env: Env) -> None:
    wait_until(lambda: env.daemon.state == "idle")
    started = env.client.start("align")
    run_id = started["run_id"]
    wait_until(lambda: (env.client.status().get("progress") or {}).get("phase") == "move")
    st = env.client.status()  # status keeps answering during a run
    assert st["state"] == "aligning" and st["run_id"] == run_id
    assert st["progress"]["iteration"] == 1 and st["progress"]["offset_norm_um"] > 800
    for kind in ("align", "check"):
        with pytest.raises(ApiError) as exc:
            env.client.start(kind)
        assert exc.value.status == 409 and exc.value.code == "busy"
        assert f"run {run_id}" in str(exc.value)
    env.gate.set()
    out = follow(env.client, run_id)
    assert out["result"]["verdict"] == "aligned" and out["result"]["run_id"] == run_id
    assert out["result"]["truth"]["offset_norm_um"] == pytest.approx(2.236)
    kinds = [e["type"] for e in out["events"]]
    assert kinds[0] == "state" and kinds[-1] == "end" and "progress" in kinds
    steps = [e["step"] for e in out["events"] if e["type"] == "progress" and e.get("step")]
    assert steps[:5] == [1, 2, 3, 4, 5]
    assert env.client.status()["state"] == "idle"
    hist = env.client.history(10)
    assert [r["id"] for r in hist] == [run_id]  # the refused requests left no record
    run = env.client.run(run_id)
    assert len(run["sweeps"]) == 2 and len(run["iteration_records"]) == 2
    assert run["devices"]["turntable"]["serial"] == "FAKE1"
    png = env.client.frame(run["frames"][0]["hash"])
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_abort_stops_axes_and_records_who(env: Env) -> None:
    wait_until(lambda: env.daemon.state == "idle")
    run_id = env.client.start("check", "timer")["run_id"]
    wait_until(lambda: env.client.status().get("progress") is not None)
    reply = env.client.abort()
    assert reply["aborted"] == run_id
    out = follow(env.client, run_id)
    assert out["result"]["verdict"] == "aborted"
    assert "aborted by" in out["result"]["reason"] and f"uid {os.getuid()}" in \
        out["result"]["reason"]
    assert env.rig.stops >= 1  # every axis told to stop
    last = env.client.run(run_id)["events"][-1]
    assert last["level"] == "warning" and last["msg"] == (
        "positions after stop: turntable=-3.25, x=unknown (port vanished)")
    assert env.client.status()["state"] == "idle"
    assert env.client.history(1)[0]["started_by"] == "timer"
    assert env.client.abort()["aborted"] is None  # nothing left to abort


def test_events_long_poll_waits_for_news(env: Env) -> None:
    wait_until(lambda: env.daemon.state == "idle")
    run_id = env.client.start("align")["run_id"]
    wait_until(lambda: (env.client.status().get("progress") or {}).get("phase") == "move")
    first = env.client.events(run_id, after=0, wait_s=0)
    t0 = time.monotonic()
    threading.Timer(0.3, env.gate.set).start()
    nxt = env.client.events(run_id, after=first["next"], wait_s=5)
    assert time.monotonic() - t0 >= 0.25  # it waited for the gate rather than returning empty
    assert nxt["events"] and nxt["events"][0]["seq"] > first["next"]


# ---- faults -----------------------------------------------------------------------------------
def test_device_error_faults_the_daemon_until_reset() -> None:
    exc = DeviceTimeoutError("platform (zaber) on socket://127.0.0.1:1: no reply to '/1 get pos'")
    procs = {"align": make_procedure(raise_exc=exc), "check": make_procedure()}
    for env in make_env(procs):
        wait_until(lambda env=env: env.daemon.state == "idle")
        run_id = env.client.start("align")["run_id"]
        out = follow(env.client, run_id)
        assert out["result"]["verdict"] == "fault"
        assert "no reply to '/1 get pos'" in out["result"]["reason"]
        assert env.rig.stops >= 1
        st = env.client.status()
        assert st["state"] == "fault" and "no reply" in st["fault"]
        with pytest.raises(ApiError) as refused:
            env.client.start("check")
        assert refused.value.code == "fault" and refused.value.status == 409
        env.client.reset()
        wait_until(lambda env=env: env.daemon.state == "idle")
        assert env.rig.closed  # the rig was closed and reopened


def test_rig_that_cannot_open_leaves_daemon_up_in_fault() -> None:
    def factory(_cfg: Any) -> Any:
        raise PortBusyError("platform (zaber): /dev/ttyUSB0 is held by another process")

    for env in make_env(rig_factory=factory):
        wait_until(lambda env=env: env.daemon.state == "fault")
        st = env.client.status()
        assert "/dev/ttyUSB0 is held by another process" in st["fault"]
        with pytest.raises(ApiError, match="faulted"):
            env.client.start("align")
        assert env.client.history() == []


def test_full_store_refuses_to_start_a_run(env: Env) -> None:
    wait_until(lambda: env.daemon.state == "idle")
    env.store.min_free_bytes = 2**62  # more than any disk has: "disk full"
    with pytest.raises(ApiError) as exc:
        env.client.start("align")
    assert exc.value.status == 503 and exc.value.code == "store"
    assert "could not be recorded" in str(exc.value) and "disk nearly full" in str(exc.value)
    assert env.daemon.state == "idle" and env.rig.stops == 0  # nothing moved


# ---- authorisation ----------------------------------------------------------------------------
def test_peer_credentials_come_from_the_kernel() -> None:
    a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
    with a, b:
        peer = peer_credentials(a)
    assert (peer.pid, peer.uid, peer.gid) == (os.getpid(), os.getuid(), os.getgid())
    assert os.getgid() in peer.groups


def test_authoriser_rules() -> None:
    gid = grp.getgrnam("dialout").gr_gid
    auth = Authoriser("dialout", allow_uids=frozenset())
    assert auth.may_control(Peer(1, 0, 0))  # root always
    assert auth.may_control(Peer(1, 4242, 100, frozenset({100, gid})))
    assert not auth.may_control(Peer(1, 4242, 100, frozenset({100})))
    # no operator group: nobody but root and the allowed uids (the daemon's own user)
    assert not Authoriser(None, allow_uids=frozenset()).may_control(Peer(1, 4242, 100))
    assert Authoriser(None, allow_uids=frozenset({4242})).may_control(Peer(1, 4242, 100))
    assert Authoriser(None).may_control(Peer(1, os.getuid(), 100))  # the daemon's user
    assert not Authoriser("no-such-group-xyz", allow_uids=frozenset()).may_control(
        Peer(1, 4242, 100, frozenset({100})))




def _observer_group() -> str:
    """A group the (non-root) test user is not in."""
    mine = set(os.getgroups()) | {os.getgid()}
    return next(g.gr_name for g in grp.getgrall() if g.gr_gid not in mine)


def test_observer_may_read_but_not_control() -> None:
    if os.getuid() == 0:
        # root always may; the observer is a real other user: 'nobody' in a subprocess
        auth = Authoriser("dialout")
        for env in make_env(authoriser=auth):
            os.chmod(env.sock, 0o666)
            (s_code, status), (a_code, align), (x_code, abort) = as_observer(
                env.sock, [("GET", "/status", ""), ("POST", "/align", "{}"),
                           ("POST", "/abort", "{}")])
            assert abort["error"] == "forbidden"
            assert s_code == 200 and status["state"] in ("starting", "idle")
            assert a_code == 403 and align["error"] == "forbidden"
            assert "operator group 'dialout'" in align["message"] and "uid 65534" in \
                align["message"]
            assert x_code == 403
            assert env.client.history() == []  # nothing started
    else:
        auth = Authoriser(_observer_group(), allow_uids=frozenset())
        for env in make_env(authoriser=auth):
            assert env.client.status()["state"] in ("starting", "idle")
            with pytest.raises(ApiError) as exc:
                env.client.start("align")
            assert exc.value.status == 403 and exc.value.code == "forbidden"
            assert env.client.history() == []


# ---- hostile requests -------------------------------------------------------------------------
def _post(path: str, body: bytes) -> bytes:
    return f"POST {path} HTTP/1.1\r\nContent-Length: {len(body)}\r\n\r\n".encode() + body


def test_bad_requests_get_errors_and_daemon_keeps_answering(env: Env) -> None:
    cases = [
        (b"GET /nowhere HTTP/1.1\r\nHost: x\r\n\r\n", b" 404 "),
        (b"DELETE /status HTTP/1.1\r\nHost: x\r\n\r\n", b" 405 "),
        (b"GET /status HTTP/1.1\r\n" + b"X: y\r\n" * 200 + b"\r\n", b" 431 "),
        (b"\x00\xff\xfe garbage\r\n\r\n", b" 400 "),
        (b"GET /" + b"a" * 70000 + b" HTTP/1.1\r\n\r\n", b" 414 "),
        (b"POST /align HTTP/1.1\r\nContent-Length: 5\r\n\r\n{oops", b'"bad_json"'),
        (b"POST /align HTTP/1.1\r\nContent-Length: 2\r\n\r\n[]", b'"bad_json"'),
        (b"POST /align HTTP/1.1\r\nContent-Length: 10000000\r\n\r\n{}", b" 413 "),
        (b"POST /align HTTP/1.1\r\nContent-Length: -4\r\n\r\n", b" 400 "),
        (b"POST /align HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\n", b" 411 "),
        (_post("/check", b'{"started_by": "; rm -rf"}'), b" 400 "),
        (_post("/check", b'{"started_by": 7}'), b" 400 "),
        (_post("/check", b'{"started_by": "user"' + b" " * 70000 + b"}"), b" 413 "),
        (_post("/check", b"\xff\xfe{}"), b'"bad_json"'),
        (b"GET /runs/abc HTTP/1.1\r\n\r\n", b" 400 "),
        (b"GET /runs/99 HTTP/1.1\r\n\r\n", b" 404 "),
        (b"GET /history?limit=x HTTP/1.1\r\n\r\n", b" 400 "),
        (b"GET /frames/../../etc/passwd HTTP/1.1\r\n\r\n", b" 40"),
        (b"GET /runs/1/events?wait=nan HTTP/1.1\r\n\r\n", b" 400 "),
    ]
    for request, expect in cases:
        reply = raw(env.sock, request)
        assert expect in reply, (request[:60], reply[:200])
        assert b"Connection: close" in reply or reply.startswith(b"HTTP/1.1 4")
    assert env.client.status()["state"] in ("starting", "idle")
    assert env.client.history() == []  # none of them started anything


def test_stalled_and_excess_connections_are_cut() -> None:
    for env in make_env(request_timeout_s=0.5, limits=Limits(total=2, reserved=0)):
        stalled = []
        for _ in range(2):  # two clients that never finish their request
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.connect(env.sock)
            s.sendall(b"GET /status HTTP/1.1\r\nHost: x\r\n")
            stalled.append(s)
        time.sleep(0.1)
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:  # one too many
            s.settimeout(3.0)
            s.connect(env.sock)
            third = s.recv(4096)  # refused at once, before it even sends its request
        assert b" 503 " in third and b"too many connections" in third
        for s in stalled:  # cut within the request deadline (and a reaper period)
            s.settimeout(3.0)
            data = s.recv(4096)
            assert data == b"" or b" 408 " in data or b" 400 " in data
            s.close()
        def answers(env: Any = env) -> bool:  # until the cut threads free their slots,
            try:  # the server refuses at once and the send may hit a closed socket
                return b" 200 " in raw(env.sock, b"GET /status HTTP/1.1\r\n\r\n")
            except OSError:
                return False

        wait_until(answers)
        # a client that dribbles a byte now and then never trips the read timeout, but
        # the whole request must arrive within the deadline
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.connect(env.sock)
            t0 = time.monotonic()
            with pytest.raises(OSError):  # the send loop is the stimulus
                for _ in range(50):
                    s.sendall(b"X")
                    time.sleep(0.1)
            assert time.monotonic() - t0 < 2.0
        # (the cut dribbler's thread frees its slot after the cut: until then a new
        # connection is refused at once and closed, and a send to it breaks the pipe)
        wait_until(answers)
        # a body that stops arriving part-way is cut too, and the daemon is unaffected
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(3.0)
            s.connect(env.sock)
            s.sendall(b"POST /align HTTP/1.1\r\nContent-Length: 100\r\n\r\n{")
            reply = s.recv(4096)
        assert reply == b"" or b" 408 " in reply
        assert env.client.history() == []
        assert env.client.status()["state"] in ("starting", "idle")


def test_peer_groups_are_the_processes_groups() -> None:
    # SO_PEERGROUPS: the connecting process's supplementary groups, as the kernel has them
    a, b = socket.socketpair()
    with a, b:
        p = peer_credentials(a)
    assert set(p.groups) == set(os.getgroups()) | {os.getgid()}


def test_fuzzed_requests_never_hurt_the_daemon(env: Env) -> None:
    """Seeded mutations of valid requests: each gets an HTTP error or a closed connection,
    nothing is started, and the daemon answers afterwards."""
    import random

    wait_until(lambda: env.daemon.state == "idle")
    threads = threading.active_count()
    rng = random.Random(20261122)
    seeds = [b"GET /status HTTP/1.1\r\nHost: x\r\n\r\n",
             b"GET /history?limit=5 HTTP/1.1\r\n\r\n",
             _post("/align", b'{"started_by": "user"}'),
             _post("/abort", b"{}")]
    for _ in range(60):
        req = bytearray(rng.choice(seeds))
        for _ in range(rng.randint(1, 6)):
            if not req:
                break
            op = rng.randrange(4)
            i = rng.randrange(len(req))
            if op == 0:
                req[i] = rng.randrange(256)  # flip a byte
            elif op == 1:
                del req[i:i + rng.randint(1, 8)]  # drop some
            elif op == 2:
                req[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
            else:
                req = req[:i]  # truncate
        if bytes(req).startswith(b"POST /align") and b'"user"' in req:
            continue  # an intact start request is not a fuzz case
        reply = raw(env.sock, bytes(req))
        assert reply == b"" or reply.startswith(b"HTTP/1."), reply[:80]
    assert b" 200 " in raw(env.sock, b"GET /status HTTP/1.1\r\n\r\n")
    # every connection's thread has finished: nothing leaks per request
    wait_until(lambda: threading.active_count() <= threads)


# ---- access as a real other user (issue 9) -------------------------------------------------
needs_root = pytest.mark.skipif(os.getuid() != 0, reason="drops privileges to uid 65534")


@needs_root
def test_without_operator_group_an_observer_may_read_but_not_control() -> None:
    # operator_group: null (the shipped sim config) once meant "anyone may move the stages"
    for env in make_env(authoriser=Authoriser(None)):
        wait_until(lambda env=env: env.daemon.state == "idle")
        (s_code, st), (a_code, align), (x_code, _), (r_code, _) = as_observer(
            env.sock, [("GET", "/status", ""), ("POST", "/align", "{}"),
                       ("POST", "/abort", "{}"), ("POST", "/reset", "{}")])
        assert s_code == 200 and st["state"] == "idle"
        assert (a_code, x_code, r_code) == (403, 403, 403)
        assert "uid 65534" in align["message"] and "no daemon.operator_group" in \
            align["message"]
        assert env.client.history() == []
        run_id = env.client.start("check")["run_id"]  # root still may
        assert env.client.abort()["aborted"] == run_id


@needs_root
def test_operator_rights_are_the_connecting_processes_own_groups() -> None:
    """uid 65534 is in no group of the group database: only the groups its process holds
    (as the kernel reports them, SO_PEERGROUPS) count, including past 256 of them."""
    dialout = grp.getgrnam("dialout").gr_gid
    assert "nobody" not in grp.getgrnam("dialout").gr_mem
    many = list(range(60000, 60300))  # 300 groups: beyond what 1024 bytes can hold
    for env in make_env(authoriser=Authoriser("dialout")):
        wait_until(lambda env=env: env.daemon.state == "idle")
        for groups, expect in (([dialout], 200), ([], 403), ([*many, dialout], 200),
                               (many, 403)):
            [(code, reply)] = as_observer(env.sock, [("POST", "/abort", "{}")], groups)
            assert code == expect, (len(groups), reply)
            if expect == 200:
                assert reply["aborted"] is None  # allowed; there was nothing to abort
        [(code, reply)] = as_observer(env.sock, [("POST", "/check", "{}")], [dialout])
        assert code == 202 and env.client.history(1)[0]["user"] == "nobody"
        env.client.abort()


def test_without_so_peergroups_only_the_primary_group_counts(
        monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Fail closed: when the kernel cannot report the peer's groups, the group database
    (which says what the user *could* hold, not what the process holds) is not asked."""
    import errno

    import alignd.api as api

    class NoPeerGroups(socket.socket):
        def getsockopt(self, level: int, opt: int, *args: int) -> Any:  # type: ignore[override]
            if opt == api.SO_PEERGROUPS:
                raise OSError(errno.ENOPROTOOPT, "Protocol not available")
            return super().getsockopt(level, opt, *args)

    operators = 4242
    monkeypatch.setattr(os, "getgrouplist", lambda _user, gid: [gid, operators])
    a, b = socket.socketpair()
    with a, b, NoPeerGroups(fileno=os.dup(a.fileno())) as s:
        peer = peer_credentials(s)
    assert peer.groups == {os.getgid()} and not peer.groups_known
    assert "supplementary groups" in caplog.text
    auth = Authoriser("dialout", allow_uids=frozenset())
    auth.operator_gid = operators
    stranger = Peer(peer.pid, 4242, peer.gid, peer.groups, peer.groups_known)
    assert not auth.may_control(stranger)
    with pytest.raises(Exception, match="did not report the process's groups"):
        auth.require_control(stranger, "start an alignment")


def test_deeply_nested_body_is_a_400_not_a_crash(env: Env) -> None:
    wait_until(lambda: env.daemon.state == "idle")  # the last request starts a run
    deep = b"[" * 30000 + b"]" * 30000
    reply = raw(env.sock, _post("/align", deep))
    assert reply.startswith(b"HTTP/1.1 400 ") and b"nested 30000 levels deep" in reply
    reply = raw(env.sock, _post("/check", b'{"started_by": {"a": [[["user"]]]}}'))
    assert reply.startswith(b"HTTP/1.1 400 ")  # shallow enough to parse, still not a word
    reply = raw(env.sock, _post("/check", b'{"started_by": "user", "x": "[[[[[[[[[[[["}'))
    assert reply.startswith(b"HTTP/1.1 202 ")  # brackets inside strings do not nest
    env.client.abort()


@needs_root
def test_control_requests_are_authorised_before_the_body_is_read() -> None:
    for env in make_env(authoriser=Authoriser("dialout")):
        deep = "[" * 30000 + "]" * 30000
        (d_code, d), (b_code, b) = as_observer(
            env.sock, [("POST", "/align", deep), ("POST", "/check", "{" * 65000)])
        assert (d_code, d["error"]) == (403, "forbidden")
        assert (b_code, b["error"]) == (403, "forbidden")
