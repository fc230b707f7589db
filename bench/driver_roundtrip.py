"""Command round-trip time and polling rate per protocol, driver against emulator.

Runs the reference rig's emulators on real pseudo-terminals (and loopback TCP), connects
the real drivers, and times ``position()`` and ``status()`` round trips: once as fast as
the software allows ("free"), once with the emulators pacing the bytes at the real
controllers' baud rates ("paced": what to expect on hardware, device latency aside).

    python bench/drivers.py [--quick] [--n 500]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from alignd.config import load_config  # noqa: E402
from drivers import registry  # noqa: E402
from drivers.sim.rig import SimRig  # noqa: E402


def time_calls(fn: Callable[[], object], n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1000.0)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="few calls (CI)")
    ap.add_argument("--n", type=int, default=500)
    ap.add_argument("--config", default=str(ROOT / "configs" / "sim.yaml"))
    args = ap.parse_args()
    n = 30 if args.quick else args.n
    cfg = load_config(args.config)
    rows = []
    for pace, transport in ((False, "pty"), (False, "tcp"), (True, "pty")):
        sim = cfg.sim.model_copy(update={"pace_serial": pace})
        with SimRig(cfg.controllers, [], sim, seed=1, transport=transport) as rig:
            for ctl in cfg.controllers:
                url_ctl = ctl.model_copy(update={"port": rig.url(ctl.name)})
                ax = registry.make_axes(url_ctl, time_scale=cfg.sim.time_scale)[0]
                with ax:
                    ax.identify()
                    for what, fn in (("position", ax.position), ("status", ax.status)):
                        ms = time_calls(fn, n)
                        p95 = sorted(ms)[int(0.95 * (len(ms) - 1))]
                        link = f"{transport}/{'paced' if pace else 'free'}"
                        rows.append((ctl.protocol, link, what, statistics.median(ms), p95,
                                     1000.0 / statistics.mean(ms)))
    print(f"driver round trips against the emulators ({n} calls each)")
    print(f"{'protocol':<9}{'link':<11}{'call':<10}{'median ms':>11}{'p95 ms':>9}{'polls/s':>9}")
    for proto, link, what, med, p95, rate in rows:
        print(f"{proto:<9}{link:<11}{what:<10}{med:>11.3f}{p95:>9.3f}{rate:>9.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
