"""What the read-only dashboard costs, against the real daemon on the simulated rig:
the latency of its JSON status, of one live camera view (the worker's frame with the holder
tracked and the overlays drawn, JPEG), of a run's report figure (rendered once per run and
cached) and of a /metrics scrape; and the live view's frame rate while a page watches.

    python bench/web.py [--quick]

Targets: a live view at >= 3 frames per second (the dashboard asks for about 3), a status
answer and a metrics scrape well inside the dashboard's 0.5 s poll (p95 <= 100 ms).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import urllib.request
from pathlib import Path

sys.path[0] = str(Path(__file__).resolve().parents[1] / "tests")

from faults_support import sim_daemon  # noqa: E402


def _get(url: str) -> tuple[bytes, dict[str, str]]:
    with urllib.request.urlopen(url, timeout=30) as r:
        return r.read(), dict(r.headers)


def _times(url: str, n: int) -> list[float]:
    out = []
    for _ in range(n):
        t0 = time.perf_counter()
        _get(url)
        out.append(time.perf_counter() - t0)
    return out


def _row(name: str, samples: list[float], target: str = "") -> str:
    ms = sorted(s * 1e3 for s in samples)
    p95 = ms[min(len(ms) - 1, int(0.95 * len(ms)))]
    return f"| {name:34s} | {len(ms):4d} | {statistics.median(ms):8.1f} | {p95:8.1f} | {target} |"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="fewer samples (CI)")
    args = p.parse_args(argv)
    n = 5 if args.quick else 40
    rows = ["| request                            |    n | median ms |   p95 ms | target |",
            "|---|---:|---:|---:|---|"]
    with sim_daemon(args=["--web", "127.0.0.1:0"], env={"FAULTS_TOOLS": "real"}) as dp:
        url = dp.client.status()["web"]
        run_id = dp.run_and_wait("check")["id"]
        status = _times(url + "api/status", n)
        rows.append(_row("GET /api/status", status, "p95 <= 100 ms"))
        _get(url + f"runs/{run_id}/report.png")  # the first render
        rows.append(_row("GET /runs/ID/report.png (cached)",
                         _times(url + f"runs/{run_id}/report.png", n)))
        t0 = time.perf_counter()
        _get(url + "metrics")
        rows.append(_row("GET /metrics", _times(url + "metrics", n), "p95 <= 100 ms"))
        # the live view while watched: new frames per second as a page would see them
        # watching starts with the first request; the idle worker notices within its tick:
        # that start-up is its own row, the rate is measured from the first new frame on
        _, headers = _get(url + "live/top.jpg")
        first = json.loads(headers["X-Alignd-View"])["seq"]
        t_watch = time.perf_counter()
        while time.perf_counter() - t_watch < 10.0:
            _, headers = _get(url + "live/top.jpg")
            if json.loads(headers["X-Alignd-View"])["seq"] != first:
                break
            time.sleep(0.01)
        startup_ms = 1e3 * (time.perf_counter() - t_watch)
        seqs, t0 = [], time.perf_counter()
        views = []
        while time.perf_counter() - t0 < (3.0 if args.quick else 15.0):
            t1 = time.perf_counter()
            _, headers = _get(url + "live/top.jpg")
            views.append(time.perf_counter() - t1)
            seqs.append(json.loads(headers["X-Alignd-View"])["seq"])
            time.sleep(0.05)
        elapsed = time.perf_counter() - t0
        rows.append(_row("GET /live/top.jpg", views))
    fps = (len(set(seqs)) - 1) / elapsed
    print("\n".join(rows))
    verdict = "PASS" if fps >= 3.0 else "FAIL"
    print(f"\nlive top view: {fps:.1f} new frames per second while watched "
          f"(target >= 3): {verdict}")
    print(f"live top view: first new frame {startup_ms:.0f} ms after watching began (info)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
