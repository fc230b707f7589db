"""The daemon process and alignctl: start-up refusals, SIGTERM and SIGKILL mid-run,
sd_notify, CLI output and exit codes, atomic reports, and the systemd units."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
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
                          "--socket", str(tmp / "s")], rig_factory=FakeRig, procedures={})
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
def _recv_all(sock: socket.socket) -> list[str]:
    msgs = []
    while True:
        try:
            msgs.append(sock.recv(4096).decode())
        except BlockingIOError:
            return msgs


def test_sigterm_mid_run_aborts_records_and_exits_in_time(tmp: Path) -> None:
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(tmp / "notify"))
    notify.setblocking(False)
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
        msgs = "\n".join(_recv_all(notify))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        notify.close()
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
                                "--state-dir", str(tmp / "state")], rig_factory=FakeRig,
                               procedures={}) == 3
        assert "another alignd is using this state directory" in capsys.readouterr().err
        assert daemon_mod.main(["--config", str(SIM_CONFIG), "--socket", str(tmp / "s.sock"),
                                "--state-dir", str(tmp / "other")], rig_factory=FakeRig,
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
        assert "[sweep] iteration 1 step 1/5" in err and "offset 854.4 ± 5.0 um" in err
        assert alignctl(["check", "--socket", env.sock]) == 1  # --socket after the command
        out, _ = capsys.readouterr()
        assert "run 2: out_of_tolerance" in out and "offset     53.4 ± 5.0 um" in out
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
        assert img.shape == (report.HEADER_H + 540 + report.VERDICT_H + report.PLOT_H,
                         report.WIDTH, 3)
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
    assert img.shape == (report.HEADER_H + 540 + report.VERDICT_H + report.PLOT_H,
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
