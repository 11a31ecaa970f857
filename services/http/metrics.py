"""Prometheus metrics of the service: counters, gauges and histograms, rendered per scrape.

A collector reads the runtime at each scrape (a private registry per call: several apps
in one process, as the tests make, never share one).  Counters are the driver's and the
ingest's running totals (``*_total``), histograms the ingest's pose delays and the
finished runs' durations; gauges what is true now; ``swpc_build_info`` the version
serving (an info metric: 1, its labels say it).
"""

from __future__ import annotations

import datetime as _dt
import platform
from collections.abc import Iterator
from typing import Any

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST
from prometheus_client.metrics_core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    InfoMetricFamily,
    Metric,
)

from services.http.edge.streams import StreamGate
from services.runtime.health import service_health
from services.runtime.runtime import Runtime
from services.store.provenance import tool_version

CAN_ERROR_KINDS = (
    "error_frames",
    "bus_off",
    "unknown_ids",
    "bad_dlc",
    "decode_errors",
    "listener_errors",
    "send_errors",
    "feedback_gaps",
    "heartbeat_losses",
    "node_faults",
)
POSE_OUTCOMES = (
    "received",
    "accepted",
    "dropped",
    "decode_errors",
    "non_finite",
    "non_unit_quaternion",
    "duplicates",
    "out_of_order",
    "clock_resets",
)
GYRO_OUTCOMES = (
    "received",
    "accepted",
    "dropped",
    "decode_errors",
    "non_finite",
    "duplicates",
    "out_of_order",
    "clock_resets",
)
RUN_DURATION_BUCKETS = (30.0, 60.0, 120.0, 300.0, 600.0, 1200.0, 1800.0, 3600.0)
HEALTH = {"ok": 0.0, "degraded": 1.0, "failing": 2.0}
TERMINAL = ("DONE", "FAILED", "ABORTED")


def _time(text: Any) -> float | None:
    try:
        return _dt.datetime.fromisoformat(str(text).replace("Z", "+00:00")).timestamp()
    except ValueError:
        return None


class RuntimeCollector:
    def __init__(self, rt: Runtime, streams: StreamGate | None = None) -> None:
        self.rt = rt
        self.streams = streams

    def collect(self) -> Iterator[Metric]:
        rt = self.rt
        yield InfoMetricFamily(
            "swpc_build",
            "the swpc version serving, and its Python's",
            value={"version": tool_version(), "python": platform.python_version()},
        )
        d = rt.drives
        if d is not None:
            s = d.stats()
            frames = CounterMetricFamily("swpc_can_frames", "CAN frames", labels=["direction"])
            frames.add_metric(["rx"], s.rx_frames)
            frames.add_metric(["tx"], s.tx_frames)
            yield frames
            errs = CounterMetricFamily("swpc_can_errors", "CAN errors by kind", labels=["kind"])
            for kind in CAN_ERROR_KINDS:
                errs.add_metric([kind], getattr(s, kind))
            yield errs
            alive = GaugeMetricFamily(
                "swpc_node_alive", "controller heartbeat alive", labels=["module"]
            )
            for m in d.modules():
                alive.add_metric([str(m)], 1.0 if d.module_state(m).alive else 0.0)
            yield alive
        st = rt.mocap.stats()
        yield GaugeMetricFamily("swpc_pose_rate_hz", "accepted poses per second", st["rate_hz"])
        poses = CounterMetricFamily("swpc_poses", "pose samples by outcome", labels=["outcome"])
        for k in POSE_OUTCOMES:
            poses.add_metric([k], st[k])
        yield poses
        buckets, total, _count = rt.mocap.delay_histogram()
        yield HistogramMetricFamily(
            "swpc_pose_delay_seconds",
            "pose receipt minus its mapped sampling time (the latency with clock mode wall)",
            buckets=[(("+Inf" if b == float("inf") else repr(b)), n) for b, n in buckets],
            sum_value=total,
        )
        gy = rt.gyro.stats()
        yield GaugeMetricFamily(
            "swpc_gyro_rate_hz", "accepted gyro samples per second", gy["rate_hz"]
        )
        gyro = CounterMetricFamily(
            "swpc_gyro_samples", "gyro samples (imu/<robot>/data) by outcome", labels=["outcome"]
        )
        for k in GYRO_OUTCOMES:
            gyro.add_metric([k], gy[k])
        yield gyro
        runs = rt.list_runs()
        by_state = GaugeMetricFamily("swpc_runs", "calibration runs by state", labels=["state"])
        counts = {state: 0 for state in rt.run_states()}
        for r in runs:
            counts[str(r["state"])] = counts.get(str(r["state"]), 0) + 1
        for state, n in counts.items():
            by_state.add_metric([state], n)
        yield by_state
        durations = []
        for r in runs:
            t0, t1 = _time(r.get("started")), _time(r.get("finished"))
            if t0 is not None and t1 is not None and r.get("state") in TERMINAL:
                durations.append(max(0.0, t1 - t0))
        cum = [(repr(b), sum(1 for x in durations if x <= b)) for b in RUN_DURATION_BUCKETS]
        cum.append(("+Inf", len(durations)))
        yield HistogramMetricFamily(
            "swpc_run_duration_seconds",
            "wall time of finished runs, start to end",
            buckets=cum,
            sum_value=sum(durations),
        )
        if self.streams is not None:
            open_ = GaugeMetricFamily(
                "swpc_http_streams", "open event streams (GET /events)", labels=["token"]
            )
            with_token, without = self.streams.counts()
            open_.add_metric(["yes"], with_token)
            open_.add_metric(["no"], without)
            yield open_
            yield CounterMetricFamily(
                "swpc_http_streams_refused", "event streams refused 429 (a cap reached)",
                self.streams.refused,
            )  # fmt: skip
        status, _doc = service_health(rt)
        yield GaugeMetricFamily(
            "swpc_health", "0 ok, 1 degraded, 2 failing (GET /health)", HEALTH[status]
        )


def render_metrics(rt: Runtime, streams: StreamGate | None = None) -> tuple[bytes, str]:
    reg = CollectorRegistry()
    reg.register(RuntimeCollector(rt, streams))
    return generate_latest(reg), CONTENT_TYPE_LATEST
