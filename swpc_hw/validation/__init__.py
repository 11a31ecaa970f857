"""Square-path validation drive: the seed's odometry test (paper Table 5, Figure 13).

The robot drives a square of side ``L`` (default 2.5 m) with a 90 deg turn in place at each
corner, clockwise and counter-clockwise, ``runs`` times each, at about 0.2 m/s, with one
kinematic file used for *both* control
(:class:`swpc_hw.onboard.twist_controller.TwistController`) and odometry
(:class:`swpc_hw.onboard.odometry.Odometry`); the end pose of the odometry is compared with
the true end pose (simulator truth key, or motion capture on a real robot).  Doing
this for the nominal and the calibrated file shows what calibration buys.

Everything goes through CAN exactly as on the robot:

* commands: per module, steering VELOCITY ``theta_hat_dot`` and wheel VELOCITY ``psi_dot``
  from the inverse kinematics of the commanded body twist at the reported steering
  (:meth:`TwistController.command`), refreshed at ``control_rate`` Hz of robot time (the
  driver itself keeps the controllers' watchdog fed);
* odometry: :class:`DriverOdometry` consumes the driver's feedback frames (``theta_hat``,
  ``psi`` per module, timed by the frames' bus time stamps on the driver's clock), one
  update per feedback cycle of all modules;
* truth: :class:`ZenohTruth` on the simulator's ``sim/<robot>/truth/pose`` (JSON) or on
  the motion-capture pose key ``mocap/<robot>/pose`` (:func:`swpc_hw.sensors.mocap.decode_pose`),
  averaged over a still window at the start and end of every run.

Path following happens in the odometry frame (the robot believes its odometry, as it would
in use).  Odometry is reset to the true start pose at the start of every run, so the errors
of one run are ``e_p = |p_odo,end - p_true,end|`` and
``e_yaw = |wrap(yaw_odo,end - yaw_true,end)|``; the report gives their means per file and
direction (mean absolute errors, as the paper).

The follower is :mod:`swpc_hw.onboard.square_path`; the odometry feed
:mod:`swpc_hw.validation.odometry_feed`; the truth :mod:`swpc_hw.validation.truth`; the
results :mod:`swpc_hw.validation.report`; the drive :mod:`swpc_hw.validation.drive`.
Time is the driver's clock (:mod:`swpc_hw.clock`).

Imports numpy and the CAN driver; zenoh only through a session object that the caller
opens; matplotlib only inside :meth:`ValidationReport.plot`.
"""

from swpc_hw.onboard.square_path import Direction, Leg, SquareOptions, follow_step, square_plan
from swpc_hw.validation.drive import SquareDrive, prepare_driver, validate
from swpc_hw.validation.errors import ValidationError
from swpc_hw.validation.odometry_feed import DriverOdometry
from swpc_hw.validation.report import RunResult, ValidationReport, to_start_frame
from swpc_hw.validation.truth import ZenohTruth, mocap_decoder, sim_truth_decoder

__all__ = [
    "Direction",
    "DriverOdometry",
    "Leg",
    "RunResult",
    "SquareDrive",
    "SquareOptions",
    "ValidationError",
    "ValidationReport",
    "ZenohTruth",
    "follow_step",
    "mocap_decoder",
    "prepare_driver",
    "sim_truth_decoder",
    "square_plan",
    "to_start_frame",
    "validate",
]
