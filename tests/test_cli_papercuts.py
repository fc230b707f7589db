"""Issue 14: alignctl papercuts: negative-number lists, units, "µm" where the terminal can
show it, no repeated outcome lines, no empty "s/n"/"fw" fields, status with axes."""

from __future__ import annotations

import io

import pytest

from alignd.cli import build_parser, join_negative_values
from alignd.cli.daemon_cmds import progress_text, repeats_result, status_text
from alignd.textfmt import identity_text, micro, with_micro


def test_angles_may_start_with_a_minus() -> None:
    argv = ["analyze", "top", "a.png", "b.png", "--angles", "-10,-9.5", "--json"]
    with pytest.raises(SystemExit):  # what argparse alone does with it (the bug)
        build_parser().parse_args(argv)
    args = build_parser().parse_args(join_negative_values(argv))
    assert args.angles == [-10.0, -9.5] and args.json and args.images == ["a.png", "b.png"]
    assert join_negative_values(["--angles", "-.5,1"]) == ["--angles=-.5,1"]
    assert join_negative_values(["--angles", "--json"]) == ["--angles", "--json"]
    assert join_negative_values(["--angles"]) == ["--angles"]


def test_micro_sign_only_where_the_stream_can_encode_it() -> None:
    utf8 = io.TextIOWrapper(io.BytesIO(), encoding="utf-8")
    ascii_ = io.TextIOWrapper(io.BytesIO(), encoding="ascii")
    latin1 = io.TextIOWrapper(io.BytesIO(), encoding="latin-1")
    assert micro(utf8) == "µm" and micro(latin1) == "µm" and micro(ascii_) == "um"
    assert with_micro("offset 1.0 ± 2.0 um", utf8) == "offset 1.0 ± 2.0 µm"
    assert with_micro("offset 1.0 um", ascii_) == "offset 1.0 um"


def test_identity_leaves_out_what_the_device_did_not_report() -> None:
    assert identity_text({"vendor": "Newport", "model": "SMC100CC", "serial": "",
                          "firmware": "3.1.2", "stage": "URS75BCC"}) == \
        "Newport SMC100CC fw 3.1.2 (URS75BCC)"
    assert identity_text({"vendor": "Zaber", "model": "X-LSM050A", "serial": "91302",
                          "firmware": "7.38", "stage": "X-LSM050A"}) == \
        "Zaber X-LSM050A s/n 91302 fw 7.38"


def test_status_shows_positions_with_units_homed_state_and_cameras() -> None:
    st = {"state": "idle", "name": "rig", "version": "0.1", "socket": "/tmp/s",
          "web": "http://127.0.0.1:8080/",
          "last_run": {"id": 4, "kind": "align", "verdict": "aborted",
                       "reason": "aborted by root"},
          "devices": {"turntable": {"vendor": "Newport", "model": "SMC100CC", "serial": "",
                                    "firmware": "3.1.2"},
                      "x": {"vendor": "Zaber", "model": "X-LSM050A", "serial": "91302",
                            "firmware": "7.38"}},
          "axes": {"turntable": {"position": -3.25, "units": "deg", "homed": True,
                                 "age_s": 3.0},
                   "x": {"position": None, "units": "mm", "homed": None, "age_s": None}},
          "cameras": {"top": {"state": "ok", "fps": 4.0}}}
    text = status_text(st)
    assert "last run: 4 (align) aborted: aborted by root" in text
    lines = text.splitlines()
    tt = next(ln for ln in lines if ln.strip().startswith("turntable"))
    assert "-3.250 deg (read 3 s ago)" in tt and "homed" in tt and "s/n" not in tt
    x = next(ln for ln in lines if ln.strip().startswith("x "))
    assert "position not read yet" in x and "homed ?" in x and "s/n 91302 fw 7.38" in x
    assert "dashboard: http://127.0.0.1:8080/ (read-only)" in text
    assert "camera top    ok          source ? (fps 4.0)" in text


def test_the_outcome_is_printed_once() -> None:
    assert repeats_result({"type": "end", "verdict": "aborted"})
    assert repeats_result({"type": "progress", "phase": "done", "message": "aborted: x"})
    assert repeats_result({"type": "event", "msg": "align finished: aborted: x"})
    assert not repeats_result({"type": "event", "msg": "pre-check: sample tilt +0.3 deg"})
    assert not repeats_result({"type": "progress", "phase": "sweep", "step": 3})


def test_a_progress_line_names_the_offset_once() -> None:
    ev = {"type": "progress", "phase": "solve", "iteration": 1,
          "message": "check 1: offset 2571.0 ± 10.1 um (centre sigma 2.2 um)",
          "offset_norm_um": 2571.0, "U_um": 10.1}
    assert progress_text(ev).count("offset") == 1
    ev["message"] = "solving"
    assert progress_text(ev).endswith("solving offset 2571.0 ± 10.1 " + micro())
