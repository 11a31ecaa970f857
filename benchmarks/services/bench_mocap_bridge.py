"""``swpc mocap`` at 100 and 360 Hz: QTM's stream through the bridge onto zenoh, on loopback.

The simulator's QTM server sends a frame every 1/rate s for ``SECONDS``; the bridge reads
it through Qualisys' qtm-rt and publishes it; a zenoh subscriber receives the poses.
Printed per rate: frames sent, poses received (loss), and the latency from the server's
send to the subscriber's receipt (median, 99th percentile, largest), on this host's clock.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from services.sensors.bridge import Bridge, Source, zenoh_publisher
from simulators.sensors.qtm import QtmBody, QtmServer
from swpc_hw.sensors.mocap import decode_native, pose_key
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session

SECONDS = 10.0
IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


def one(rate: float) -> None:
    srv = QtmServer(["swpc"], frequency=rate)
    srv.start()
    ep = free_tcp_endpoint()
    sub, pub = open_session(listen=[ep]), open_session(connect=[ep])
    sent: dict[int, float] = {}
    got: dict[int, float] = {}
    # the capture time (us) names the frame: what arrived and when
    sub.declare_subscriber(pose_key("swpc"), lambda s: got.setdefault(
        round(decode_native(bytes(s.payload.to_bytes())).t * 1e6), time.monotonic()))  # fmt: skip
    probe = pub.declare_publisher(pose_key("swpc"))
    while not probe.matching_status.matching:  # the subscription known to the bridge's side
        time.sleep(0.01)
    bridge = Bridge(Source.parse(f"qtm://127.0.0.1:{srv.port}"), "swpc",
                    zenoh_publisher(pub, pose_key("swpc")), report_every=0)  # fmt: skip
    runner = threading.Thread(target=bridge.run, daemon=True)
    runner.start()
    while not srv.streaming:
        time.sleep(0.01)
    n = int(SECONDS * rate)
    t0 = time.monotonic()
    for k in range(1, n + 1):
        due = t0 + k / rate
        while (now := time.monotonic()) < due:
            time.sleep(min(due - now, 0.001))
        stamp = 1_000 * k
        sent[stamp] = time.monotonic()
        srv.publish(stamp, k, [QtmBody((1000.0, 0.0, 0.0), IDENTITY)])
    time.sleep(0.5)
    bridge.stop()
    runner.join(timeout=10)
    srv.stop()
    pub.close()
    sub.close()
    lat = np.array([got[s] - sent[s] for s in sent if s in got]) * 1e3
    lost = len(sent) - lat.size
    print(
        f"{rate:5.0f} Hz: {len(sent)} frames sent, {lat.size} poses received, {lost} lost "
        f"({bridge.count.dropped} dropped by frame number); latency median "
        f"{np.median(lat):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms, max {lat.max():.2f} ms"
    )


def main() -> None:
    for rate in (100.0, 360.0):
        one(rate)


if __name__ == "__main__":
    main()
