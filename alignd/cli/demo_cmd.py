"""``alignctl demo``: the whole instrument on the simulated rig, in one command.

Starts ``alignd`` (which starts the byte-faithful emulators and the rendered cameras of a
simulated-rig config) on a private socket and state directory, runs a closed-loop
alignment through the control API with live progress, writes the run's report (PNG and
JSON), shows the history, and stops the daemon.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.resources
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from alignd.cli import EXIT_FAULT, EXIT_USAGE
from alignd.config import load_config


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``alignctl demo``."""
    p = sub.add_parser("demo", help="closed-loop alignment on the simulated rig, with a report",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="a simulated-rig config (default: the "
                   "reference rig shipped with alignd, configs/sim.yaml)")
    p.add_argument("--out", default="out/demo", help="where the state, log and report go")
    p.add_argument("--seed", type=int, default=None, help="seed of the simulated world")
    p.set_defaults(func=cmd_demo)


def _wait_for_socket(path: Path, proc: subprocess.Popen, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.05)
    return False


@contextlib.contextmanager
def config_path(arg: str | None) -> Iterator[Path]:
    """``--config``, else the reference simulated rig packaged with alignd (so the demo
    works from any folder after ``pip install``)."""
    if arg is not None:
        yield Path(arg)
        return
    with importlib.resources.as_file(
            importlib.resources.files("alignd") / "data" / "sim.yaml") as path:
        yield path


def cmd_demo(args: argparse.Namespace) -> int:
    with config_path(args.config) as path:
        return _demo(args, path)


def _demo(args: argparse.Namespace, config: Path) -> int:
    from alignd.cli import daemon_cmds

    cfg = load_config(config)  # a bad config fails here, before anything starts
    if cfg.sim is None:
        print(f"alignctl: error: {config} is not a simulated-rig config (no 'sim:')",
              file=sys.stderr)
        return EXIT_USAGE
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    sock = out / "alignd.sock"
    sock.unlink(missing_ok=True)
    log_path = out / "alignd.log"
    cmd = [sys.executable, "-m", "alignd.daemon", "--config", str(config.resolve()),
           "--socket", str(sock), "--state-dir", str(out / "state"), "-v"]
    if args.seed is not None:
        cmd += ["--seed", str(args.seed)]
    print(f"alignd demo: starting the daemon on the simulated rig (log: {log_path})",
          file=sys.stderr)
    with open(log_path, "ab") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=log, env=os.environ.copy())
    try:
        if not _wait_for_socket(sock, proc, 60.0):
            print(f"alignctl: error: the daemon did not start; see {log_path}", file=sys.stderr)
            return EXIT_FAULT
        common = {"socket": str(sock), "json": False}
        code = daemon_cmds.cmd_align(argparse.Namespace(
            **common, started_by="user", detach=False, wait_ready=120.0, quiet=False))
        runs = daemon_cmds._client(argparse.Namespace(**common)).history(1)
        if runs:
            print()
            daemon_cmds.cmd_report(argparse.Namespace(**common, run=int(runs[0]["id"]),
                                                      out=str(out)))
            print()
            daemon_cmds.cmd_history(argparse.Namespace(**common, limit=5))
        return code
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
