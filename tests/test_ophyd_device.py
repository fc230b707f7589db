"""Issue 14 (optional extra): alignd as an ophyd-async device, driven by a Bluesky
RunEngine against the real daemon on the simulated rig. Skips when the ``bluesky`` extra
is not installed (``pip install -e '.[bluesky]'``)."""

from __future__ import annotations

import threading
import time
from typing import Any

import pytest
from faults_support import sim_daemon

pytest.importorskip("ophyd_async", reason="the bluesky extra is not installed")
pytest.importorskip("bluesky", reason="the bluesky extra is not installed")

from bluesky import RunEngine
from bluesky import plans as bp
from bluesky.run_engine import call_in_bluesky_event_loop
from bluesky.utils import FailedStatus

from alignd.client import Client
from alignd.ophyd_device import AligndDevice


@pytest.fixture(scope="module")
def engine() -> Any:
    RE = RunEngine({}, call_returns_result=True)
    yield RE


def test_count_triggers_a_check_and_reads_its_result(engine: Any) -> None:
    with sim_daemon() as dp:
        dev = AligndDevice(dp.sock, kind="check", name="alignd")
        call_in_bluesky_event_loop(dev.connect())
        docs: list[tuple[str, dict[str, Any]]] = []
        engine(bp.count([dev], num=2), lambda name, doc: docs.append((name, doc)))
        events = [d for n, d in docs if n == "event"]
        assert len(events) == 2
        runs = {r["id"]: r for r in Client(dp.sock).history()}
        for ev in events:
            data = ev["data"]
            run = runs[data["alignd-run_id"]]
            assert run["kind"] == "check"
            assert data["alignd-verdict"] == run["verdict"]
            assert data["alignd-offset_um"] == pytest.approx(run["offset_norm_um"])
            assert data["alignd-uncertainty_um"] == pytest.approx(run["U_um"])
            assert data["alignd-within_tolerance"] == (run["verdict"] == "within_tolerance")
        desc = next(d for n, d in docs if n == "descriptor")
        assert desc["data_keys"]["alignd-offset_um"]["units"] == "um"
        assert sorted(runs) == [1, 2]


def test_stop_aborts_the_run_and_the_trigger_fails(engine: Any) -> None:
    with sim_daemon(time_scale=20.0, procedure={}) as dp:
        dev = AligndDevice(dp.sock, kind="align", name="alignd")
        call_in_bluesky_event_loop(dev.connect())
        client = Client(dp.sock)

        def abort_when_running() -> None:  # the operator's Ctrl-C, from another thread
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                st = client.status()
                if st["state"] == "aligning" and (st.get("progress") or {}).get("phase"):
                    call_in_bluesky_event_loop(dev.stop())
                    return
                time.sleep(0.02)

        t = threading.Thread(target=abort_when_running)
        t.start()
        with pytest.raises(FailedStatus):
            engine(bp.count([dev]))
        t.join(timeout=60)
        run = client.history(1)[0]
        assert run["kind"] == "align" and run["verdict"] == "aborted"
        assert "aborted by" in run["reason"]
        assert dev.last_result is not None and dev.last_result.verdict == "aborted"
