"""alignctl commands that talk to the daemon: status, align, check, commission, abort, reset,
history, report.

Human output by default, ``--json`` for scripts (``align``/``check`` print the run-result
JSON as the final stdout line). Live progress goes to stderr. Exit codes (contract):
0 aligned / within tolerance, 1 out of tolerance / not converged / aborted, 2 usage, config
or permission, 3 fault, busy or daemon unreachable. Only for ``--started-by timer``: 75
(EX_TEMPFAIL) when the daemon refuses the run because it is busy, starting or faulted, so
a scheduled check is reported as *skipped*, not failed (alignd-check.service accepts 75).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from alignd.client import ApiError, Client, DaemonUnreachable, resolve_socket
from alignd.procedures.commission import COMMISSION_EXIT
from alignd.procedures.result import EXIT_CODES
from alignd.textfmt import identity_text, micro, with_micro

EXIT_OK, EXIT_OUT_OF_TOLERANCE, EXIT_USAGE, EXIT_FAULT = 0, 1, 2, 3
EXIT_SKIPPED = 75  # EX_TEMPFAIL, --started-by timer only: busy/starting/faulted -> skipped
VERDICT_EXIT = {**EXIT_CODES, **COMMISSION_EXIT,
                "interrupted": EXIT_FAULT}  # interrupted: a record-only verdict


def exit_code(result: dict[str, Any] | None) -> int:
    """The contract exit code for a run result."""
    if not result:
        return EXIT_FAULT
    verdict = str(result.get("verdict"))
    if verdict == "fault" and result.get("config_error"):
        return EXIT_USAGE
    return VERDICT_EXIT.get(verdict, EXIT_FAULT)


def register(sub: argparse._SubParsersAction) -> None:
    """Add this module's subcommands."""

    def add(name: str, help_: str, func: Any) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("--socket", default=argparse.SUPPRESS, metavar="PATH",
                       help="daemon socket (default: $ALIGND_SOCKET, else "
                       "/run/alignd/alignd.sock)")
        p.add_argument("--json", action="store_true", help="machine-readable output")
        p.set_defaults(func=func)
        return p

    add("status", "show the daemon's state and the progress of a run", cmd_status)
    commands = {"align": cmd_align, "check": cmd_check, "commission": cmd_commission}
    for kind, help_ in (("align", "align the sample onto the rotation axis (closed loop)"),
                        ("check", "measure the offset without moving the sample"),
                        ("commission", "measure the rig's conventions once (turntable "
                         "direction, scale, runout; axes; cameras; holder); align and "
                         "check use the record")):
        p = add(kind, help_, commands[kind])
        p.add_argument("--started-by", default="user", choices=["user", "timer"],
                       help="recorded with the run; 'timer' also turns a refusal because "
                       f"the daemon is busy or faulted into a skip (exit {EXIT_SKIPPED})")
        p.add_argument("--detach", action="store_true",
                       help="start the run and return at once (prints the run id)")
        p.add_argument("--wait-ready", type=float, default=60.0, metavar="S",
                       help="wait this long for a daemon still connecting its hardware "
                       "(default %(default)s)")
        p.add_argument("--quiet", "-q", action="store_true", help="no progress on stderr")
    add("abort", "abort the run in progress (all axes stop)", cmd_abort)
    add("reset", "reconnect the hardware after a fault", cmd_reset)
    p = add("history", "list recent runs", cmd_history)
    p.add_argument("--limit", "-n", type=int, default=20, help="how many (default %(default)s)")
    p = add("report", "write a run's report: PNG (top view, convergence, side view) and JSON",
            cmd_report)
    p.add_argument("run", type=int, metavar="RUN", help="run id (see alignctl history)")
    p.add_argument("--out", default=".", metavar="DIR", help="output directory (default .)")


def _client(args: argparse.Namespace) -> Client:
    return Client(resolve_socket(getattr(args, "socket", None)))


def _print_json(obj: Any) -> None:
    print(json.dumps(obj, sort_keys=False), flush=True)


def _fmt_offset(d: dict[str, Any]) -> str:
    norm, u = d.get("offset_norm_um"), d.get("U_um")
    if norm is None:
        return "-"
    um = micro()
    return f"{norm:.1f} ± {u:.1f} {um}" if u is not None else f"{norm:.1f} {um}"


def _fmt_position(v: float, units: str) -> str:
    return f"{v:.3f} deg" if units == "deg" else f"{v:.4f} {units}"


# ---- status -----------------------------------------------------------------------------------
def status_text(st: dict[str, Any]) -> str:
    from alignd.daemon import status_line

    lines = [f"alignd {st.get('version', '?')} '{st.get('name', '?')}' at "
             f"{st.get('socket') or '?'}",
             f"state: {with_micro(status_line(st))}"]
    last = st.get("last_run")
    if last:
        lines.append(f"last run: {last['id']} ({last['kind']}) {last['verdict']}"
                     + (f": {with_micro(last['reason'])}" if last.get("reason") else ""))
    com = st.get("commission")
    if isinstance(com, dict):
        lines.append(f"commission: {com.get('note')}")
    else:
        lines.append("commission: none recorded (run 'alignctl commission' once per rig)")
    if st.get("web"):
        lines.append(f"dashboard: {st['web']} (read-only)")
    devices = st.get("devices") or {}
    axes = st.get("axes") or {}
    if devices or axes:
        lines.append("axes:")
    for role in sorted(set(devices) | set(axes)):
        ident = devices.get(role)
        text = identity_text(ident) if isinstance(ident, dict) else "?"
        got = axes.get(role)
        ax: dict[str, Any] = got if isinstance(got, dict) else {}
        where = "position not read yet"
        if ax.get("position") is not None:
            where = _fmt_position(float(ax["position"]), str(ax.get("units") or ""))
            if ax.get("age_s") is not None:
                where += f" (read {_fmt_age(float(ax['age_s']))} ago)"
        homed = {True: "homed", False: "NOT homed"}.get(bool(ax["homed"]), "homed ?") \
            if isinstance(ax.get("homed"), bool) else "homed ?"
        lines.append(f"  {role:10s} {where:34s} {homed:9s}  {text}")
    for role, cam in sorted((st.get("cameras") or {}).items()):
        if isinstance(cam, dict):
            size = cam.get("size")
            what = f"{size[0]}x{size[1]}" if cam.get("state") == "ok" and size else \
                (cam.get("error") or "")
            extra = ", ".join(f"{k} {v}" for k, v in cam.items()
                              if k not in ("state", "source", "size", "error")
                              and v is not None and not isinstance(v, (dict, list)))
            lines.append(f"  camera {role:6s} {cam.get('state', '?'):11s} source "
                         f"{cam.get('source', '?')}" + (f": {what}" if what else "")
                         + (f" ({extra})" if extra else ""))
    for warning in st.get("warnings") or []:
        lines.append(f"  warning: {warning}")
    return "\n".join(lines)


def _fmt_age(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.0f} min" if s < 7200 else f"{s / 3600:.0f} h"


def cmd_status(args: argparse.Namespace) -> int:
    st = _client(args).status()
    if args.json:
        _print_json(st)
    else:
        print(status_text(st))
    return EXIT_FAULT if st.get("state") == "fault" else EXIT_OK


# ---- align / check ----------------------------------------------------------------------------
def progress_text(ev: dict[str, Any]) -> str:
    """One line of live progress for an event from ``GET /runs/ID/events``."""
    kind = ev.get("type")
    if kind == "progress":
        parts = [f"[{ev.get('phase', '?')}]"]
        if ev.get("iteration") is not None:
            parts.append(f"iteration {ev['iteration']}")
        if ev.get("step") is not None and ev.get("total") is not None:
            parts.append(f"step {ev['step']}/{ev['total']}")
        if ev.get("message"):
            parts.append(str(ev["message"]))
        if ev.get("offset_norm_um") is not None and "offset" not in str(ev.get("message")):
            parts.append(f"offset {_fmt_offset(ev)}")
        return " ".join(parts)
    if kind == "end":
        return f"[end] {ev.get('verdict')}" + (f": {ev['reason']}" if ev.get("reason") else "")
    level = ev.get("level")
    return f"[{level}] {ev.get('msg', '')}" if level and level != "info" else \
        f"[note] {ev.get('msg', '')}"


def commission_text(result: dict[str, Any]) -> str:
    """A commission record as a findings table: verdict, item, what was measured."""
    lines = [f"run {result.get('run_id')}: {result.get('verdict')}"
             + (f" ({result['reason']})" if result.get("reason") else "")]
    for f in result.get("findings") or []:
        if not isinstance(f, dict):
            continue
        mark = {"pass": "pass", "warn": "WARN", "fail": "FAIL"}.get(str(f.get("verdict")), "?")
        lines.append(f"  {mark:4s}  {f.get('item')!s:26s} {f.get('message', '')}")
    return "\n".join(lines)


def result_text(result: dict[str, Any]) -> str:
    if result.get("kind") == "commission":
        return commission_text(result)
    lines = [f"run {result.get('run_id')}: {result.get('verdict')}"
             + (f" ({result['reason']})" if result.get("reason") else "")]
    if result.get("offset_um") is not None:
        x, y = result["offset_um"]
        lines.append(f"  offset     {_fmt_offset(result)} (k = 2)  [x {x:.1f}, y {y:.1f} um]")
    moves = f"  moves      {result.get('iterations')}"
    if result.get("sweeps") is not None:
        moves += f", {result['sweeps']} sweep(s)"
    lines.append(moves)
    budget = result.get("budget")
    if isinstance(budget, dict):
        parts = ", ".join(f"{c['name']} {c['u_um']:.2f}" for c in budget.get("contributions", [])
                          if c.get("u_um") is not None)
        lines.append(f"  budget     u (um): {parts}; combined {budget['combined_um']:.2f}, "
                     f"U (k={budget['k']:g}) {budget['U_um']:.2f}")
    decision = result.get("decision")
    if isinstance(decision, dict):
        lines.append(f"  rule       {decision.get('rule_name')}")
    for key, label in (("tilt_deg", "tilt"), ("yaw_deg", "yaw")):
        if result.get(key) is not None:
            u = result.get("tilt_u_deg") if key == "tilt_deg" else None
            lines.append(f"  {label:10s} {result[key]:.3f} deg" if u is None else
                         f"  {label:10s} {result[key]:.4f} +- {u:.4f} deg (u, k = 1)")
    if result.get("eccentricity") is not None:
        ue = result.get("eccentricity_u")
        lines.append(f"  rim e      {result['eccentricity']:.4f}" + (
            "" if ue is None else f" +- {ue:.4f} (u, k = 1)") + " (top camera placement)")
    truth = result.get("truth")
    if isinstance(truth, dict) and truth.get("offset_norm_um") is not None:
        lines.append(f"  truth      {truth['offset_norm_um']:.1f} um (simulator, not used by "
                     "the loop)")
    return "\n".join(lines)


def repeats_result(ev: dict[str, Any]) -> bool:
    """Events that only repeat the outcome the run's result is about to print: the "done"
    phase, the recorded "<kind> finished: ..." note and the end event."""
    if ev.get("type") == "end":
        return True
    if ev.get("type") == "progress" and ev.get("phase") == "done":
        return True
    msg = str(ev.get("msg") or "")
    return ev.get("type") == "event" and msg.split(" finished: ", 1)[0] in ("align", "check")


class _ProgressPrinter:
    """Progress on stderr: sweep steps overwrite one line on a terminal."""

    def __init__(self, quiet: bool) -> None:
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self._open = False

    def __call__(self, ev: dict[str, Any]) -> None:
        if self.quiet or repeats_result(ev):
            return
        text = with_micro(progress_text(ev), sys.stderr)
        stepping = ev.get("type") == "progress" and ev.get("step") is not None
        if self.tty and stepping:
            sys.stderr.write("\r\x1b[K" + text)
            self._open = True
        else:
            if self._open:
                sys.stderr.write("\n")
                self._open = False
            sys.stderr.write(text + "\n")
        sys.stderr.flush()

    def close(self) -> None:
        if self._open and not self.quiet:
            sys.stderr.write("\n")
            self._open = False


def _start(client: Client, kind: str, args: argparse.Namespace) -> tuple[int | None, int]:
    """POST the run; returns (run_id, exit code if refused)."""
    deadline = time.monotonic() + max(0.0, args.wait_ready)
    timer = args.started_by == "timer"
    while True:
        try:
            return int(client.start(kind, args.started_by)["run_id"]), EXIT_OK
        except ApiError as exc:
            if exc.code == "starting" and time.monotonic() < deadline:
                time.sleep(0.5)
                continue
            if timer and exc.code in ("busy", "starting", "fault"):
                print(f"alignctl: {kind} skipped: {exc}", file=sys.stderr)
                return None, EXIT_SKIPPED
            if exc.code == "forbidden":
                print(f"alignctl: error: {exc}", file=sys.stderr)
                return None, EXIT_USAGE
            print(f"alignctl: error: {exc}", file=sys.stderr)
            return None, EXIT_FAULT


def follow(client: Client, run_id: int, on_event: Any, poll_s: float = 10.0
           ) -> dict[str, Any] | None:
    """Follow a run's live events until it ends; return its result. Ctrl-C once asks the
    daemon to abort the run (and keeps following so the outcome is shown); twice detaches."""
    after, aborted = 0, False
    while True:
        try:
            reply = client.events(run_id, after=after, wait_s=poll_s)
        except KeyboardInterrupt:
            if aborted:
                raise
            aborted = True
            print(f"\nalignctl: aborting run {run_id} (Ctrl-C again to detach)",
                  file=sys.stderr)
            try:
                client.abort()
            except (ApiError, DaemonUnreachable) as exc:
                print(f"alignctl: abort failed: {exc}", file=sys.stderr)
            continue
        for ev in reply.get("events", []):
            on_event(ev)
        after = int(reply.get("next", after))
        if reply.get("done"):
            return reply.get("result")


def _run_cmd(args: argparse.Namespace, kind: str) -> int:
    client = _client(args)
    run_id, code = _start(client, kind, args)
    if run_id is None:
        return code
    if args.detach:
        if args.json:
            _print_json({"run_id": run_id, "kind": kind})
        else:
            print(f"run {run_id} ({kind}) started")
        return EXIT_OK
    printer = _ProgressPrinter(args.quiet)
    try:
        result = follow(client, run_id, printer)
    except DaemonUnreachable as exc:
        printer.close()
        print(f"alignctl: lost contact with alignd during run {run_id}: {exc}",
              file=sys.stderr)
        return EXIT_FAULT
    finally:
        printer.close()
    if result is None:
        print(f"alignctl: run {run_id} ended without a result (interrupted?); see "
              f"'alignctl history'", file=sys.stderr)
        return EXIT_FAULT
    if args.json:
        _print_json(result)
    else:
        print(with_micro(result_text(result)))
    return exit_code(result)


def cmd_align(args: argparse.Namespace) -> int:
    return _run_cmd(args, "align")


def cmd_check(args: argparse.Namespace) -> int:
    return _run_cmd(args, "check")


def cmd_commission(args: argparse.Namespace) -> int:
    return _run_cmd(args, "commission")


# ---- abort / reset ---------------------------------------------------------------------------
def _control(args: argparse.Namespace, what: str) -> int:
    client = _client(args)
    try:
        reply = client.abort() if what == "abort" else client.reset()
    except ApiError as exc:
        print(f"alignctl: error: {exc}", file=sys.stderr)
        return EXIT_USAGE if exc.code in ("forbidden", "config") else EXIT_FAULT
    if args.json:
        _print_json(reply)
    else:
        print(reply.get("message", "ok"))
    return EXIT_OK


def cmd_abort(args: argparse.Namespace) -> int:
    return _control(args, "abort")


def cmd_reset(args: argparse.Namespace) -> int:
    return _control(args, "reset")


# ---- history / report ------------------------------------------------------------------------
def history_table(runs: list[dict[str, Any]]) -> str:
    head = f"{'ID':>5}  {'KIND':5}  {'STARTED (UTC)':19}  {'BY':16}  {'VERDICT':16}  " \
           f"{'OFFSET (k=2)':20}  REASON"
    rows = [head]
    for r in runs:
        started = str(r.get("started_at") or "")[:19].replace("T", " ")
        by = f"{r.get('user') or '?'}/{r.get('started_by')}"
        verdict = r.get("verdict") or r.get("status") or "?"
        rows.append(f"{r['id']:>5}  {r['kind']:5}  {started:19}  {by[:16]:16}  "
                    f"{verdict:16}  {_fmt_offset(r):20}  {r.get('reason') or ''}")
    return "\n".join(rows)


def cmd_history(args: argparse.Namespace) -> int:
    if args.limit < 1:
        print("alignctl: error: --limit must be at least 1", file=sys.stderr)
        return EXIT_USAGE
    runs = _client(args).history(args.limit)
    if args.json:
        _print_json(runs)
    elif not runs:
        print("no runs recorded yet")
    else:
        print(with_micro(history_table(runs)))
    return EXIT_OK


def _report_dir(out: Path) -> str | None:
    """Why ``out`` cannot take the report files (``None``: it can); created if missing."""
    if out.exists() and not out.is_dir():
        return f"--out {out} is a file, not a folder; give a folder for run-RUN.png/.json"
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot create the folder --out {out}: {exc.strerror or exc}"
    try:  # what the report's atomic writes need: a new file in that folder
        with tempfile.TemporaryFile(dir=out):
            pass
    except OSError as exc:
        return f"cannot write into --out {out}: {exc.strerror or exc}; choose another folder"
    return None


def cmd_report(args: argparse.Namespace) -> int:
    from alignd import report
    from alignd.report_side import side_frame_hash

    out = Path(args.out)
    problem = _report_dir(out)
    if problem:
        print(f"alignctl: error: {problem}", file=sys.stderr)
        return EXIT_USAGE
    client = _client(args)
    try:
        run = client.run(args.run)
    except ApiError as exc:
        print(f"alignctl: error: {exc}", file=sys.stderr)
        return EXIT_USAGE if exc.status in (400, 404) else EXIT_FAULT
    image = None
    pick = report.pick_frame(run)
    if pick is not None:
        try:
            image = report.decode_png(client.frame(pick["hash"]))
        except ApiError as exc:
            print(f"alignctl: warning: frame {pick['hash'][:12]} unavailable: {exc}",
                  file=sys.stderr)
    side_image = None
    side = side_frame_hash(run)
    if side is not None:
        try:
            side_image = report.decode_png(client.frame(side))
        except ApiError as exc:
            print(f"alignctl: warning: side frame {side[:12]} unavailable: {exc}",
                  file=sys.stderr)
    try:
        paths = report.write_report(run, out, image, side_image)
    except OSError as exc:
        print(f"alignctl: error: cannot write the report of run {args.run} into {out}: "
              f"{exc.strerror or exc}", file=sys.stderr)
        return EXIT_USAGE
    if args.json:
        _print_json({k: str(v) for k, v in paths.items()})
    else:
        for kind, path in paths.items():
            print(f"{kind}: {path}")
    return EXIT_OK
