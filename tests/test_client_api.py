"""Issue 14: the supported Python API (``alignd.client``) and its example script, against
the real daemon on the simulated rig."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from faults_support import sim_daemon

from alignd.client import ApiError, Client, Event, RunResult

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "docs" / "examples" / "measure_sequence.py"


def test_run_result_from_the_contract_json() -> None:
    r = RunResult.from_json({"run_id": 4, "verdict": "within_tolerance", "offset_um": [3.0, -4.0],
                             "offset_norm_um": 5.0, "U_um": 2.5, "iterations": 1,
                             "tilt_deg": None, "yaw_deg": 0.5, "reason": "ok"})
    assert r.ok and r.offset_um == (3.0, -4.0) and r.U_um == 2.5 and r.tilt_deg is None
    bad = RunResult.from_json({"run_id": 5, "verdict": "fault", "offset_um": None})
    assert not bad.ok and bad.offset_um is None and bad.iterations == 0
    ev = Event.from_json({"seq": 3, "run_id": 4, "type": "progress", "t": 1.0,
                          "phase": "sweep", "step": 2, "total": 21, "iteration": 1})
    assert str(ev) == "[sweep] iteration 1 step 2/21"


def test_check_align_progress_status_history() -> None:
    with sim_daemon() as dp:
        client = Client(dp.sock)
        events: list[Event] = []
        check = client.check(on_event=events.append)
        assert isinstance(check, RunResult) and check.run_id == 1
        assert check.verdict in ("within_tolerance", "out_of_tolerance")
        assert events[0].type == "state" and events[-1].type == "end"
        assert events[-1].verdict == check.verdict
        sweeps: list[list[int]] = []
        for e in events:  # a check may take more than one sweep (measuring better)
            if e.type == "progress" and e.phase == "sweep" and e.step is not None:
                if e.step == 1 or not sweeps:
                    sweeps.append([])
                sweeps[-1].append(e.step)
        assert sweeps and all(s == sorted(s) and len(s) >= 5 for s in sweeps)  # in order
        run_id = client.align(wait=False)
        assert run_id == 2 and client.status()["run_id"] == 2
        with pytest.raises(ApiError) as busy:
            client.check()
        assert busy.value.code == "busy"
        seen = list(client.progress(run_id))
        assert seen[-1].type == "end"
        result = client.result(run_id)
        assert result.verdict == seen[-1].verdict and result.iterations >= 1
        assert [r["id"] for r in client.history()] == [2, 1]
        assert client.status()["state"] == "idle"


def test_example_sequence_checks_before_each_sample_and_aligns_when_needed() -> None:
    with sim_daemon(procedure={}) as dp:  # the reference procedure: 21 steps, 4 iterations
        out = subprocess.run([sys.executable, str(EXAMPLE), "--socket", str(dp.sock),
                              "--samples", "2"], capture_output=True, text=True, timeout=300,
                             cwd=REPO)
        assert out.returncode == 0, out.stdout + out.stderr
        lines = [ln for ln in out.stdout.splitlines() if ln.startswith("sample")]
        kinds = [r["kind"] for r in reversed(Client(dp.sock).history())]
        runs = [r for r in reversed(Client(dp.sock).history())]
    # every sample: a check first; an alignment exactly when that check failed; then measured
    assert sum(ln.endswith("measuring") for ln in lines) == 2
    i = 0
    for n in (1, 2):
        assert runs[i]["kind"] == "check"
        assert re.match(rf"sample {n}: check \(run {runs[i]['id']}\): ", lines.pop(0))
        if runs[i]["verdict"] not in ("aligned", "within_tolerance"):
            i += 1
            assert runs[i]["kind"] == "align" and runs[i]["verdict"] == "aligned"
            assert lines.pop(0).startswith(f"sample {n}: align (run {runs[i]['id']}): aligned")
        assert lines.pop(0) == f"sample {n}: measuring"
        i += 1
    assert i == len(kinds)
    # the simulated world starts mm off the axis: the first check fails, so it aligned
    assert kinds[:2] == ["check", "align"]
