"""Back-to-back: the driver's lifecycle (configure, activate, deactivate, shutdown), its
configuration and bus errors, and what others see of a run: the candump-format recording
that cantools decodes, and ``swpc can monitor``.

The driver against emulated controllers on a real python-can bus (the rig and the bus:
:mod:`tests.drives.swpc.back_to_back_rig`); the same module runs on SocketCAN in the VM
(``deploy/vm/in-vm.sh``).
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from firmware_protocol import codec
from firmware_protocol.codec import Axis, AxisState
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.errors import (
    CanBusError,
    CanConfigError,
    CanError,
    LifecycleError,
    NodeTimeoutError,
)
from swpc_hw.drives.swpc.driver import SwpcDriver
from swpc_hw.drives.types import EventKind, Lifecycle
from swpc_hw.errors import SwpcError
from tests.can_rig import (
    FEEDBACK_RATE_HZ,
    INTERFACE,
    TIME_FACTOR,
    WATCHDOG_MS,
    Observer,
    ScaledDriver,
    T,
    can_config,
    emulator,
    new_channel,
    now,
    rig_clock,
    sleep,
    wait_until,
)
from tests.drives.swpc.back_to_back_rig import ALL_AXES, NODES, Rig, make_rig, stop_frames
from tests.service_rig import ROOT


# ---------------------------------------------------------------------------- lifecycle
def test_lifecycle_inactive_reads_without_sending(rig: Rig) -> None:
    drv = rig.drv
    assert drv.state == Lifecycle.UNCONFIGURED
    with pytest.raises(LifecycleError):
        drv.activate()
    drv.configure()
    assert drv.state == Lifecycle.INACTIVE
    # a socket bus gets a bigger kernel receive buffer (frames survive a stalled reader);
    # the in-VM run of this suite is root, so SO_RCVBUFFORCE passes net.core.rmem_max
    rx_buffer = drv.stats().rx_buffer_bytes
    if INTERFACE == "socketcan":
        assert rx_buffer is not None and rx_buffer >= 2 * drv.config.rx_buffer_bytes
    else:
        assert rx_buffer is None
    with pytest.raises(LifecycleError, match="configure"):
        drv.configure()
    assert wait_until(lambda: all(drv.module_state(m).alive for m in NODES))
    assert wait_until(lambda: len(drv.history(3)) >= 20)
    with pytest.raises(LifecycleError, match=r"module 1 \(node 1\) axis 1 \(wheel\).*inactive"):
        drv.enable(1, Axis.WHEEL)
    assert rig.host_frames() == []  # inactive: nothing sent, only received
    assert drv.stats().tx_frames == 0

    t0 = now()
    drv.activate()
    assert drv.state == Lifecycle.ACTIVE
    assert wait_until(lambda: len(rig.host_frames(t0)) >= 8)
    sent = rig.host_frames(t0)
    assert {(f.node, f.timeout_ms) for f in sent if isinstance(f, codec.SetWatchdog)} == {
        (n, WATCHDOG_MS) for n in NODES
    }
    assert {(f.node, f.rate_hz) for f in sent if isinstance(f, codec.SetFeedback)} == {
        (n, FEEDBACK_RATE_HZ) for n in NODES
    }
    drv.enable(2, Axis.STEER)
    drv.wait_axis_state(2, Axis.STEER, AxisState.ENABLED)

    t1 = now()
    drv.deactivate()
    assert drv.state == Lifecycle.INACTIVE
    assert wait_until(lambda: stop_frames(rig.host_frames(t1)) == (ALL_AXES, ALL_AXES))
    drv.wait_axis_state(2, Axis.STEER, AxisState.DISABLED)
    drv.shutdown()
    drv.shutdown()  # idempotent
    assert drv.state == Lifecycle.FINALIZED
    with pytest.raises(LifecycleError):
        drv.configure()


def test_grow_receive_buffer_asks_the_kernel() -> None:
    """On any socket (a UDP one here, unbound: no traffic): the buffer in effect is what
    Linux grants for the size asked, doubled; capped at net.core.rmem_max without
    CAP_NET_ADMIN."""
    import os
    import socket

    from swpc_hw.drives.recording import grow_receive_buffer

    size = 1 << 20
    rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        before = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        got = grow_receive_buffer(sock, size)
        assert got == sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    want = 2 * size if os.geteuid() == 0 or size <= rmem_max else 2 * rmem_max
    assert got == want and got > before


def test_context_manager_and_shutdown_from_active() -> None:
    with rig_clock():
        channel = new_channel()
        obs = Observer(channel)
        with emulator([1], channel):
            with ScaledDriver(can_config(channel, modules={1: 1})) as drv:
                assert drv.state == Lifecycle.INACTIVE
                drv.activate()
                drv.enable(1, Axis.WHEEL)
                t0 = now()
            assert drv.state == Lifecycle.FINALIZED

            def frames() -> list[codec.Decoded]:
                return [
                    codec.parse(m.arbitration_id, bytes(m.data))
                    for t, m in obs.snapshot()
                    if t >= t0 and codec.split_id(m.arbitration_id)[1] in codec.HOST_COMMANDS
                ]

            # on a real clock the observer's own bus receives on its own thread: the stop
            # frames, sent before shutdown returned, may reach it a moment later
            want = ({(1, Axis.STEER), (1, Axis.WHEEL)},) * 2
            assert wait_until(lambda: stop_frames(frames()) == want), stop_frames(frames())
        obs.close()


def test_activate_names_the_silent_node() -> None:
    for r in make_rig(nodes=(1, 2, 3), activate_timeout_s=0.4):
        r.drv.configure()
        with pytest.raises(NodeTimeoutError, match=r"module 4 \(node 4\)") as info:
            r.drv.activate()
        assert info.value.node == 4
        assert r.drv.state == Lifecycle.INACTIVE
        lost = [e for e in r.drv.events() if e.kind == EventKind.HEARTBEAT_LOST]
        assert [e.node for e in lost] == [4]


def test_config_and_bus_errors_share_one_root() -> None:
    with pytest.raises(CanConfigError, match=r"modules\[1\]: node id 9"):
        CanConfig(modules={1: 9})
    with pytest.raises(CanConfigError, match="distinct"):
        CanConfig(modules={1: 2, 2: 2})
    with pytest.raises(CanConfigError, match="unknown CAN configuration key"):
        CanConfig.from_mapping({"bogus": 1})
    cfg = CanConfig.from_mapping({"channel": "x", "modules": {"1": "3"}, "max_torque": [1, 2]})
    assert cfg.modules == {1: 3} and cfg.max_torque == (1.0, 2.0)
    drv = SwpcDriver(CanConfig(interface="no_such_interface"))
    with pytest.raises(CanBusError, match="no_such_interface") as info:
        drv.configure()
    assert isinstance(info.value, CanError) and isinstance(info.value, SwpcError)
    drv.shutdown()


# ---------------------------------------------------------------------------- recording
def test_recording_decodes_with_cantools(tmp_path: Path) -> None:
    log = tmp_path / "run.log"
    for r in make_rig(log_path=str(log)):
        r.drv.configure()
        r.drv.activate()
        r.drv.enable(2, Axis.WHEEL)
        r.drv.set_velocity(2, Axis.WHEEL, 1.5)
        sleep(T(0.2))
        r.drv.shutdown()
    text = log.read_text()
    lines = text.splitlines()
    assert any(line.endswith(" T") for line in lines)
    if INTERFACE == "virtual":  # SocketCAN flags every frame made on this host as sent (T)
        assert any(line.endswith(" R") for line in lines)
    out = subprocess.run(
        [sys.executable, "-m", "cantools", "decode", str(ROOT / "firmware_protocol" / "swpc.dbc")],
        input=text,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "N2_SetControl(" in out and "VelocitySetpoint: 1.5 rad/s" in out
    assert "N2_SetAxisState(" in out and "RequestedState: ENABLED" in out
    assert "N4_Heartbeat(" in out and "N1_FeedbackPosition(" in out
    assert "N3_FeedbackVelocityTorque(" in out and "N1_SetWatchdog(" in out
    assert "Unknown frame" not in out


# ---------------------------------------------------------------------------- CLI
def test_can_monitor_prints_nodes(capsys: pytest.CaptureFixture[str]) -> None:
    from services.cli import main

    channel = new_channel()
    # the emulated controllers keep real-time periods (heartbeat 0.1 s), which a slow
    # machine (F > 1) cannot hold: the loss window is scaled instead (at F = 9.5 in the VM
    # every node read lost with the 0.3 s default)
    rc = main(
        ["can", "monitor", "--interface", INTERFACE, "--channel", channel, "--emulate",
         "--duration", str(T(1.2)), "--interval", str(T(0.3)), "--plain",
         "--heartbeat-loss-periods", str(math.ceil(3 * TIME_FACTOR))]
    )  # fmt: skip
    assert rc == 0
    out = capsys.readouterr().out
    rows = [line.split("  ") for line in out.splitlines() if line[:1].isdigit()]
    assert {r[0] for r in rows} == {"1", "2", "3", "4"}
    assert all(r[2] == "yes" and r[3] == "DISABLED/FREE" for r in rows)
    last = rows[-4:]
    # feedback ~200 Hz: the monitor's emulated controllers run at their default 200 Hz, which
    # a slow machine (F > 1) cannot sustain for 4 nodes: at least 100/F Hz there
    assert all(100.0 / TIME_FACTOR < float(r[8]) < 260.0 for r in last)
    assert "error frames 0" in out and "unknown ids 0" in out
