"""The calibration experiment's default protocol: the one statement of it.

Every module locked in turn at each steering angle while the others spin the robot about
its wheel's contact point (docs/model-and-frames.md, "The calibration experiment"), with
the pauses between: what the robot config's ``protocol`` section holds when it says
nothing (``services.config.robot.ProtocolConfig``), what the offline generator plays
(``simulators.offline.datagen.ExperimentOptions``) and what the planner starts from
(:data:`swpc_hw.calibration.plan.plan.ANGLE_SETS`).  Degrees and seconds, as the robot config.
A module of its own, light: the robot config reads it, and ``swpc_hw.calibration``
imports the solver.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Protocol:
    """A calibration protocol (angles in degrees, times in seconds, lengths in metres)."""

    angles_deg: tuple[float, ...] = (45.0, 165.0)
    """Steering angles of the locked module (the paper's a1, a2)."""
    sweep_deg: float = 360.0
    """Yaw swept per spin, measured."""
    settle_time: float = 3.0
    """Spin time before the measurement window opens."""
    stop_time: float = 1.5
    """Time allowed to spin down."""
    align_time: float = 1.0
    """Time to align the dynamic modules before a spin."""
    resteer_time: float = 2.5
    """Time to re-steer the locked module to the next angle."""
    rest_time: float = 2.0
    """Without motion capture: the robot held still before every spin, around the straight
    drive and at the end (the gyro's bias)."""
    drive_length: float = 4.0
    """Without motion capture: the straight drive at the end (the wheel radii)."""


DEFAULT_PROTOCOL = Protocol()
"""The protocol of a robot config that states none."""

PRECHECK_TIME = 3.4
"""s of robot time: the fast part's probe of one module before the first spin (motion
capture, docs/commissioning.md): its steering moves, settling and a roll of 8 deg (3.1 to
3.8 s on the in-process simulator, the paper's robot, 2026-11-30; with the gyro alone 3.3
to 3.9 s, 2026-12-01)."""
GYRO_PRECHECK_MODULES = 4
"""Modules a robot needs for the fast part with the gyro alone: the locked one, the
driver and two free ones, whose wheels give the fixed point
(:mod:`swpc_hw.calibration.commission.trailing`)."""


def has_fast_part(n_modules: int, metrology: str, precheck: bool = True) -> bool:
    """Whether a run starts with the fast part (``protocol.precheck``): with motion
    capture always, with the gyro alone on :data:`GYRO_PRECHECK_MODULES` modules or more."""
    return precheck and (metrology == "mocap" or n_modules >= GYRO_PRECHECK_MODULES)
