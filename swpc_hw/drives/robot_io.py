"""The small interface through which the calibration state machine sees the robot.

:class:`RobotIO` is all the state machine uses; :class:`DrivesRobotIO` implements it on
the robot's drives of any kind (:class:`swpc_hw.drives.interface.Drives`), so the
simulator (which speaks the same CAN frames) and the real robot, and every drive kind,
are interchangeable.
"""

from __future__ import annotations

import math
import threading
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from firmware_protocol.codec import Axis
from swpc_hw.drives.errors import NodeError
from swpc_hw.drives.interface import Drives
from swpc_hw.drives.types import (
    AxisSigns,
    DriverEvent,
    Lifecycle,
    Severity,
    axis_sign,
    module_signs,
)
from swpc_hw.robot.model import nearest_turn

FloatArray = NDArray[np.float64]


class RobotIO(Protocol):
    """What calibration needs from a robot (all angles in rad, torques in N.m)."""

    @property
    def module_ids(self) -> list[int]: ...

    def problems(self) -> list[str]:
        """Why the robot is not ready (nodes dead, errors, not homed); empty when ready."""
        ...

    def activate(self) -> None:
        """Clear errors and let commands flow (controllers enabled, watchdog refreshed)."""
        ...

    def unhomed(self) -> list[int]:
        """Modules whose steering has not been homed yet."""
        ...

    def start_homing(self, module: int) -> None:
        """Run the controller's homing sequence on the steering axis."""
        ...

    def lock(self, module: int, steer: float) -> None:
        """Steering position-hold at ``steer`` (reported angle, any turn: the steering
        takes the shortest way), wheel braked."""
        ...

    def steer_to(self, module: int, steer: float) -> None:
        """Steering to ``steer`` (reported angle, any turn), the shortest way."""
        ...

    def free_steer(self, module: int) -> None: ...

    def wheel_torque(self, module: int, torque: float) -> None: ...

    def wheel_velocity(self, module: int, velocity: float) -> None:
        """The wheel at ``velocity`` (rad/s, the robot's sense)."""
        ...

    def spins_by_torque(self, module: int) -> bool:
        """Whether the module's wheel spins the robot by torque; False: its drive has no
        torque mode, so it spins it by velocity and is free with its power stage off."""
        ...

    def wheel_hold(self, module: int) -> None: ...

    def wheel_free(self, module: int) -> None: ...

    def steering(self, module: int) -> float:
        """Latest reported steering angle."""
        ...

    def stop_all(self) -> None:
        """Zero torque and disable on every axis (the fault path)."""
        ...

    def release(self) -> None:
        """Back to observing only (no commands)."""
        ...

    def encoders(self, module: int, since: float) -> FloatArray:
        """Feedback rows ``(t, theta_hat, psi)`` received at clock time >= ``since``."""
        ...

    def encoder_rows(self, module: int, cursor: int, since: float) -> tuple[FloatArray, int]:
        """Feedback rows ``(t, theta_hat, psi)`` after ``cursor`` (0 at first) with clock
        time >= ``since``, and the new cursor: each row once, as it comes."""
        ...

    def take_faults(self) -> list[str]:
        """Fault messages observed since the last call."""
        ...

    def close(self) -> None:
        """Stop listening to the robot (the run is over); idempotent."""
        ...


class DrivesRobotIO:
    """:class:`RobotIO` on the robot's :class:`Drives` (which own the bus and its lifecycle).

    ``limits``: ``(max torque, (steer, wheel) max velocity)`` sent to every controller at
    activation, after the drives' own (a run's tightened limits, :mod:`services.config.robot`).
    """

    def __init__(
        self,
        drives: Drives,
        limits: tuple[float, tuple[float, float]] | None = None,
        polarity: AxisSigns | None = None,
    ) -> None:
        self.drives = drives
        self.limits = limits
        self.polarity = dict(polarity or {})
        """Module -> (steer, wheel): -1 for an axis that turns the other way round from what
        its drive reports; what a run commands and reads is turned by it here."""
        self._faults: list[str] = []
        self._cause_taken = drives.fault_cause  # the drives' fault cause last looked at
        self._skip_event: str | None = None  # its event, when the cause was reported first
        self._lock = threading.Lock()
        drives.add_event_callback(self._on_event)

    def _on_event(self, ev: DriverEvent) -> None:
        if ev.severity is Severity.FAULT:
            with self._lock:
                if ev.message == self._skip_event:
                    self._skip_event = None  # already reported through the drives' cause
                else:
                    self._faults.append(ev.message)

    @property
    def module_ids(self) -> list[int]:
        return self.drives.modules()

    def problems(self) -> list[str]:
        out = []
        for m in self.module_ids:
            st = self.drives.module_state(m)
            if not st.alive:
                out.append(f"module {m} (node {st.node}): no heartbeat")
                continue
            if any(st.errors):
                out.append(f"module {m} (node {st.node}): active errors {st.errors}")
            if not st.homed:
                out.append(f"module {m} (node {st.node}): steering not homed")
            if st.feedback is None:
                out.append(f"module {m} (node {st.node}): no feedback")
        return out

    def activate(self) -> None:
        d = self.drives
        if d.state is not Lifecycle.ACTIVE:
            d.activate()
        for m in self.module_ids:
            if self.limits is not None:
                torque, velocity = self.limits
                for axis in (Axis.STEER, Axis.WHEEL):
                    d.set_limits(m, axis, torque, velocity[axis])
            d.clear_errors(m)
            d.enable(m, Axis.STEER)
            d.enable(m, Axis.WHEEL)

    def unhomed(self) -> list[int]:
        return [m for m in self.module_ids if not self.drives.module_state(m).homed]

    def start_homing(self, module: int) -> None:
        self.drives.start_homing(module)

    def _sign(self, module: int, axis: Axis) -> int:
        return axis_sign(self.polarity, module, axis)

    def _steer_setpoint(self, module: int, steer: float) -> float:
        """``steer`` on the turn nearest the steering's reported position: the controller's
        position is multi-turn (free casters trail through whole turns during spins), a
        raw ``steer`` could send it the long way round, up to many turns.  In the drive's
        own sense (its polarity)."""
        st = self.drives.module_state(module)
        if not math.isfinite(st.theta_hat):
            raise NodeError(
                f"module {module} (node {st.node}): no steering feedback, cannot steer it",
                node=st.node,
                axis=int(Axis.STEER),
            )
        s = self._sign(module, Axis.STEER)
        return s * float(nearest_turn(s * st.theta_hat, steer))

    def lock(self, module: int, steer: float) -> None:
        self.drives.set_position(module, Axis.STEER, self._steer_setpoint(module, steer))
        self.drives.hold(module, Axis.WHEEL)

    def steer_to(self, module: int, steer: float) -> None:
        self.drives.set_position(module, Axis.STEER, self._steer_setpoint(module, steer))

    def free_steer(self, module: int) -> None:
        self.drives.free(module, Axis.STEER)

    def wheel_torque(self, module: int, torque: float) -> None:
        self.drives.set_torque(module, Axis.WHEEL, self._sign(module, Axis.WHEEL) * torque)

    def wheel_velocity(self, module: int, velocity: float) -> None:
        self.drives.set_velocity(module, Axis.WHEEL, self._sign(module, Axis.WHEEL) * velocity)

    def spins_by_torque(self, module: int) -> bool:
        st = self.drives.axis_status(module, Axis.WHEEL)
        return st is None or st.torque_mode

    def wheel_hold(self, module: int) -> None:
        self.drives.hold(module, Axis.WHEEL)

    def wheel_free(self, module: int) -> None:
        self.drives.free(module, Axis.WHEEL)

    def steering(self, module: int) -> float:
        return self._sign(module, Axis.STEER) * self.drives.module_state(module).theta_hat

    def _turned(self, module: int, rows: FloatArray) -> FloatArray:
        """Feedback rows ``(t, theta_hat, psi)`` in the robot's sense (the polarity)."""
        s, w = module_signs(self.polarity, module)
        if s == 1 and w == 1:
            return rows
        out = np.array(rows, dtype=float, copy=True)
        out[:, 1] *= s
        out[:, 2] *= w
        return out

    def stop_all(self) -> None:
        self.drives.stop_all()

    def release(self) -> None:
        if self.drives.state is Lifecycle.ACTIVE:
            self.drives.deactivate()

    def encoders(self, module: int, since: float) -> FloatArray:
        """Feedback on the drives' clock, timed by the frames' *bus* time stamps.

        The drives map every bus stamp (kernel arrival on SocketCAN, send time on the
        virtual bus) onto their clock (:func:`swpc_hw.drives.tracking.frame_time`): the
        receive thread's queueing delay, which can reach a second on a loaded host, is not
        in it.
        """
        rows, _ = self.drives.history_since(module, 0, since)  # cursor 0: every row kept
        return self._turned(module, rows)

    def encoder_rows(self, module: int, cursor: int, since: float) -> tuple[FloatArray, int]:
        rows, cursor = self.drives.history_since(module, cursor, since)
        return self._turned(module, rows), cursor

    def take_faults(self) -> list[str]:
        """The fault events since the last call, and the drives' fault cause as soon as they
        have dropped out of ACTIVE: the event callbacks run just after that drop, so a
        caller polling between the two would otherwise see no fault yet its next command
        refused (LifecycleError)."""
        cause = self.drives.fault_cause  # None while the drives are ACTIVE
        with self._lock:
            out, self._faults = self._faults, []
            if cause is not None and cause is not self._cause_taken:  # a new fault stop
                self._cause_taken = cause
                if cause not in out:  # its event has not arrived yet
                    out.insert(0, cause)
                    self._skip_event = cause
        return out

    def close(self) -> None:
        self.drives.remove_event_callback(self._on_event)
