"""Soak (issue 6, scenario 22): back-to-back checks on the simulated rig with random faults.

Runs the real ``alignd`` in a subprocess (as the fault tests do, ``tests/faults_support``),
with wire faults injected at random on every controller, and starts ``--runs`` checks one
after the other (a faulted daemon is reset first, as an operator would). Prints the verdict
counts and the daemon's memory, threads and file descriptors before and after, and checks
that every run was recorded, the database is sound and no target left the soft limits.

    .venv/bin/python bench/soak.py            # 200 checks
    .venv/bin/python bench/soak.py --quick    # 20 checks (CI)
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from faults_support import sim_daemon, soft_limit_violations
from test_faults_daemon import SOAK_FAULTS, proc_usage, soak

from alignd.store import Store


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--quick", action="store_true", help="20 checks")
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--seed", type=int, default=3)
    args = p.parse_args(argv)
    n = 20 if args.quick else args.runs
    proc = {"sweep_steps": 5, "sweep_deg": 5.0, "max_iterations": 1}
    t0 = time.monotonic()
    with sim_daemon(faults=SOAK_FAULTS, procedure=proc, reply_timeout_s=0.15,
                    seed=args.seed) as dp:
        soak(dp, args.warmup)
        dp.wait_state("idle", "fault")
        time.sleep(0.5)
        before = proc_usage(dp.pid)
        t1 = time.monotonic()
        reasons: list[str] = []
        verdicts = soak(dp, n, reasons)
        elapsed = time.monotonic() - t1
        dp.wait_state("idle", "fault")
        time.sleep(0.5)
        after = proc_usage(dp.pid)
        runs = dp.client.history(10_000)
        recorded = sum(1 for r in runs if r["status"] == "finished" and r["verdict"])
        integrity = Store(dp.state).integrity_check()
        violations = soft_limit_violations(dp.target_log, dp.cfg)
        faults_hit = dp.stderr().count("INFO drivers.sim.server: fault ")
    started = args.warmup + n - verdicts.get("reset_failed", 0)
    total = time.monotonic() - t0
    print(f"soak: {n} checks after {args.warmup} warm-up, seed {args.seed}, {elapsed:.1f} s "
          f"({elapsed / max(n, 1):.2f} s per check), total {total:.1f} s")
    print(f"{'':<22}{'before':>12}{'after':>12}{'change':>12}")
    for key, unit in (("rss_kb", "RSS (kB)"), ("threads", "threads"), ("fds", "open fds")):
        print(f"{unit:<22}{before[key]:>12}{after[key]:>12}{after[key] - before[key]:>+12}")
    print(f"{'verdict':<22}{'runs':>12}")
    for v, k in sorted(verdicts.items(), key=lambda kv: -kv[1]):
        print(f"{v:<22}{k:>12}")
    print(f"{'faults injected':<22}{faults_hit:>12}")
    if reasons:
        print("why runs faulted (numbers and ports folded):")
        for why, k in Counter(re.sub(r"\d+(\.\d+)?", "N", r)[:150] for r in reasons
                              ).most_common():
            print(f"{k:>5}  {why}")
    print(f"{'runs recorded':<22}{recorded:>12}  (started {started})")
    print(f"{'integrity_check':<22}{' '.join(integrity):>12}")
    print(f"{'soft-limit violations':<22}{len(violations):>12}")
    ok = (recorded == started and integrity == ["ok"] and not violations
          and after["threads"] <= before["threads"] + 1 and after["fds"] <= before["fds"] + 2)
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
