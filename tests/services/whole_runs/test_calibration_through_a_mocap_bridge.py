"""A whole calibration whose poses come through ``swpc mocap`` (issue 46): the in-process
simulator's motion capture served as a QTM (``SWPC_SIM_MOCAP_QTM_PORT``), read by the
bridge through Qualisys' qtm-rt client, converted and put on the robot's pose key of a
zenoh router on loopback, to which the service connects as it would to a lab's."""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.demo import parameters_digest
from services.http.app import create_app
from services.http.console.router import _LiveCursor, live_snapshot
from services.sensors.bridge import Bridge, BridgeError, Source, zenoh_publisher
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from swpc_hw.sensors.mocap import pose_key, source_key
from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, open_session
from tests.service_rig import AUTH, SPINS_ONLY, TOKEN, Sim, start, wait_state

NAMES = ("x_s", "y_s", "beta", "b", "r")


def test_a_whole_calibration_through_the_bridge_is_done_and_accurate(tmp_path: Path) -> None:
    ep = free_tcp_endpoint()
    router = open_session(mode="router", listen=[ep])  # the lab's zenoh router
    port = int(free_tcp_endpoint().rsplit(":", 1)[1])
    bridge = Bridge(
        Source.parse(f"qtm://127.0.0.1:{port}"), "swpc", zenoh_publisher(router, pose_key("swpc")),
        report_every=0, status=zenoh_publisher(router, source_key("swpc"), "application/json"),
    )  # fmt: skip
    failure: list[BaseException] = []

    def bridging() -> None:  # as its unit would: again until the QTM is there
        while not bridge.stopping:
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
            run_id = start(client, {"protocol": SPINS_ONLY})
            st = wait_state(client, run_id, {"DONE", "FAILED", "ABORTED"}, timeout=600)
            assert st["state"] == "DONE", (st["errors"], failure, bridge.count.line())
            res = client.get(f"/calibrations/{run_id}/result").json()
            # the service shows where its poses come from, and what the bridge counted
            src = client.get("/health").json()["mocap_source"]
            assert src["source"] == f"qtm://127.0.0.1:{port}" and src["body"] == "swpc", src
            assert src["seen"] and src["dropped"] == 0 and src["bodies"] == ["swpc"], src
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


def test_a_body_the_bridge_does_not_see_refuses_the_start_naming_it(sim: Sim) -> None:
    """The bridge's word (``mocap/<robot>/source``) that the system does not see the body:
    GET /health fails naming the source, the body and the bodies the system has, and no
    run starts; the console's live view carries it."""
    doc = {
        "source": "qtm://192.0.2.10:22223",
        "body": "swpc",
        "seen": False,
        "bodies": ["wand", "robot7"],
        "rate_hz": 100.0,
        "dropped": 0,
        "not_seen": 150,
    }
    assert not sim.rt.mocap_source.feed(b"{not json")
    assert sim.rt.mocap_source.feed(json.dumps(doc).encode())
    try:
        h = sim.client.get("/health").json()
        why = ("motion capture: qtm://192.0.2.10:22223 does not see the body 'swpc' (it has: "
               "wand, robot7)")  # fmt: skip
        assert any(p.startswith(why) for p in h["problems"]), h["problems"]
        assert h["mocap_source"]["seen"] is False
        r = sim.client.post("/calibrations", json={}, headers=AUTH)
        assert r.status_code == 409 and why in r.text, r.text
        # the console's live view: the bridge's word, and the poses' delays (ms)
        live = live_snapshot(sim.rt, _LiveCursor())["mocap"]
        assert live["source"]["bodies"] == ["wand", "robot7"] and not live["source"]["seen"]
        p50, p99 = live["delay_ms"]
        assert 0 <= p50 <= p99, live
    finally:
        sim.rt.mocap_source.feed(json.dumps({**doc, "seen": True}).encode())
    assert not any("does not see" in p for p in sim.client.get("/health").json()["problems"])
