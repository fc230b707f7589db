"""What recording and the control API cost: per-record write times of the SQLite history
(WAL, synchronous=FULL, one transaction per record), a frame save (PNG + fsync + rename),
and the latency of ``GET /status`` over the Unix socket, idle and while a run records.

    python bench/daemon_io.py [--quick] [--dir DIR]

``--dir`` puts the database on the disk you care about (default: a temp dir).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

# the tests' fakes, and not bench/ itself first on the path (bench/drivers.py would shadow
# the drivers package)
sys.path[0] = str(Path(__file__).resolve().parents[1] / "tests")

from daemon_fakes import make_env, make_procedure  # noqa: E402

from alignd.store import SqliteRecorder, Store  # noqa: E402


def _row(name: str, samples: list[float]) -> str:
    ms = [s * 1e3 for s in samples]
    ms.sort()
    p95 = ms[min(len(ms) - 1, int(0.95 * len(ms)))]
    return f"| {name:34s} | {len(ms):5d} | {statistics.median(ms):8.2f} | {p95:8.2f} |"


def bench_store(root: Path, n: int) -> list[str]:
    store = Store(root / "state").open()
    run_id = store.start_run("align", started_by="bench", software_version="bench",
                             config_hash="0", config_json="{}")
    rec = SqliteRecorder(store, run_id)
    rng = np.random.default_rng(1)
    sweep = {"version": 1, "pixel_size_um": 160.0,
             "frames": [{"angle_deg": float(a), "features": rng.normal(600, 50, (4, 2)).tolist()}
                        for a in np.linspace(-10, 10, 21)]}
    angles = list(np.linspace(-10, 10, 21))
    rows = []
    t_sweep, t_iter, t_event, t_frame, t_run = [], [], [], [], []
    for i in range(n):
        t0 = time.perf_counter()
        rec.sweep("measure", i, sweep, angles, angles)
        t1 = time.perf_counter()
        rec.iteration(i, {"offset_um": [1.0, 2.0], "U_um": 3.0, "centre_px": [640.0, 360.0]})
        t2 = time.perf_counter()
        rec.event(f"event {i}")
        t3 = time.perf_counter()
        t_sweep.append(t1 - t0)
        t_iter.append(t2 - t1)
        t_event.append(t3 - t2)
    for i in range(max(3, n // 4)):
        # a rendered-looking frame: smooth background, a bright holder, noise
        img = np.full((720, 1280), 60, np.uint8)
        img[200 + i:500 + i, 400:800] = 200
        img = np.clip(img + rng.normal(0, 3, img.shape), 0, 255).astype(np.uint8)
        t0 = time.perf_counter()
        rec.frame(img, f"measure-0-{i:03d}")
        t_frame.append(time.perf_counter() - t0)
    for _ in range(max(3, n // 4)):
        t0 = time.perf_counter()
        rid = store.start_run("check", started_by="bench", software_version="bench",
                              config_hash="0", config_json="{}")
        store.finish_run(rid, verdict="within_tolerance", reason=None, result={"v": 1})
        t_run.append(time.perf_counter() - t0)
    rows += [_row("sweep record (21 frames x 4 features)", t_sweep),
             _row("iteration record", t_iter), _row("event record", t_event),
             _row("frame 1280x720 (PNG, fsync, rename)", t_frame),
             _row("run start + finish", t_run)]
    store.close()
    return rows


def bench_api(n: int) -> list[str]:
    rows = []
    procs = {"align": make_procedure("aligned", steps=21, iterations=50, step_sleep_s=0.002),
             "check": make_procedure("within_tolerance")}
    for env in make_env(procs):
        while env.daemon.state != "idle":
            time.sleep(0.01)
        idle = []
        for _ in range(n):
            t0 = time.perf_counter()
            env.client.status()
            idle.append(time.perf_counter() - t0)
        env.client.start("align")
        busy = []
        stop = threading.Event()
        for _ in range(n):
            if env.daemon.state != "aligning":
                break
            t0 = time.perf_counter()
            env.client.status()
            busy.append(time.perf_counter() - t0)
        stop.set()
        env.client.abort()
        rows += [_row("GET /status, idle", idle)]
        if busy:
            rows += [_row("GET /status, during a recording run", busy)]
    return rows


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="few samples (CI)")
    p.add_argument("--dir", type=Path, help="where to put the database (default: temp dir)")
    args = p.parse_args()
    n = 10 if args.quick else 100
    print("| operation                          |     n | median ms |   p95 ms |")
    print("|---|---:|---:|---:|")
    with tempfile.TemporaryDirectory(dir=args.dir) as d:
        for line in bench_store(Path(d), n):
            print(line)
    for line in bench_api(n):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
