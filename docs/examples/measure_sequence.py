#!/usr/bin/env python3
"""A measurement sequence that keeps the sample on the rotation axis.

Before each sample: a check (the sample is not moved); if the offset is not within the
tolerance, an alignment, and the sample is measured only once alignd says it is on the
axis. Replace ``measure_sample`` with your instrument's measurement.

    python docs/examples/measure_sequence.py --samples 3 [--socket /run/alignd/alignd.sock]

Exit status: 0 all samples measured, 1 a sample could not be aligned (the sequence stops
there), 3 alignd unreachable or refused (busy, faulted, not allowed).
"""

from __future__ import annotations

import argparse
import sys

from alignd.client import ApiError, Client, DaemonUnreachable, Event, RunResult


def measure_sample(n: int) -> None:
    """Your measurement goes here (e.g. a BRDF scan of sample ``n``)."""
    print(f"sample {n}: measuring", flush=True)


def show(ev: Event) -> None:
    if ev.type == "progress" and ev.step is None and ev.phase in ("solve", "move", "done"):
        print(f"    {ev}", flush=True)


def summary(what: str, r: RunResult) -> str:
    off = "-" if r.offset_norm_um is None else f"{r.offset_norm_um:.1f} ± {r.U_um:.1f} um"
    return f"{what} (run {r.run_id}): {r.verdict}, offset {off}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--socket", help="alignd's socket (default: $ALIGND_SOCKET, else "
                   "/run/alignd/alignd.sock)")
    p.add_argument("--samples", type=int, default=3)
    args = p.parse_args(argv)
    client = Client(args.socket)
    try:
        for n in range(1, args.samples + 1):
            check = client.check()
            print(f"sample {n}: {summary('check', check)}", flush=True)
            if not check.ok:
                aligned = client.align(on_event=show)
                print(f"sample {n}: {summary('align', aligned)}", flush=True)
                if not aligned.ok:
                    print(f"sample {n}: not aligned ({aligned.reason}); stopping the sequence",
                          file=sys.stderr)
                    return 1
            measure_sample(n)
    except (ApiError, DaemonUnreachable) as exc:
        print(f"alignd: {exc}", file=sys.stderr)
        return 3
    return 0


if __name__ == "__main__":
    sys.exit(main())
