"""Drive kinds by name: the registry, its entry points, and a fourth kind written from
scratch on :class:`swpc_hw.drives.base.DriverBase` (docs/drives.md, *The library*).

The fourth kind, ``toy``, speaks a protocol of three frames (a heartbeat ``0x700 + node``,
a feedback ``0x180 + node`` with the steering and wheel angles, a setpoint
``0x200 + node``) with one node a module; :class:`ToyDevice` is its drives on the
in-process CAN bus.  The test registers the kind, has the robot config's ``drives:``
name it, opens it through the registry and runs it as a run would (through
:class:`~swpc_hw.drives.robot_io.DrivesRobotIO`): activation, a steering command and its
feedback, the refresh, and the base's fault path when the drives go silent.
"""

from __future__ import annotations

import math
import struct
import threading
import time
import tomllib
import uuid
from typing import Any, Literal

import can
import pytest
from pydantic import Field, TypeAdapter, ValidationError

from firmware_protocol.codec import Axis, ControlMode, Frame
from swpc_hw.clock import Clock
from swpc_hw.drives import registry
from swpc_hw.drives.base import DriverBase
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.errors import CanConfigError, LifecycleError
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.registry import DrivesConfig, Kind, KindConfig, open_drives
from swpc_hw.drives.robot_io import DrivesRobotIO
from swpc_hw.drives.tracking import Applied, FeedbackRing, NodeTrack, Supervision
from swpc_hw.drives.types import EventKind, FeedbackSample, Lifecycle, ModuleState, Severity
from tests.service_rig import ROOT

HEARTBEAT, FEEDBACK, SETPOINT = 0x700, 0x180, 0x200
NODE_MASK = 0x7F


# ---------------------------------------------------------------- the kind: its config
class ToyDrives(KindConfig):
    """The ``toy`` kind's part of the robot config: module id -> node."""

    kind: Literal["toy"] = "toy"
    modules: dict[int, int] | None = Field(None)

    def module_ids(self) -> list[int] | None:
        return None if self.modules is None else list(self.modules)

    def for_modules(self, ids: list[int]) -> ToyDrives:
        if self.modules is not None:
            return self
        return self.model_copy(update={"modules": {m: i + 1 for i, m in enumerate(ids)}})

    def nodes(self) -> list[int]:
        return list((self.modules or {}).values())


# ---------------------------------------------------------------- the kind: its driver
def setpoint(node: int, axis: Axis, mode: ControlMode, value: float) -> Frame:
    return Frame(SETPOINT + node, struct.pack("<BBf", int(axis), int(mode), value))


class ToyDriver(DriverBase):
    """Only the toy protocol: the base owns lifecycle, I/O, supervision, faults, events."""

    def __init__(self, config: ToyDrives, bus: CanConfig, clock: Clock) -> None:
        super().__init__(bus, clock=clock)
        assert config.modules is not None
        self._nodes = {m: NodeTrack(m, n, FeedbackRing(10_000)) for m, n in config.modules.items()}
        self._by_node = {nd.node: nd for nd in self._nodes.values()}

    # what a frame tells (under the lock)
    def _node_of(self, arbitration_id: int) -> int | None:
        return arbitration_id & NODE_MASK

    def _apply_frame(self, msg: can.Message, t: float) -> Applied:
        out = Applied()
        self._stats.rx_frames += 1
        nd = self._by_node.get(msg.arbitration_id & NODE_MASK)
        kind = msg.arbitration_id & ~NODE_MASK
        if nd is None or kind not in (HEARTBEAT, FEEDBACK):
            return out
        if kind == HEARTBEAT:
            nd.t_heartbeat, nd.alive = t, True
            nd.heartbeats += 1
            return out
        theta, psi = struct.unpack("<ff", bytes(msg.data))
        nd.seq += 1
        nd.feedback_frames += 1
        sample = FeedbackSample(t, float(msg.timestamp), nd.seq & 0xFF, nd.seq, theta, psi)
        nd.last = sample
        nd.history.append((t, sample.t_bus, sample.counter, nd.seq, theta, psi))
        out.sample = (nd.module, sample)
        return out

    # supervision: heartbeat loss and the refresh, by the base's rule
    def _check(self, now: float, active: bool) -> Supervision:
        return self._check_nodes(
            self._nodes.values(), now, active, lambda nd: bool(nd.commanded), self._frames
        )

    def _frames(self, nd: NodeTrack) -> list[Frame]:
        return [setpoint(nd.node, a, m, v) for a, (m, v) in nd.commanded.items()]

    # activation and the stop
    def _bring_up(self) -> None:
        self._wait_all(
            "heartbeat",
            self._nodes.values,
            lambda nd: nd.alive,
            lambda nd: f"module {nd.module}",
            self.config.activate_timeout_s,
        )

    def _stopping(self) -> None:
        for nd in self._nodes.values():
            nd.commanded.clear()

    def _stop_frames(self) -> list[Frame]:
        return [
            setpoint(nd.node, a, ControlMode.FREE, 0.0) for nd in self._nodes.values() for a in Axis
        ]

    # observation
    def modules(self) -> list[int]:
        return list(self._nodes)

    def module_state(self, module: int) -> ModuleState:
        with self._lock:
            return self._nodes[module].snapshot()

    def _ring(self, module: int) -> FeedbackRing:
        return self._nodes[module].history

    # commands
    def _set(self, module: int, axis: Axis, mode: ControlMode, value: float) -> None:
        nd = self._nodes[module]
        with self._tx_lock:
            self._require_active(f"set {mode.name}", f"module {module}")
            with self._lock:
                nd.commanded[Axis(axis)] = (mode, value)
            self._send_frames([setpoint(nd.node, Axis(axis), mode, value)])

    def enable(self, module: int, axis: Axis) -> None:
        self._set(module, axis, ControlMode.FREE, 0.0)

    def clear_errors(self, module: int, axes: tuple[Axis, ...] = (Axis.STEER, Axis.WHEEL)) -> None:
        self._require_active("clear errors", f"module {module}")

    def set_limits(self, module: int, axis: Axis, max_torque: float, max_velocity: float) -> None:
        self._require_active("set limits", f"module {module}")

    def set_position(self, module: int, axis: Axis, position: float) -> None:
        self._set(module, axis, ControlMode.POSITION, position)

    def set_velocity(self, module: int, axis: Axis, velocity: float) -> None:
        self._set(module, axis, ControlMode.VELOCITY, velocity)

    def set_torque(self, module: int, axis: Axis, torque: float) -> None:
        self._set(module, axis, ControlMode.TORQUE, torque)

    def hold(self, module: int, axis: Axis) -> None:
        self._set(module, axis, ControlMode.HOLD, 0.0)

    def free(self, module: int, axis: Axis) -> None:
        self._set(module, axis, ControlMode.FREE, 0.0)

    def start_homing(self, module: int) -> None:
        self._require_active("start homing", f"module {module}")
        with self._lock:
            self._nodes[module].homed = True


def _open_toy(config: Any, bus: CanConfig, clock: Clock) -> Drives:
    return ToyDriver(config, bus, clock)


TOY = Kind("toy", ToyDrives, _open_toy)


# ---------------------------------------------------------------- the kind: its drives
class ToyDevice:
    """The toy drives on the in-process bus: heartbeats every 50 ms and feedback every
    20 ms per node; the steering follows its position setpoint at once."""

    def __init__(self, channel: str, nodes: list[int]) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.nodes = nodes
        self.steer = dict.fromkeys(nodes, 0.0)
        self.received: list[tuple[int, int, int, float]] = []
        self.silent = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def _run(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            msg = self.bus.recv(0.02)
            while msg is not None:
                if msg.arbitration_id & ~NODE_MASK == SETPOINT:
                    node = msg.arbitration_id & NODE_MASK
                    axis, mode, value = struct.unpack("<BBf", bytes(msg.data))
                    self.received.append((node, axis, mode, value))
                    if axis == Axis.STEER and mode == ControlMode.POSITION:
                        self.steer[node] = value
                msg = self.bus.recv(0)
            if self.silent.is_set():
                continue
            now = time.monotonic()
            for node in self.nodes:
                data = struct.pack("<ff", self.steer[node], 0.0)
                self.bus.send(can.Message(arbitration_id=FEEDBACK + node, data=data,
                                          is_extended_id=False))  # fmt: skip
                if now >= next_beat:
                    self.bus.send(can.Message(arbitration_id=HEARTBEAT + node, data=b"\x05",
                                              is_extended_id=False))  # fmt: skip
            if now >= next_beat:
                next_beat = now + 0.05

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.bus.shutdown()


def _until(cond: Any, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.01)
    return False


# ---------------------------------------------------------------- the tests
def test_a_fourth_kind_registered_is_opened_by_name_and_runs() -> None:
    registry.register(TOY)
    channel = f"toy-{uuid.uuid4().hex[:8]}"
    device = ToyDevice(channel, [1, 2])
    drives: Drives | None = None
    try:
        config = TypeAdapter(DrivesConfig).validate_python("toy")  # the short form
        assert isinstance(config, ToyDrives) and "toy" in registry.known()
        # what a run's timing budget makes, with room for a loaded test host: 20 of the
        # toy's heartbeats (its period, 50 ms, not the swpc firmware's 100 ms) missed is a
        # loss, 1 s of silence, which the test waits for once the drives go silent
        bus = CanConfig(interface="virtual", channel=channel, heartbeat_period_s=0.05,
                        heartbeat_loss_periods=20, activate_timeout_s=10.0)  # fmt: skip
        drives = open_drives(config, bus, [1, 2])
        assert isinstance(drives, ToyDriver) and drives.modules() == [1, 2]
        events: list[Any] = []
        drives.add_event_callback(events.append)
        device.start()
        drives.configure()
        io = DrivesRobotIO(drives)
        io.activate()  # activate(), limits, errors cleared, both axes enabled
        assert drives.state is Lifecycle.ACTIVE
        io.lock(1, 0.5)  # steering to 0.5 rad, wheel held
        st = drives.wait_for(1, lambda s: abs(s.theta_hat - 0.5) < 1e-6, 10.0, "steer 0.5")
        assert st.alive and st.feedback is not None
        # a kind that reports whole modules only (the base's axis_status): the console
        # shows its modules' snapshots
        assert drives.axis_status(1, Axis.STEER) is None
        rows, cursor = io.encoder_rows(1, 0, -math.inf)
        assert rows.shape[1] == 3 and cursor > 0 and abs(rows[-1, 1] - 0.5) < 1e-6
        assert _until(lambda: len([r for r in device.received if r[2] == ControlMode.POSITION]) > 2)
        # the drives go silent: the base's fault path stops every axis, then tells
        device.silent.set()
        assert _until(lambda: drives.state is Lifecycle.INACTIVE)
        assert drives.fault_cause is not None and "no heartbeat" in drives.fault_cause
        assert _until(lambda: any(e.kind is EventKind.STOPPED for e in events))
        fault = next(e for e in events if e.severity is Severity.FAULT)
        assert fault.kind is EventKind.HEARTBEAT_LOST
        assert io.take_faults() and _until(
            lambda: any(r[2] == ControlMode.FREE for r in device.received[-4:])
        )
        with pytest.raises(LifecycleError, match="stopped by a fault: module 1"):
            drives.set_torque(1, Axis.WHEEL, 0.1)
        io.close()
    finally:
        if drives is not None:
            drives.shutdown()
        device.close()
        registry.unregister("toy")


def test_an_unknown_kind_names_the_known_ones() -> None:
    with pytest.raises(CanConfigError, match=r"unknown kind 'laser' \(known: cia402, odrive, swpc"):
        registry.get("laser")
    with pytest.raises(ValidationError, match="unknown kind 'laser'"):
        TypeAdapter(DrivesConfig).validate_python({"kind": "laser"})
    with pytest.raises(CanConfigError, match="built-in"):
        registry.register(Kind("swpc", ToyDrives, _open_toy))


def test_a_kind_from_an_entry_point(monkeypatch: pytest.MonkeyPatch) -> None:
    """Another package's kind: an entry point of group ``swpc.drives`` named as the kind."""

    class EntryPoint:
        name = "toy"

        def load(self) -> Kind:
            return TOY

    def entry_points(group: str) -> list[EntryPoint]:
        return [EntryPoint()] if group == registry.ENTRY_POINT_GROUP else []

    monkeypatch.setattr(registry, "entry_points", entry_points)
    assert "toy" in registry.known() and registry.get("toy") is TOY
    config = TypeAdapter(DrivesConfig).validate_python({"kind": "toy", "modules": {1: 3}})
    assert isinstance(config, ToyDrives)
    # the config dumps as its kind's (not as the bare base model)
    assert TypeAdapter(DrivesConfig).dump_python(config) == {"kind": "toy", "modules": {1: 3}}


def test_the_built_in_kinds_are_the_entry_points_declared() -> None:
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    declared = pyproject["project"]["entry-points"][registry.ENTRY_POINT_GROUP]
    assert declared == registry.BUILTIN
    for name in registry.BUILTIN:
        kind = registry.get(name)
        assert kind.name == name and issubclass(kind.config, KindConfig)
        assert kind.config.model_validate({"kind": name}).kind == name
