"""Issue 14: the read-only web dashboard and /metrics, against the real daemon on the
simulated rig (a subprocess), and in a real browser (headless Chromium through selenium).

The browser test saves screenshots under ``out/screens/``. It skips, saying why, only when
Chromium, chromedriver or selenium cannot be found (``make test`` installs them when it
can). Every wait is on a condition with a generous bound, never a fixed sleep.
"""

from __future__ import annotations

import json
import shutil
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from faults_support import SIM_YAML, sim_daemon

from alignd.errors import ConfigError
from alignd.web.server import parse_address, run_csv

REPO = Path(__file__).resolve().parents[1]
SCREENS = REPO / "out" / "screens"
WEB = ["--web", "127.0.0.1:0"]
REAL = {"FAULTS_TOOLS": "real"}  # rendered cameras and the real vision


def get(url: str) -> tuple[int, dict[str, str], bytes]:
    try:
        with urllib.request.urlopen(url, timeout=20) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


def post(url: str) -> tuple[int, bytes]:
    req = urllib.request.Request(url, data=b"{}", method="POST")
    try:
        with urllib.request.urlopen(req, timeout=20) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def until(pred: Callable[[], Any], timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = pred()
        if got:
            return got
        time.sleep(0.05)
    raise AssertionError(f"not within {timeout_s} s: {what}")


@pytest.fixture(scope="module")
def rig() -> Iterator[Any]:
    """The sim daemon with the dashboard on an ephemeral port; one check already done."""
    with sim_daemon(time_scale=200.0, args=WEB, env=REAL) as dp:
        st = dp.client.status()
        assert st["web"] and st["web"].startswith("http://127.0.0.1:"), st
        dp.url = st["web"]  # type: ignore[attr-defined]
        dp.first = dp.run_and_wait("check")  # type: ignore[attr-defined]
        yield dp


def test_address_parsing() -> None:
    assert parse_address("0.0.0.0:8080") == ("0.0.0.0", 8080)
    assert parse_address(":9100") == ("127.0.0.1", 9100)
    assert parse_address("8080") == ("127.0.0.1", 8080)
    assert parse_address("[::1]:80") == ("::1", 80)
    with pytest.raises(ConfigError, match="HOST:PORT"):
        parse_address("localhost:http")


def test_read_only_refuses_every_change(rig: Any) -> None:
    for path in ("api/status", "align", "check", "abort", "reset"):
        code, body = post(rig.url + path)
        assert code == 405, (path, code)
        assert "read-only" in json.loads(body)["message"]
        assert "alignctl" in json.loads(body)["message"]
    assert rig.client.status()["state"] == "idle"  # nothing started
    assert len(rig.client.history(10)) == 1


def test_json_views_and_downloads(rig: Any) -> None:
    run_id = rig.first["id"]
    code, _, body = get(rig.url + "api/status")
    st = json.loads(body)
    assert code == 200 and st["state"] == "idle" and st["dashboard"]["read_only"] is True
    code, headers, body = get(rig.url + f"runs/{run_id}.json")
    assert code == 200 and "attachment" in headers["Content-Disposition"]
    assert json.loads(body)["result"]["verdict"] == rig.first["verdict"]
    code, headers, body = get(rig.url + f"runs/{run_id}.csv")
    lines = body.decode().splitlines()
    assert lines[0].startswith("run,sweep,kind,iteration,frame,commanded_deg,readback_deg")
    n_frames = sum(len(s["sweep"]["frames"]) for s in rig.first["sweeps"])
    assert len(lines) == 1 + 4 * n_frames  # one row per frame and corner
    code, headers, body = get(rig.url + f"runs/{run_id}/report.png")
    assert code == 200 and body[:8] == b"\x89PNG\r\n\x1a\n"
    assert get(rig.url + "runs/999.json")[0] == 404
    assert get(rig.url + "nope")[0] == 404


def test_live_view_is_the_workers_grab_with_overlays(rig: Any) -> None:
    def view() -> dict[str, Any] | None:
        code, headers, body = get(rig.url + "live/top.jpg")
        if code != 200:
            return None
        assert body[:2] == b"\xff\xd8"  # JPEG
        return json.loads(headers["X-Alignd-View"])

    first = until(view, 30, "a live top frame")
    # watched and idle: the worker keeps grabbing (a newer frame arrives)
    later = until(lambda: (v := view()) and v["seq"] > first["seq"] and v, 30, "a newer frame")
    assert later["holder"] == "tracked"
    assert later["centre_run"] == rig.first["id"]  # the check measured the centre
    assert get(rig.url + "live/nosuch.jpg")[0] == 404


def _samples(text: str) -> dict[str, float]:
    from prometheus_client.parser import text_string_to_metric_families

    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            labels = ",".join(f'{k}="{v}"' for k, v in sorted(s.labels.items()))
            out[f"{s.name}{{{labels}}}" if labels else s.name] = s.value
    return out


def test_metrics_in_prometheus_format(rig: Any) -> None:
    code, headers, body = get(rig.url + "metrics")
    assert code == 200 and headers["Content-Type"].startswith("text/plain")
    m = _samples(body.decode())
    assert m['alignd_state{state="idle"}'] == 1.0 and m['alignd_state{state="fault"}'] == 0.0
    verdict = rig.first["verdict"]
    assert m[f'alignd_runs_total{{kind="check",verdict="{verdict}"}}'] >= 1.0
    assert m['alignd_last_offset_um{kind="check"}'] == pytest.approx(
        rig.first["result"]["offset_norm_um"])
    assert m['alignd_last_uncertainty_um{kind="check"}'] == pytest.approx(
        rig.first["result"]["U_um"])
    assert m['alignd_last_run_timestamp_seconds{kind="check"}'] > 1.7e9
    assert m["alignd_faults_total"] == 0.0
    assert m["alignd_last_run_solve_seconds"] > 0.0
    assert m["alignd_frame_grab_seconds_count"] >= len(rig.first["sweeps"][0]["sweep"]["frames"])


def test_run_csv_marks_missed_corners_empty() -> None:
    run = {"id": 5, "sweeps": [{"kind": "check", "iteration": 1, "commanded": [1.0],
                                "sweep": {"frames": [{"angle_deg": 1.0005,
                                                      "features": [[1.5, 2.5], None]}]}}]}
    assert run_csv(run).splitlines()[1:] == ["5,0,check,1,0,1,1.0005,0,1.5,2.5",
                                             "5,0,check,1,0,1,1.0005,1,,"]


# ---- the real browser -----------------------------------------------------------------------
def _browser() -> Any:
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed (pip install -e '.[dev]')")
    binary = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not binary or not driver:
        pytest.skip("headless Chromium not found: apt-get install chromium chromium-driver "
                    "(make test does this when run as root)")
    opts = webdriver.ChromeOptions()
    opts.binary_location = binary
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
              "--window-size=1400,1000"):
        opts.add_argument(a)
    return webdriver.Chrome(service=Service(driver), options=opts)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    d = _browser()
    SCREENS.mkdir(parents=True, exist_ok=True)
    try:
        yield d
    finally:
        d.quit()


def _text(d: Any, css: str) -> str:
    from selenium.webdriver.common.by import By

    return str(d.find_element(By.CSS_SELECTOR, css).text)


def _wait(d: Any, pred: Callable[[Any], Any], what: str, timeout_s: float = 60.0) -> Any:
    from selenium.webdriver.support.ui import WebDriverWait

    try:
        return WebDriverWait(d, timeout_s, poll_frequency=0.05).until(pred)
    except Exception as exc:
        d.save_screenshot(str(SCREENS / "failed.png"))
        raise AssertionError(f"browser: {what} not within {timeout_s} s") from exc


def test_browser_dashboard_watches_a_run(browser: Any) -> None:
    d = browser
    # The check's one sweep turns +-45 deg in 11 steps of 9 deg. In real time (time scale
    # 1) each step's motion alone takes 0.45 s at 20 deg/s, so the page (it polls every
    # 0.5 s) sees most steps however fast the machine is; at time scale 10 the steps were
    # as short as the frame processing, and a faster machine once showed only two.
    with sim_daemon(time_scale=1.0, procedure={"max_iterations": 1}, args=WEB,
                    env=REAL) as dp:
        url = dp.client.status()["web"]
        d.get(url)
        _wait(d, lambda d: _text(d, "#state") == "idle", "state idle")
        _wait(d, lambda d: "holder tracked" in _text(d, "#cam-top figcaption"),
              "the live top view with the tracked holder")
        assert "alignd" in d.title and "reference-sim" in _text(d, "#title")
        assert "read-only" in _text(d, "header")
        d.save_screenshot(str(SCREENS / "dashboard-idle.png"))

        run_id = dp.client.start("check")["run_id"]
        _wait(d, lambda d: _text(d, "#state") == "checking", "state checking")
        _wait(d, lambda d: f"run {run_id}" in _text(d, "#run-title"), "the run's title")
        seen: set[str] = set()

        def steps_advance(d: Any) -> bool:
            step = _text(d, "#progress-step")
            if "/" in step:
                seen.add(step)
            return len(seen) >= 3

        _wait(d, steps_advance, "three different sweep steps shown", 120)
        d.save_screenshot(str(SCREENS / "dashboard-running.png"))
        _wait(d, lambda d: _text(d, "#state") == "idle", "the run's end", 180)
        _wait(d, lambda d: f"run {run_id}" in _text(d, "#last-run"), "the last run")
        run = dp.client.run(run_id)
        assert run["verdict"] in _text(d, "#last-run")
        _wait(d, lambda d: f"centre from run {run_id}" in _text(d, "#cam-top figcaption"),
              "the measured centre on the live view")
        _wait(d, lambda d: " deg" in _text(d, "#devices") and "homed" in _text(d, "#devices"),
              "the turntable's read-back position and homed state")
        d.save_screenshot(str(SCREENS / "dashboard-after-check.png"))

        d.get(url + "history")
        _wait(d, lambda d: d.find_elements("css selector", "#trend svg circle.pt"),
              "the trend chart's point")
        assert d.find_elements("css selector", "#tolerance-line")
        assert str(run_id) in _text(d, "#runs-table tbody")
        d.save_screenshot(str(SCREENS / "history.png"))

        d.get(url + f"run/{run_id}")
        _wait(d, lambda d: run["verdict"] in _text(d, "#run-verdict"), "the run's verdict")
        _wait(d, lambda d: d.execute_script(
            "const i = document.querySelector('#report-img'); "
            "return i.complete && i.naturalWidth > 0"), "the report figure")
        assert "µm" in _text(d, "#run-summary")
        hrefs = [e.get_attribute("href") for e in d.find_elements(
            "css selector", "#download-json, #download-csv")]
        assert hrefs == [url + f"runs/{run_id}.json", url + f"runs/{run_id}.csv"]
        d.save_screenshot(str(SCREENS / "run.png"))


def test_browser_shows_a_faulted_daemon_without_cameras(browser: Any, tmp_path: Path) -> None:
    d = browser
    data = yaml.safe_load(SIM_YAML.read_text())
    data["controllers"][0]["port"] = "socket://127.0.0.1:9"  # nothing listens: cannot open
    with sim_daemon(controllers=data["controllers"], args=WEB, env=REAL) as dp:
        st = dp.wait_state("fault")
        d.get(st["web"])
        _wait(d, lambda d: _text(d, "#state") == "fault", "state fault")
        assert "cannot open the rig" in _text(d, "#fault")
        assert "alignctl reset" in _text(d, "#fault")
        _wait(d, lambda d: "cannot open the rig" in _text(d, "#cam-top .none"),
              "the camera view saying why there is no frame")
        d.save_screenshot(str(SCREENS / "dashboard-fault.png"))


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="no systemd-analyze")
def test_metrics_textfile_units_verify(tmp_path: Path) -> None:
    import subprocess

    names = ["alignd-metrics-textfile.service", "alignd-metrics-textfile.timer"]
    for n in names:
        (tmp_path / n).write_text((REPO / "systemd" / n).read_text())
    out = subprocess.run(["systemd-analyze", "verify", "--man=no",
                          *(str(tmp_path / n) for n in names)],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stderr.strip() == "", out.stderr
    svc = (REPO / "systemd" / names[0]).read_text()
    assert "http://127.0.0.1:8080/metrics" in svc and "mv " in svc  # atomic rename


def test_connections_are_capped_and_idle_ones_dropped(rig: Any) -> None:
    import socket

    from alignd.web.server import MAX_CONNECTIONS

    host, port = parse_address(rig.url.removeprefix("http://").rstrip("/"))
    idle = []
    for _ in range(MAX_CONNECTIONS):  # clients that connect and send nothing
        s = socket.create_connection((host, port), timeout=10)
        idle.append(s)

    def refused() -> bool:
        with socket.create_connection((host, port), timeout=10) as s:
            s.settimeout(10)
            return s.recv(100).startswith(b"HTTP/1.1 503")

    assert until(refused, 30, "one connection too many is refused")
    for s in idle:
        s.close()
    assert until(lambda: get(rig.url + "api/status")[0] == 200, 30, "the dashboard again")


def test_a_bad_web_address_is_a_usage_error(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    from alignd import daemon

    rc = daemon.main(["--config", str(SIM_YAML), "--socket", str(tmp_path / "s.sock"),
                      "--state-dir", str(tmp_path / "state"), "--web", "localhost:http"],
                     rig_factory=lambda: None)
    assert rc == 2
    err = capsys.readouterr().err
    assert "web address 'localhost:http'" in err and "HOST:PORT" in err
    assert not (tmp_path / "s.sock").exists()  # nothing left listening
