"""The daemon process and alignctl: start-up refusals, SIGTERM and SIGKILL mid-run,
sd_notify, CLI output and exit codes, atomic reports, and the systemd units."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from daemon_fakes import (
    SIM_CONFIG,
    FakeRig,
    follow,
    make_env,
    make_procedure,
    short_tmp,
    wait_until,
)

from alignd import daemon as daemon_mod
from alignd import report
from alignd.cli import main as alignctl
from alignd.client import Client, resolve_socket
from alignd.daemon import Notifier, resolve_state_dir, status_line
from alignd.errors import DeviceFault
from alignd.store import Store

FAKES = Path(__file__).with_name("daemon_fakes.py")
REPO = Path(__file__).resolve().parents[1]


def fake_rig(_cfg: object) -> FakeRig:
    return FakeRig()


@pytest.fixture
def tmp() -> Iterator[Path]:
    d = short_tmp()
    yield d
    shutil.rmtree(d, ignore_errors=True)


def spawn(tmp: Path, mode: str, *extra: str, env: dict[str, str] | None = None
          ) -> subprocess.Popen[str]:
    """The real alignd main in a subprocess, with a fake rig and procedures."""
    return subprocess.Popen(
        [sys.executable, str(FAKES), mode, "--config", str(SIM_CONFIG), "--socket",
         str(tmp / "s.sock"), "--state-dir", str(tmp / "state"), "--stop-timeout", "5", *extra],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, **(env or {})})


def wait_ready(client: Client, proc: subprocess.Popen[str], timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[1]
        try:
            if client.status()["state"] == "idle":
                return
        except Exception:  # not up yet
            pass
        time.sleep(0.05)
    raise AssertionError("daemon did not become ready")


# ---- start-up refusals (in-process: main() returns before serving) ---------------------------
def test_bad_config_exits_2_naming_the_key(tmp: Path, capsys: pytest.CaptureFixture) -> None:
    bad = tmp / "bad.yaml"
    bad.write_text(SIM_CONFIG.read_text().replace("tolerance_um: 10.0", "tolerance_um: -1"))
    assert daemon_mod.main(["--config", str(bad), "--state-dir", str(tmp / "st"),
                            "--socket", str(tmp / "s")]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "procedure.tolerance_um" in err
    assert not (tmp / "s").exists()


def test_unwritable_state_dir_exits_3(tmp: Path, capsys: pytest.CaptureFixture) -> None:
    (tmp / "file").write_text("x")
    rc = daemon_mod.main(["--config", str(SIM_CONFIG), "--state-dir", str(tmp / "file" / "st"),
                          "--socket", str(tmp / "s")], rig_factory=fake_rig,
                          procedures={})
    assert rc == 3
    assert "cannot use the state directory" in capsys.readouterr().err


def test_resolution_order_for_socket_and_state_dir(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ALIGND_SOCKET", "/env.sock")
    assert resolve_socket("/arg.sock", "/cfg.sock") == "/arg.sock"
    assert resolve_socket(None, "/cfg.sock") == "/env.sock"
    monkeypatch.delenv("ALIGND_SOCKET")
    assert resolve_socket(None, "/cfg.sock") == "/cfg.sock"
    assert resolve_socket(None) == "/run/alignd/alignd.sock"
    env = {"STATE_DIRECTORY": "/var/lib/alignd:/other", "XDG_STATE_HOME": "/x"}
    assert resolve_state_dir("/arg", env) == Path("/arg")
    assert resolve_state_dir(None, env) == Path("/var/lib/alignd")
    assert resolve_state_dir(None, {"XDG_STATE_HOME": "/x"}) == Path("/x/alignd")
    assert resolve_state_dir(None, {}) == Path.home() / ".local" / "state" / "alignd"


# ---- signals and sd_notify (subprocess) --------------------------------------------------------
class _NotifyReader:
    """The service manager's side of ``$NOTIFY_SOCKET``, read continuously (as systemd
    does): its queue holds only ``net.unix.max_dgram_qlen`` (10) messages."""

    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.msgs: list[str] = []
        self._stop = False
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop:
            with contextlib.suppress(TimeoutError):
                self.msgs.append(self.sock.recv(4096).decode())

    def close(self) -> str:
        self._stop = True
        self._thread.join(5)
        self.sock.close()
        return "\n".join(self.msgs)


def test_sigterm_mid_run_aborts_records_and_exits_in_time(tmp: Path) -> None:
    notify = _NotifyReader(tmp / "notify")
    proc = spawn(tmp, "block", env={"NOTIFY_SOCKET": str(tmp / "notify"),
                                    "WATCHDOG_USEC": "200000"})
    client = Client(tmp / "s.sock")
    try:
        wait_ready(client, proc)
        run_id = client.start("align")["run_id"]
        wait_until(lambda: client.status()["progress"] is not None)
        time.sleep(0.2)  # a few watchdog periods while the run is in progress
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=10)
        elapsed = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        msgs = notify.close()
    err = proc.stderr.read()
    assert rc == 0, err
    assert elapsed < 5.0  # within --stop-timeout
    assert "READY=1" in msgs and "WATCHDOG=1" in msgs and "STOPPING=1" in msgs
    assert f"STATUS=aligning (run {run_id})" in msgs
    store = Store(tmp / "state").open()
    run = store.get_run(run_id)
    assert run["status"] == "finished" and run["verdict"] == "aborted"
    assert "daemon stopping (SIGTERM)" in run["reason"]
    assert store.integrity_check() == ["ok"]
    store.close()
    assert not (tmp / "s.sock").exists()


def test_sigkill_mid_run_then_restart_marks_it_interrupted(tmp: Path,
                                                           capsys: pytest.CaptureFixture) -> None:
    proc = spawn(tmp, "block")
    client = Client(tmp / "s.sock")
    try:
        wait_ready(client, proc)
        run_id = client.start("align")["run_id"]
        wait_until(lambda: client.status()["progress"] is not None)
        # a second daemon on the same state directory or socket is refused, harmlessly
        assert daemon_mod.main(["--config", str(SIM_CONFIG), "--socket", str(tmp / "t.sock"),
                                "--state-dir", str(tmp / "state")], rig_factory=fake_rig,
                               procedures={}) == 3
        assert "another alignd is using this state directory" in capsys.readouterr().err
        assert daemon_mod.main(["--config", str(SIM_CONFIG), "--socket", str(tmp / "s.sock"),
                                "--state-dir", str(tmp / "other")], rig_factory=fake_rig,
                               procedures={}) == 3
        assert "already listening" in capsys.readouterr().err
        assert client.status()["state"] == "aligning"  # the first daemon is unaffected
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    assert (tmp / "s.sock").exists()  # a stale socket, as a crash leaves it

    proc2 = spawn(tmp, "quick")
    try:
        wait_ready(client, proc2)
        runs = client.history(10)
        assert [(r["id"], r["status"], r["verdict"]) for r in runs] == [
            (run_id, "interrupted", "interrupted")]  # and nothing was started on its own
        assert "SIGKILL" in runs[0]["reason"]
        st = client.status()
        assert st["state"] == "idle" and st["run_id"] is None
        assert Store(tmp / "state").integrity_check() == ["ok"]
        # the restarted daemon works normally
        new = client.start("check")["run_id"]
        assert follow(client, new)["result"]["verdict"] == "within_tolerance"
    finally:
        proc2.send_signal(signal.SIGTERM)
        assert proc2.wait(timeout=10) == 0


def test_notifier_protocol(tmp: Path) -> None:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0alignd-test-" + tmp.name)  # abstract namespace, as systemd may use
    sock.settimeout(2.0)
    n = Notifier({"NOTIFY_SOCKET": "@alignd-test-" + tmp.name, "WATCHDOG_USEC": "4000000"})
    n.ready("idle")
    assert sock.recv(4096).decode().startswith("READY=1\nSTATUS=idle")
    n.watchdog()
    n.watchdog()  # rate-limited: a quarter of the interval must pass between pings
    assert sock.recv(4096) == b"WATCHDOG=1"
    n.status("aligning")
    assert sock.recv(4096) == b"STATUS=aligning"
    sock.close()
    other = Notifier({"NOTIFY_SOCKET": "@x", "WATCHDOG_USEC": "4000000", "WATCHDOG_PID": "1"})
    assert other.watchdog_s is None  # the watchdog is meant for another process
    assert not Notifier({}).send("READY=1")  # outside systemd: a no-op
    # a receiver that does not read (its queue holds 10): messages are dropped, the daemon
    # is never blocked (it was: the worker hung in sendall and SIGTERM could not stop it)
    deaf = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    deaf.bind(str(tmp / "deaf"))
    sent: list[bool] = []
    t = threading.Thread(target=lambda: sent.extend(
        Notifier({"NOTIFY_SOCKET": str(tmp / "deaf")}).send("WATCHDOG=1") for _ in range(30)),
        daemon=True)
    t.start()
    t.join(10)
    deaf.close()
    assert not t.is_alive() and sent[0] and not sent[-1]


def test_status_line_names_the_progress() -> None:
    st = {"state": "aligning", "run_id": 7, "progress": {
        "phase": "sweep", "iteration": 2, "step": 5, "total": 21, "offset_norm_um": 123.45,
        "U_um": 4.0}}
    assert status_line(st) == ("aligning (run 7): sweep, iteration 2, step 5/21, "
                               "offset 123.5 ± 4.0 um")
    assert status_line({"state": "fault", "fault": "port gone"}) == "fault: port gone"


# ---- alignctl against a live in-process daemon -------------------------------------------------
def ctl(sock: str, *args: str) -> int:
    return alignctl(["--socket", sock, *args])


def test_cli_align_and_check_exit_codes(capsys: pytest.CaptureFixture) -> None:
    procs = {"align": make_procedure("aligned"), "check": make_procedure("out_of_tolerance")}
    for env in make_env(procs):
        wait_until(lambda env=env: env.daemon.state == "idle")
        assert ctl(env.sock, "align", "--json") == 0
        out, err = capsys.readouterr()
        result = json.loads(out.strip().splitlines()[-1])  # the final line: run-result JSON
        assert result["verdict"] == "aligned" and result["run_id"] == 1
        assert {"offset_um", "offset_norm_um", "U_um", "iterations", "tilt_deg", "yaw_deg",
                "reason", "truth"} <= set(result)
        assert "[sweep] iteration 1 step 1/5" in err and "offset 854.4 ± 5.0 µm" in err
        assert alignctl(["check", "--socket", env.sock]) == 1  # --socket after the command
        out, _ = capsys.readouterr()
        assert "run 2: out_of_tolerance" in out and "offset     53.4 ± 5.0 µm" in out
        assert ctl(env.sock, "status") == 0
        assert "state: idle" in capsys.readouterr().out
        assert ctl(env.sock, "history", "--json") == 0
        hist = json.loads(capsys.readouterr().out)
        assert [(r["id"], r["verdict"]) for r in hist] == [(2, "out_of_tolerance"),
                                                            (1, "aligned")]
        assert ctl(env.sock, "history", "-n", "1") == 0
        table = capsys.readouterr().out.splitlines()
        assert table[0].split()[:2] == ["ID", "KIND"] and len(table) == 2


def test_cli_fault_and_timer_skip(capsys: pytest.CaptureFixture) -> None:
    procs = {"align": make_procedure(raise_exc=DeviceFault("x (zaber) on /dev/ttyUSB0: "
                                                           "stalled during '/1 move abs'")),
             "check": make_procedure("within_tolerance")}
    for env in make_env(procs):
        wait_until(lambda env=env: env.daemon.state == "idle")
        assert ctl(env.sock, "align", "-q") == 3
        assert "stalled during '/1 move abs'" in capsys.readouterr().out
        assert ctl(env.sock, "status") == 3  # faulted
        assert ctl(env.sock, "check") == 3  # an operator is told: fault
        assert "faulted" in capsys.readouterr().err
        assert ctl(env.sock, "check", "--started-by", "timer") == 75  # the timer: skipped
        assert "check skipped" in capsys.readouterr().err
        assert [r["id"] for r in env.client.history()] == [1]


def test_cli_busy_is_skipped_and_unreachable_is_3(capsys: pytest.CaptureFixture,
                                                  tmp: Path) -> None:
    for env in make_env():  # gated procedures: a run stays in progress
        wait_until(lambda env=env: env.daemon.state == "idle")
        run_id = env.client.start("align")["run_id"]
        assert ctl(env.sock, "check", "--started-by", "timer") == 75
        assert f"busy: run {run_id} (align) is in progress" in capsys.readouterr().err
        assert ctl(env.sock, "align") == 3  # interactive: refused as busy, a plain failure
        assert "busy" in capsys.readouterr().err
        assert ctl(env.sock, "abort") == 0
        assert "aborted by" in capsys.readouterr().out
        assert follow(env.client, run_id)["result"]["verdict"] == "aborted"
    missing = str(tmp / "nobody-here.sock")
    assert ctl(missing, "status") == 3
    assert missing in capsys.readouterr().err
    os.environ["ALIGND_SOCKET"] = missing
    try:
        assert alignctl(["history"]) == 3
        assert missing in capsys.readouterr().err
    finally:
        del os.environ["ALIGND_SOCKET"]


# ---- reports ------------------------------------------------------------------------------------
def test_cli_report_writes_png_and_json(capsys: pytest.CaptureFixture, tmp: Path) -> None:
    procs = {"align": make_procedure("aligned"), "check": make_procedure("within_tolerance")}
    for env in make_env(procs):
        wait_until(lambda env=env: env.daemon.state == "idle")
        run_id = env.client.start("align")["run_id"]
        follow(env.client, run_id)
        assert ctl(env.sock, "report", str(run_id), "--out", str(tmp / "rep"), "--json") == 0
        paths = json.loads(capsys.readouterr().out)
        img = cv2.imread(paths["png"])
        assert img.shape == (report.HEADER_H + 540 + report.VERDICT_H + report.PLOT_H
                             + report.NOTES_H, report.WIDTH, 3)
        rec = json.loads(Path(paths["json"]).read_text())
        assert rec["id"] == run_id and rec["result"]["verdict"] == "aligned"
        assert len(rec["sweeps"]) == 2
        # the view shows the last sweep's frame nearest 0 deg: step 2 of 5 of iteration 2
        # (its bar: image row 12, columns 30-39; the view is scaled by 960 / 128 = 7.5)
        view = img[report.HEADER_H:report.HEADER_H + 540]
        assert view[round(12.5 * 7.5), round(35 * 7.5)].min() > 200
        assert view[round(10.5 * 7.5), round(35 * 7.5)].max() < 60  # not step 0's frame
        assert view[round(12.5 * 7.5), round(15 * 7.5)].max() < 60  # not iteration 1's
        # the target point: centre + offset at 0 deg, (60, 30) px, drawn as a magenta ring
        ring = view[round(30.5 * 7.5) - 8:round(30.5 * 7.5) + 8,
                    round(60.5 * 7.5) - 8:round(60.5 * 7.5) + 8]
        assert ((ring[..., 0] > 200) & (ring[..., 1] < 60) & (ring[..., 2] > 200)).any()
        assert ctl(env.sock, "report", "999", "--out", str(tmp / "rep")) == 2
        assert sorted(p.name for p in (tmp / "rep").iterdir()) == [
            f"run-{run_id}.json", f"run-{run_id}.png"]


def _can_mount() -> bool:
    return subprocess.run(["unshare", "-m", "true"], capture_output=True).returncode == 0


def _alignctl_proc(*args: str, stdout: int | None = None, read_only: Path | None = None
                   ) -> subprocess.CompletedProcess[str]:
    """alignctl in its own process, onto a given stdout; with ``read_only``, in a mount
    namespace where that folder is a read-only bind mount (unwritable even for root)."""
    cmd = [str(Path(sys.executable).with_name("alignctl")), *args]
    if read_only is not None:
        cmd = ["unshare", "-m", "sh", "-c", 'mount --bind "$0" "$0" && mount -o '
               'remount,bind,ro "$0" && exec "$@"', str(read_only), *cmd]
    return subprocess.run(cmd, cwd="/", stdout=stdout if stdout is not None else
                          subprocess.PIPE, stderr=subprocess.PIPE, text=True, timeout=60)


def test_report_out_onto_a_file_or_an_unwritable_folder_is_a_clear_error(
        capsys: pytest.CaptureFixture, tmp: Path) -> None:
    procs = {"align": make_procedure("aligned"), "check": make_procedure("within_tolerance")}
    for env in make_env(procs):
        wait_until(lambda env=env: env.daemon.state == "idle")
        run_id = str(env.client.start("check")["run_id"])
        follow(env.client, int(run_id))
        (tmp / "afile").write_text("keep me\n")
        assert ctl(env.sock, "report", run_id, "--out", str(tmp / "afile")) == 2
        err = capsys.readouterr().err
        assert f"--out {tmp / 'afile'} is a file, not a folder" in err
        assert (tmp / "afile").read_text() == "keep me\n"
        assert ctl(env.sock, "report", run_id, "--out", str(tmp / "afile" / "sub")) == 2
        assert "cannot create the folder" in capsys.readouterr().err  # "Not a directory"
        if not _can_mount():
            pytest.skip("an unwritable folder needs a read-only bind mount (CAP_SYS_ADMIN)")
        locked = tmp / "locked"  # read-only for everyone, root included: a read-only mount
        locked.mkdir()
        for out, says in ((locked, "cannot write into --out"),
                          (locked / "new", "cannot create the folder")):
            r = _alignctl_proc("--socket", env.sock, "report", run_id, "--out", str(out),
                               read_only=locked)
            assert r.returncode == 2, r.stderr
            assert says in r.stderr and "Read-only file system" in r.stderr
            assert "Traceback" not in r.stderr
        assert list(locked.iterdir()) == []


def test_output_into_a_closed_pipe_ends_quietly() -> None:
    """``alignctl status | head -1``: the reader leaves early; no BrokenPipe traceback."""
    for env in make_env():
        wait_until(lambda env=env: env.daemon.state == "idle")
        for cmd in (["status"], ["history", "--json"], ["status", "--json"]):
            r_fd, w_fd = os.pipe()
            os.close(r_fd)  # the reader is gone before anything is written
            try:
                r = _alignctl_proc("--socket", env.sock, *cmd, stdout=w_fd)
            finally:
                os.close(w_fd)
            assert r.returncode == 141, r.stderr
            assert r.stderr == ""


_REPORT_WRITER = r"""
import sys
from pathlib import Path
import numpy as np
from alignd.report import write_report
out = Path(sys.argv[1])
runs = [{"id": 1, "kind": "align", "verdict": v, "result": {"verdict": v},
         "iteration_records": [{"n": 1, "offset_norm_um": 100.0 * (i + 1), "U_um": 3.0}]}
        for i, v in enumerate(["aligned", "not_converged"])]
img = np.random.default_rng(1).integers(0, 255, (720, 1280), dtype=np.uint8)  # big PNGs
write_report(runs[0], out, img)
print("ready", flush=True)
i = 0
while True:
    i += 1
    write_report(runs[i % 2], out, img)
"""


def test_report_files_are_wholly_old_or_new_after_sigkill(tmp: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", _REPORT_WRITER, str(tmp)],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.3 + (os.getpid() % 5) / 20)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    rec = json.loads((tmp / "run-1.json").read_text())  # parses: never half-written
    assert rec["verdict"] in ("aligned", "not_converged")
    img = cv2.imread(str(tmp / "run-1.png"))
    assert img is not None and img.shape[1] == report.WIDTH
    # the PNG ends with its IEND chunk: the file is complete
    assert (tmp / "run-1.png").read_bytes()[-8:] == b"IEND\xaeB`\x82"


def test_report_without_frame_or_iterations_still_renders() -> None:
    img = report.render_report({"id": 3, "kind": "check", "status": "interrupted"}, None)
    assert img.shape == (report.HEADER_H + 540 + report.VERDICT_H + report.PLOT_H + report.NOTES_H,
                         report.WIDTH, 3)
    assert np.isfinite(img).all()


# ---- systemd units ------------------------------------------------------------------------
SYSTEMD = REPO / "systemd"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_units_verify(tmp: Path) -> None:
    bindir = Path(sys.executable).parent
    for name in ("alignd.service", "alignd-check.service", "alignd-check.timer"):
        text = (SYSTEMD / name).read_text()
        # verify checks that ExecStart exists: point it at this environment's commands
        text = text.replace("/usr/bin/alignd ", f"{bindir}/alignd ")
        text = text.replace("/usr/bin/alignctl ", f"{bindir}/alignctl ")
        (tmp / name).write_text(text)
    out = subprocess.run(["systemd-analyze", "verify", "--man=no",
                          *(str(tmp / n) for n in ("alignd.service", "alignd-check.service",
                                                   "alignd-check.timer"))],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stderr.strip() == "", out.stderr
    svc = (SYSTEMD / "alignd.service").read_text()
    for needed in ("Type=notify", "WatchdogSec=", "Restart=on-failure", "User=alignd",
                   "SupplementaryGroups=dialout video", "ProtectSystem=strict",
                   "DeviceAllow=char-ttyUSB rw", "DeviceAllow=char-video4linux rw",
                   "StateDirectory=alignd", "RuntimeDirectory=alignd"):
        assert needed in svc
    assert "PrivateDevices=yes" not in svc  # it would hide the serial ports and cameras
    check = (SYSTEMD / "alignd-check.service").read_text()
    assert "SuccessExitStatus=75" in check and "--started-by timer" in check


@pytest.mark.skipif(shutil.which("systemd-sysusers") is None
                    or shutil.which("systemd-tmpfiles") is None or os.getuid() != 0,
                    reason="needs systemd-sysusers/-tmpfiles and root (chown)")
def test_sysusers_and_tmpfiles_apply_to_a_scratch_root(tmp: Path) -> None:
    root = tmp / "root"
    (root / "etc").mkdir(parents=True)
    for f in ("passwd", "group", "shadow", "gshadow"):
        (root / "etc" / f).touch()
    for cmd, conf in ((["systemd-sysusers"], "alignd.sysusers.conf"),
                      (["systemd-tmpfiles", "--create"], "alignd.tmpfiles.conf")):
        out = subprocess.run([*cmd, f"--root={root}", "-"], input=(SYSTEMD / conf).read_text(),
                             capture_output=True, text=True, timeout=30)
        assert out.returncode == 0, out.stderr
    passwd = (root / "etc" / "passwd").read_text()
    assert passwd.startswith("alignd:") and "alignd-operators" in (root / "etc" / "group"
                                                                    ).read_text()
    uid = int(passwd.split(":")[2])
    st = (root / "var" / "lib" / "alignd").stat()
    assert st.st_uid == uid and oct(st.st_mode & 0o777) == "0o750"


def test_udev_rule_lines_are_well_formed() -> None:
    lines = [ln for ln in (SYSTEMD / "99-alignd.rules").read_text().splitlines()
             if ln.strip() and not ln.startswith("#")]
    assert lines
    for ln in lines:
        keys = [kv.strip() for kv in ln.split(",")]
        assert all(("==" in kv) or ("+=" in kv) or ("=" in kv) for kv in keys), ln
        assert 'SYMLINK+="alignd/' in ln and ("GROUP=\"dialout\"" in ln or
                                               "GROUP=\"video\"" in ln)


# ---- reset re-reads the config (issue 9) ----------------------------------------------------
def test_reset_rereads_the_config_and_a_bad_file_keeps_the_old_one(
        capsys: pytest.CaptureFixture, tmp: Path) -> None:
    import yaml

    path = tmp / "rig.yaml"
    data = yaml.safe_load(SIM_CONFIG.read_text())
    path.write_text(yaml.safe_dump(data))
    opened: list[object] = []

    def factory(cfg: object) -> FakeRig:
        opened.append(cfg)
        return FakeRig()

    for env in make_env(config_path=path, rig_factory=factory):
        wait_until(lambda env=env: env.daemon.state == "idle")
        first = env.client.status()
        # the operator fixes the config (a tolerance, the name) and resets
        data["name"], data["procedure"]["tolerance_um"] = "rig-B", 7.5
        path.write_text(yaml.safe_dump(data))
        assert ctl(env.sock, "reset") == 0
        assert "reloaded" in capsys.readouterr().out
        wait_until(lambda env=env: env.daemon.state == "idle")
        st = env.client.status()
        assert st["name"] == "rig-B" and st["config_hash"] != first["config_hash"]
        assert len(opened) == 2 and opened[-1].procedure.tolerance_um == 7.5  # type: ignore
        run_id = env.client.start("check")["run_id"]
        env.gate.set()
        run = env.client.run(follow(env.client, run_id)["run_id"])
        assert run["config_hash"] == st["config_hash"] and run["config"]["name"] == "rig-B"
        # a bad file: the reset is refused, naming file and key; the config stays
        data["procedure"]["tolerance_uum"] = 5.0
        path.write_text(yaml.safe_dump(data))
        assert ctl(env.sock, "reset") == 2
        err = capsys.readouterr().err
        assert "reset refused" in err and str(path) in err
        assert "procedure.tolerance_uum" in err and "keeps the config it has" in err
        assert "Traceback" not in err
        st2 = env.client.status()
        assert st2["state"] == "idle" and st2["config_hash"] == st["config_hash"]
        assert len(opened) == 2  # the rig was not touched


# ---- a full disk (issue 9): a real small file system, in a mount namespace --------------------
def _spawn_on_small_disk(tmp: Path, config: Path, size: str) -> subprocess.Popen[str]:
    """The fake-rig daemon with its state directory on a ``size`` tmpfs of its own."""
    disk = tmp / "disk"
    disk.mkdir()
    return subprocess.Popen(
        ["unshare", "-m", "sh", "-c", 'mount -t tmpfs -o size="$0" tmpfs "$1" && shift && '
         'exec "$@"', size, str(disk), sys.executable, str(FAKES), "fill", "--config",
         str(config), "--socket", str(tmp / "s.sock"), "--state-dir", str(disk / "state"),
         "--stop-timeout", "5"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _small_camera_config(tmp: Path) -> Path:
    import yaml

    data = yaml.safe_load(SIM_CONFIG.read_text())
    for cam in data["cameras"]:
        cam.update(width=64, height=48)  # a run needs ~0.6 MiB of frames + 4 MiB of records
    path = tmp / "small.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


needs_mount = pytest.mark.skipif(not _can_mount(), reason="needs a mount namespace "
                                 "(CAP_SYS_ADMIN) for a small real file system")


@needs_mount
def test_disk_full_mid_run_still_records_the_runs_end_and_runs_resume_with_space(
        tmp: Path, capsys: pytest.CaptureFixture) -> None:
    proc = _spawn_on_small_disk(tmp, _small_camera_config(tmp), "12m")
    client = Client(tmp / "s.sock", timeout_s=10.0)
    try:
        wait_ready(client, proc)
        assert client.status()["runs_refused"] is None
        run_id = client.start("align")["run_id"]  # records frames until the disk is full
        out = follow(client, run_id)
        assert out["status"] == "finished" and out["verdict"] == "fault"
        run = client.run(run_id)
        assert run["status"] == "finished" and run["verdict"] == "fault"
        assert "No space left on device" in run["reason"] or "disk is full" in run["reason"]
        assert len(run["frames"]) > 50  # it did fill the disk
        # a run cut off mid-motion faults the daemon (as any fault does: reset to go on);
        # status also says that runs are refused for lack of space, and why
        st = client.status()
        assert st["state"] == "fault" and "disk nearly full" in st["runs_refused"]
        assert ctl(str(tmp / "s.sock"), "reset") == 0
        wait_until(lambda: client.status()["state"] == "idle")
        assert ctl(str(tmp / "s.sock"), "check") == 3
        assert "disk nearly full" in capsys.readouterr().err
        assert ctl(str(tmp / "s.sock"), "status") == 0
        assert "state: idle; runs refused: " in capsys.readouterr().out
        # space comes back (the filler and the frames are removed): runs are accepted again
        disk = Path(f"/proc/{proc.pid}/root{tmp}/disk")  # the daemon's mounts
        (disk / "filler").unlink()
        for sub in (disk / "state" / "frames").iterdir():
            if sub.is_dir():
                shutil.rmtree(sub)
        wait_until(lambda: client.status()["runs_refused"] is None)
        check = follow(client, client.start("check")["run_id"])
        assert check["verdict"] == "within_tolerance"
        assert [r["status"] for r in client.history()] == ["finished", "finished"]
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert "released the 4 MiB reserve to record the end of run 1" in err


@needs_mount
def test_too_little_space_at_start_answers_status_with_the_reason(
        tmp: Path, capsys: pytest.CaptureFixture) -> None:
    proc = _spawn_on_small_disk(tmp, SIM_CONFIG, "12m")  # a run may need 236 MiB of frames
    client = Client(tmp / "s.sock", timeout_s=10.0)
    try:
        wait_ready(client, proc)  # it started (it used to exit with 3)
        refused = client.status()["runs_refused"]
        assert "disk nearly full" in refused and "a run needs at least 236 MiB" in refused
        assert ("200 top frames of 1280x720x1 bytes and 64 side frames of 1280x720x1 bytes "
                "(keep_frames all)") in refused
        assert ctl(str(tmp / "s.sock"), "align") == 3
        assert "a run needs at least 236 MiB" in capsys.readouterr().err
        assert client.history() == []
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
