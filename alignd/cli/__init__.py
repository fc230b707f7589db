"""``alignctl``: the operator's command line. Each command group lives in its own module
and registers its subcommands here."""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys
from collections.abc import Sequence

from alignd import __version__
from alignd.errors import AligndError, ConfigError, InputError

# modules providing ``register(subparsers)``; each sets ``func`` on its parsers
COMMAND_MODULES = ["alignd.cli.solve_cmd", "alignd.cli.analyze_cmd", "alignd.cli.daemon_cmds",
                   "alignd.cli.demo_cmd"]

EXIT_OK, EXIT_OUT_OF_TOLERANCE, EXIT_USAGE, EXIT_FAULT = 0, 1, 2, 3
EXIT_BROKEN_PIPE = 141  # as for a program killed by SIGPIPE (128 + 13): output cut short


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="alignctl",
        description="alignd's command line: offline analysis (solve, analyze), the daemon's "
        "controls (status, align, check, abort, reset, history, report) and the demo.",
        epilog="exit codes: 0 ok / within tolerance, 1 out of tolerance or not converged, "
        "2 usage or config error, 3 hardware or daemon fault")
    parser.add_argument("--version", action="version", version=f"alignctl {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for wire traffic)")
    parser.add_argument("--socket", metavar="PATH", default=None,
                        help="daemon socket for the daemon commands (default: $ALIGND_SOCKET, "
                        "else /run/alignd/alignd.sock)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=[logging.WARNING, logging.INFO, logging.DEBUG][min(args.verbose, 2)],
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        code = int(args.func(args))
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's exit
        return code
    except BrokenPipeError:
        # the reader went away (``alignctl status | head -1``): that is not an error to
        # report; keep Python from complaining again when it flushes stdout at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except (InputError, ConfigError) as exc:
        print(f"alignctl: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except AligndError as exc:
        print(f"alignctl: error: {exc}", file=sys.stderr)
        return EXIT_FAULT
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
