"""A whole calibration whose poses come through ``swpc mocap`` (issue 46): the in-process
simulator's motion capture served as a QTM (``SWPC_SIM_MOCAP_QTM_PORT``), read by the
bridge through Qualisys' qtm-rt client, converted and put on the robot's pose key of a
zenoh router on loopback, to which the service connects as it would to a lab's."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.demo import parameters_digest
from services.http.app import create_app
from services.sensors.bridge import Bridge, BridgeError, Source, zenoh_publisher
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from swpc_hw.sensors.mocap import pose_key
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session
from tests.service_rig import QUICK_PROTOCOL, TOKEN, start, wait_state

NAMES = ("x_s", "y_s", "beta", "b", "r")


def test_a_whole_calibration_through_the_bridge_is_done_and_accurate(tmp_path: Path) -> None:
    ep = free_tcp_endpoint()
    router = open_session(mode="router", listen=[ep])  # the lab's zenoh router
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    bridge = Bridge(Source.parse(f"qtm://127.0.0.1:{port}"), "swpc",
                    zenoh_publisher(router, pose_key("swpc")), report_every=0)  # fmt: skip
    failure: list[BaseException] = []

    def bridging() -> None:  # as its unit would: again until the QTM is there
        while not bridge._stop.is_set():
            try:
                bridge.run()
                return
            except BridgeError as exc:
                if "no connection" not in str(exc):
                    failure.append(exc)
                    return
                time.sleep(0.05)

    runner = threading.Thread(target=bridging, daemon=True)
    runner.start()
    settings = ServiceSettings(
        data_dir=tmp_path, token=SecretStr(TOKEN), zenoh_connect=[ep], sim_mocap_qtm_port=port
    )
    try:
        with TestClient(create_app(settings)) as client:
            run_id = start(client, {"protocol": QUICK_PROTOCOL})
            st = wait_state(client, run_id, {"DONE", "FAILED", "ABORTED"}, timeout=600)
            assert st["state"] == "DONE", (st["errors"], failure, bridge.count.line())
            res = client.get(f"/calibrations/{run_id}/result").json()
            bridge.stop()  # before the service (and its simulator's QTM) stops
            runner.join(timeout=10)
    finally:
        bridge.stop()
        runner.join(timeout=10)
        router.close()
    assert not failure
    c = bridge.count
    assert c.dropped == 0 and c.not_seen == 0 and c.sent == c.frames > 2000, c.line()
    truth = {m.id: m for m in PAPER_CALIBRATED.modules}
    worst = 0.0
    for m in res["modules"]:
        for k in NAMES:
            err, sd = m[k] - getattr(truth[m["id"]], k), m["stddev"][k]
            assert abs(err) < (0.3e-3 if k != "beta" else math.radians(0.05)), (m["id"], k, err)
            worst = max(worst, abs(err) / sd)
    assert worst < 4.0
    print(f"\nthrough swpc mocap (QTM, qtm-rt, a zenoh router): DONE, {c.line()}, largest "
          f"error {worst:.2f} std devs, digest {parameters_digest(res)}")  # fmt: skip
