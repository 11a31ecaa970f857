"""What every drive kind gives the host: the robot's drives on one CAN bus.

A *drive kind* is the protocol the robot's motor controllers speak: swpc's own firmware
(:mod:`swpc_hw.drives.swpc`, the DBC in ``firmware_protocol/``), CiA 402 over CANopen
(:mod:`swpc_hw.drives.cia402`), ODrive's CAN Simple (:mod:`swpc_hw.drives.odrive`).  Each
kind implements :class:`Drives` once, on :class:`swpc_hw.drives.base.DriverBase`; the
service, its health, the validation drive, the odometry feed and the calibration state
machine (through :class:`swpc_hw.drives.robot_io.RobotIO`) see nothing else, so a robot's
drives are a line in its config and :mod:`swpc_hw.drives.registry` is the only place that
finds the kinds (by name).  Every member below is one of theirs (docs/drives.md, *The
library*).

Lifecycle, as ros2_control's hardware components::

    UNCONFIGURED --configure()--> INACTIVE --activate()--> ACTIVE
         ^                          ^  |                     |
         |                          |  +----deactivate()-----+  (also on any fault)
         +------- shutdown() (from any state, idempotent) -> FINALIZED

* INACTIVE: the bus is open, the drives are watched (liveness, faults, feedback); no
  command is sent.
* ACTIVE: commands flow and every enabled axis is kept alive by the kind's dead-man (the
  firmware's command watchdog, a CANopen heartbeat consumer, an ODrive axis watchdog):
  a host that stops renewing it stops every axis within the timing budget
  (:mod:`services.config.timing` states the bound).
* Every fault (bus-off, a drive gone silent, a drive's fault report) calls
  :meth:`Drives.stop_all` and drops back to INACTIVE with :attr:`Drives.fault_cause` set;
  a FAULT :class:`~swpc_hw.drives.types.DriverEvent` tells the listeners.

Units at this boundary are SI at the module's output: steering ``theta_hat`` in rad (0 at
the homing reference, multi-turn), wheel ``psi`` in rad (cumulative), torques in N.m,
velocities in rad/s.  A kind converts with the gear ratios and encoder counts of its
config, never with constants of its own.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Protocol

import can
import numpy as np
from numpy.typing import NDArray

from firmware_protocol.codec import Axis, Frame
from swpc_hw.clock import Clock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.tracking import Applied, Supervision
from swpc_hw.drives.types import (
    AxisStatus,
    DriverEvent,
    DriverStats,
    FeedbackSample,
    Lifecycle,
    ModuleState,
)

FloatArray = NDArray[np.float64]


class Drives(Protocol):
    """The robot's drives on one bus (module docstring).  Commands name a module and an
    axis; every command needs ACTIVE (:class:`~swpc_hw.drives.errors.LifecycleError` names the
    fault that stopped the drives otherwise) except :meth:`stop_all`."""

    clock: Clock
    config: CanConfig
    """The bus and timing settings every kind gets (interface, channel, bitrate, feedback
    rate, watchdog, refresh, heartbeat loss, limits, dead-man, CAN log)."""
    last_exception: BaseException | None
    """The last exception a receive callback raised (it also stopped the drives)."""

    # ------------------------------------------------------------ lifecycle
    @property
    def state(self) -> Lifecycle: ...

    @property
    def fault_cause(self) -> str | None:
        """Why the drives last dropped from ACTIVE on a fault (None after activate() or an
        orderly deactivate())."""
        ...

    def configure(self) -> None:
        """UNCONFIGURED -> INACTIVE: open the bus, start watching the drives."""
        ...

    def activate(self) -> None:
        """INACTIVE -> ACTIVE: every drive alive, its dead-man armed, commands flow;
        :class:`~swpc_hw.drives.errors.NodeTimeoutError` names the silent drives."""
        ...

    def deactivate(self) -> None:
        """ACTIVE -> INACTIVE: every axis free and disabled, nothing sent any more."""
        ...

    def shutdown(self) -> None:
        """Any state -> FINALIZED (idempotent): stop_all() if active, close the bus."""
        ...

    def stop_all(self) -> None:
        """Zero torque and disable on every axis, the dead-man's renewals ended: what every
        fault path calls; sends whenever the bus is open, whatever the state."""
        ...

    # ------------------------------------------------------------ commands
    def enable(self, module: int, axis: Axis) -> None:
        """Power one axis (closed loop, zero torque)."""
        ...

    def clear_errors(
        self, module: int, axes: tuple[Axis, ...] = (Axis.STEER, Axis.WHEEL)
    ) -> None: ...

    def set_limits(self, module: int, axis: Axis, max_torque: float, max_velocity: float) -> None:
        """Torque (N.m) and velocity (rad/s) limits of one axis, at the output."""
        ...

    def set_position(self, module: int, axis: Axis, position: float) -> None:
        """Position control to ``position`` (rad, the axis' multi-turn coordinate)."""
        ...

    def set_velocity(self, module: int, axis: Axis, velocity: float) -> None:
        """Velocity control at ``velocity`` (rad/s at the output)."""
        ...

    def set_torque(self, module: int, axis: Axis, torque: float) -> None:
        """Torque control at ``torque`` (N.m at the output)."""
        ...

    def hold(self, module: int, axis: Axis) -> None:
        """Hold the current position (steering lock, wheel brake)."""
        ...

    def free(self, module: int, axis: Axis) -> None:
        """Zero torque: the axis turns freely."""
        ...

    def start_homing(self, module: int) -> None:
        """Start the steering axis's homing (the axis enabled); ``homed`` in
        :meth:`module_state` once done."""
        ...

    # ------------------------------------------------------------ observation
    def modules(self) -> list[int]: ...

    def module_state(self, module: int) -> ModuleState:
        """The latest known state of one module's drives (a snapshot)."""
        ...

    def axis_status(self, module: int, axis: Axis) -> AxisStatus | None:
        """What the host knows now of one axis' drive: its node, liveness, last heartbeat,
        state, mode and error named in the kind's words (a snapshot, read only; sends
        nothing).  None from a kind that reports whole modules only (its
        :meth:`module_state`)."""
        ...

    def history_since(
        self, module: int, cursor: int, since: float
    ) -> tuple[FloatArray, int]:
        """Feedback rows ``(t, theta_hat, psi)`` after ``cursor`` (0 at first) with clock
        time >= ``since``, and the new cursor: each row once, as it comes."""
        ...

    def wait_for(
        self,
        module: int,
        predicate: Callable[[ModuleState], bool],
        timeout: float,
        what: str = "condition",
    ) -> ModuleState:
        """Block (on the drives' clock) until ``predicate(module_state)`` holds;
        :class:`~swpc_hw.drives.errors.NodeTimeoutError` naming ``what`` otherwise."""
        ...

    def stats(self) -> DriverStats: ...

    def add_feedback_callback(self, fn: Callable[[int, FeedbackSample], None]) -> None:
        """``fn(module, sample)`` for every feedback sample, on the receive path.  A
        sample's ``seq`` counts the samples at ``config.feedback_rate_hz`` (gaps
        included), so ``seq / rate`` is the drive's own time of the sample."""
        ...

    def add_event_callback(self, fn: Callable[[DriverEvent], None]) -> None: ...

    def remove_event_callback(self, fn: Callable[[DriverEvent], None]) -> None: ...

    # ------------------------------------------------------------ recording
    def start_recording(self, path: str) -> None:
        """Every frame in and out to ``path`` (candump ``.log``) until stop_recording()."""
        ...

    def stop_recording(self) -> str | None:
        """Stop the recording (idempotent); why it stopped early, if it did."""
        ...

    def log_error(self) -> str | None:
        """Why the rolling CAN log stopped (a failed write), if it did."""
        ...


class DriveKind(ABC):
    """What a drive kind implements on :class:`swpc_hw.drives.base.DriverBase` (which
    owns everything else): its protocol, as python-can's ``BusABC`` leaves a bus its
    ``send`` and ``_recv_internal``.  The abstract methods are the least a kind writes
    (docs/drives.md shows one); the others are hooks with a default."""

    def _receive_filters(self) -> list[dict[str, int | bool]] | None:
        """The kernel's receive filters on SocketCAN (None: every frame)."""
        return None

    def _node_of(self, arbitration_id: int) -> int | None:
        """The node a frame sent with this id goes to, if the kind tracks it (its
        ``last_tx``, a send error's message)."""
        return None

    def _before_open(self) -> None:
        """Before the bus opens in configure() (a kind's own checks of its config)."""
        return None

    def _opened(self, bus: can.BusABC) -> None:
        """After the bus opened in configure(), the lock held (a kind's own protocol
        stack on it)."""
        return None

    def _drained(self) -> None:
        """After the frames of an I/O step were received (a kind that collects what its
        protocol library reported while they were dispatched handles it here)."""
        return None

    def _apply_frame(self, msg: can.Message, t: float) -> Applied:
        """What one received frame tells (the kind's pure core; under the lock)."""
        raise NotImplementedError

    @abstractmethod
    def _check(self, now: float, active: bool) -> Supervision:
        """Heartbeat loss and the refresh at ``now`` (the kind's pure core; lock held)."""

    def _keep_alive(self, now: float, active: bool) -> float:
        """The kind's own periodic frames at ``now``; returns when next due."""
        return math.inf

    @abstractmethod
    def _bring_up(self) -> None:
        """activate()'s part before ACTIVE: every drive alive, set up, its dead-man
        armed (:class:`NodeTimeoutError`, :class:`~swpc_hw.drives.errors.NodeError`)."""

    def _activated(self) -> None:
        """Just turned ACTIVE (the lock held)."""
        return None

    def _after_activate(self) -> None:
        """activate()'s part once ACTIVE (the frames that start the drives)."""
        return None

    @abstractmethod
    def _stopping(self) -> None:
        """stop_all(): forget every setpoint (the lock held)."""

    @abstractmethod
    def _stop_frames(self) -> list[Frame]:
        """stop_all(): the frames that stop every axis."""

    @abstractmethod
    def enable(self, module: int, axis: Axis) -> None:
        """Power one axis (closed loop, zero torque)."""

    @abstractmethod
    def clear_errors(
        self, module: int, axes: tuple[Axis, ...] = (Axis.STEER, Axis.WHEEL)
    ) -> None: ...

    @abstractmethod
    def set_limits(self, module: int, axis: Axis, max_torque: float, max_velocity: float) -> None:
        """Torque (N.m) and velocity (rad/s) limits of one axis, at the output."""

    @abstractmethod
    def set_position(self, module: int, axis: Axis, position: float) -> None:
        """Position control to ``position`` (rad, the axis' multi-turn coordinate)."""

    @abstractmethod
    def set_velocity(self, module: int, axis: Axis, velocity: float) -> None:
        """Velocity control at ``velocity`` (rad/s at the output)."""

    @abstractmethod
    def set_torque(self, module: int, axis: Axis, torque: float) -> None:
        """Torque control at ``torque`` (N.m at the output)."""

    @abstractmethod
    def hold(self, module: int, axis: Axis) -> None:
        """Hold the current position (steering lock, wheel brake)."""

    @abstractmethod
    def free(self, module: int, axis: Axis) -> None:
        """Zero torque: the axis turns freely."""

    @abstractmethod
    def start_homing(self, module: int) -> None:
        """Start the steering axis's homing (``homed`` in module_state once done)."""
