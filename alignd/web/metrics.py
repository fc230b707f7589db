"""``GET /metrics``: the daemon's state and results in the Prometheus text format.

Why prometheus-client: the exposition format has escaping, type and help lines and
histogram conventions that a scraper checks strictly; the official library gets them right
and is a small pure-Python package. Everything is read at scrape time from the daemon's
status and the run history (a custom collector), so no counter can drift from the record;
only the frame grab times are observed as they happen.
"""

from __future__ import annotations

import calendar
import time
from collections.abc import Iterator
from typing import Any, Protocol

from prometheus_client import CollectorRegistry, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from alignd.store import Store
from alignd.web.frames import LiveFrames

STATES = ("starting", "idle", "aligning", "checking", "fault")
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


class MetricsSource(Protocol):
    store: Store
    live: LiveFrames
    faults: int

    def status(self) -> dict[str, Any]: ...
    def run(self, run_id: int) -> dict[str, Any] | None: ...


def _epoch(iso: str | None) -> float | None:
    """Seconds since the epoch of the store's UTC timestamps (``YYYY-MM-DDTHH:MM:SS...Z``)."""
    if not iso:
        return None
    try:
        return calendar.timegm(time.strptime(iso[:19], "%Y-%m-%dT%H:%M:%S"))
    except ValueError:
        return None


class _DaemonCollector(Collector):
    def __init__(self, source: MetricsSource) -> None:
        self.source = source
        self._timings_run: int | None = None
        self._timings: dict[str, float] = {}

    def collect(self) -> Iterator[Metric]:
        st = self.source.status()
        g = GaugeMetricFamily("alignd_state", "1 for the daemon's current state",
                              labels=["state"])
        for s in STATES:
            g.add_metric([s], 1.0 if st.get("state") == s else 0.0)
        yield g
        yield CounterMetricFamily("alignd_faults", "times the daemon entered the fault state "
                                  "since it started", value=float(self.source.faults))
        runs = CounterMetricFamily("alignd_runs", "recorded runs by kind and verdict",
                                   labels=["kind", "verdict"])
        for (kind, verdict), n in sorted(self.source.store.run_counts().items()):
            runs.add_metric([kind, verdict], float(n))
        yield runs
        prog = st.get("progress") or {}
        yield GaugeMetricFamily("alignd_run_in_progress", "id of the run in progress (0: none)",
                                value=float(st.get("run_id") or 0))
        if prog.get("step") is not None and prog.get("total"):
            yield GaugeMetricFamily("alignd_sweep_progress_ratio", "sweep steps done / total",
                                    value=float(prog["step"]) / float(prog["total"]))
        last = self.source.store.last_finished()
        off = GaugeMetricFamily("alignd_last_offset_um", "|offset| of the last finished run "
                                "of this kind (um)", labels=["kind"])
        unc = GaugeMetricFamily("alignd_last_uncertainty_um", "expanded uncertainty U (k = 2) "
                                "of that offset (um)", labels=["kind"])
        when = GaugeMetricFamily("alignd_last_run_timestamp_seconds", "when the last finished "
                                 "run of this kind ended (unix time)", labels=["kind"])
        good = GaugeMetricFamily("alignd_last_run_ok", "1 if that run was aligned / within "
                                 "tolerance", labels=["kind"])
        for kind, run in sorted(last.items()):
            if run.get("offset_norm_um") is not None:
                off.add_metric([kind], float(run["offset_norm_um"]))
            if run.get("U_um") is not None:
                unc.add_metric([kind], float(run["U_um"]))
            t = _epoch(run.get("ended_at") or run.get("started_at"))
            if t is not None:
                when.add_metric([kind], t)
            good.add_metric([kind], 1.0 if run.get("verdict") in ("aligned", "within_tolerance")
                            else 0.0)
        yield from (off, unc, when, good)
        newest = max((int(r["id"]) for r in last.values()), default=None)
        if newest is not None:
            timings = self._run_timings(newest)
            for name, v in sorted(timings.items()):
                yield GaugeMetricFamily(f"alignd_last_run_{name.removesuffix('_s')}_seconds",
                                        f"time spent in {name.removesuffix('_s')} in the last "
                                        "finished run (all iterations)", value=v)

    def _run_timings(self, run_id: int) -> dict[str, float]:
        """Summed timings (track, solve, grab, motion) over a run's iterations; cached."""
        if run_id == self._timings_run:
            return self._timings
        total: dict[str, float] = {}
        run = self.source.run(run_id) or {}
        for rec in run.get("iteration_records") or []:
            for k, v in (rec.get("timings") or {}).items() if isinstance(rec, dict) else ():
                if isinstance(v, (int, float)):
                    total[k] = total.get(k, 0.0) + float(v)
        self._timings_run, self._timings = run_id, total
        return total


class Metrics:
    """A registry of its own (not the process-global one) per daemon."""

    def __init__(self, source: MetricsSource) -> None:
        self.source = source
        self.registry = CollectorRegistry()
        self.registry.register(_DaemonCollector(source))
        self.grab = Histogram("alignd_frame_grab_seconds", "time to grab one camera frame",
                              buckets=(0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0),
                              registry=self.registry)

    def render(self) -> bytes:
        for s in self.source.live.drain_grab_seconds():
            self.grab.observe(s)
        return generate_latest(self.registry)
