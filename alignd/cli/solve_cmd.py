"""``alignctl solve FILE...``: centre of rotation from sweep files, offline.

Each file is solved on its own: a malformed or degenerate file is reported (stderr, and an
``{"file", "error"}`` line with ``--json``) and the others are still solved; the exit code
is then 2 (usage/input error).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from alignd.cli import EXIT_OK, EXIT_USAGE
from alignd.errors import InputError, SolveError
from alignd.solve import METHODS, CentreResult, load_sweep, solve_centre


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``solve``."""
    p = sub.add_parser("solve", help="find the centre of rotation from sweep file(s)",
                       description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("files", nargs="+", metavar="FILE", help="sweep file(s) (JSON, version 1)")
    p.add_argument("--method", choices=METHODS, default="auto",
                   help="solver (default: auto = rigid with image-estimated angles when two "
                        "or more features are tracked)")
    p.add_argument("--seed", type=int, default=0, help="seed of the thesis method's subset")
    p.add_argument("--json", action="store_true",
                   help="one JSON object per line per file (the solve-output contract)")
    p.set_defaults(func=run)


def _table_row(name: str, res: CentreResult, px_um: float | None) -> str:
    sx, sy = np.sqrt(np.diag(res.cov_px2))
    rho = res.cov_px2[0, 1] / (sx * sy) if sx > 0 and sy > 0 else 0.0
    um = "" if px_um is None else "  ({:.1f}, {:.1f}) +- ({:.1f}, {:.1f}) um".format(
        *res.center_um(px_um), sx * px_um, sy * px_um)
    return (f"{name}: {res.method:<11} centre ({res.center_px[0]:.3f}, {res.center_px[1]:.3f}) px"
            f" +- ({sx:.3f}, {sy:.3f}) px rho {rho:+.2f}{um}  rms {res.rms_residual_px:.3f} px"
            f"  inliers {res.inliers} outliers {res.outliers}")


def run(args: argparse.Namespace) -> int:
    status = EXIT_OK
    for name in args.files:
        try:
            sweep = load_sweep(name)
            res = solve_centre(sweep, method=args.method, seed=args.seed)
        except (InputError, SolveError) as exc:
            msg = str(exc) if str(exc).startswith(name) else f"{name}: {exc}"
            print(f"alignctl solve: error: {msg}", file=sys.stderr)
            if args.json:
                print(json.dumps({"file": name, "error": msg}), flush=True)
            status = EXIT_USAGE
            continue
        if args.json:
            print(json.dumps(res.to_json(name, sweep.pixel_size_um)), flush=True)
        else:
            print(_table_row(name, res, sweep.pixel_size_um), flush=True)
    return status
