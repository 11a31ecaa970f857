"""Prometheus metrics of the service (prometheus-client, a private registry per call)."""

from __future__ import annotations

from prometheus_client import CollectorRegistry, Gauge, generate_latest
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from services.runtime import Runtime


def render_metrics(rt: Runtime) -> tuple[bytes, str]:
    reg = CollectorRegistry()
    d = rt.driver
    if d is not None:
        s = d.stats()
        frames = Gauge("swpc_can_frames_total", "CAN frames", ["direction"], registry=reg)
        frames.labels("rx").set(s.rx_frames)
        frames.labels("tx").set(s.tx_frames)
        errs = Gauge("swpc_can_errors_total", "CAN error counters", ["kind"], registry=reg)
        for kind in (
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
        ):
            errs.labels(kind).set(getattr(s, kind))
        alive = Gauge("swpc_node_alive", "controller heartbeat alive", ["module"], registry=reg)
        for m in d.modules():
            alive.labels(str(m)).set(1.0 if d.module_state(m).alive else 0.0)
    st = rt.mocap.stats()
    Gauge("swpc_pose_rate_hz", "accepted poses per second", registry=reg).set(st["rate_hz"])
    poses = Gauge("swpc_poses_total", "pose samples", ["outcome"], registry=reg)
    for k in (
        "received",
        "accepted",
        "dropped",
        "decode_errors",
        "non_finite",
        "non_unit_quaternion",
        "duplicates",
        "out_of_order",
        "clock_resets",
    ):
        poses.labels(k).set(st[k])
    if "latency_p99_s" in st:
        Gauge("swpc_pose_latency_p99_seconds", "pose latency p99", registry=reg).set(
            st["latency_p99_s"]
        )
    runs = Gauge("swpc_runs", "calibration runs by state", ["state"], registry=reg)
    for state, n in rt.run_states().items():
        runs.labels(state).set(n)
    return generate_latest(reg), CONTENT_TYPE_LATEST
