"""The calibration where a ROS 2 robot looks: every export in base_link (docs/ros2.md).

:func:`swpc_hw.onboard.export.core.make_export` re-expresses a kinematic file in the robot's
base_link; :func:`render` writes it as one of :data:`TARGETS` (pure: text in, text out):

* ``urdf``: :func:`swpc_hw.onboard.export.urdf.render_urdf`, the caster modules' joints and links;
* ``ros2-params``: :func:`swpc_hw.onboard.export.ros2_params.render_ros2_params`, a ROS 2
  parameter file in the layout of ros2_controllers' swerve_drive_controller, and the
  whole calibration;
* ``kinematics``: :func:`swpc_hw.onboard.export.core.render_kinematics`, the kinematic file with
  ``frame: base_link``.
"""

from __future__ import annotations

from swpc_hw.onboard.export.core import Export, make_export, render_kinematics
from swpc_hw.onboard.export.ros2_params import render_ros2_params
from swpc_hw.onboard.export.urdf import render_urdf

__all__ = ["TARGETS", "Export", "file_name", "make_export", "render"]

TARGETS: dict[str, tuple[str, str]] = {
    "urdf": (".urdf", "application/xml"),
    "ros2-params": (".ros2-params.yaml", "application/yaml"),
    "kinematics": (".base_link.yaml", "application/yaml"),
}
"""Each target of ``swpc export --to`` and ``GET /calibrations/{id}/export?to=``: the
suffix of its file name and its media type."""


def render(exp: Export, target: str) -> str:
    """``exp`` as ``target`` text; ``ValueError`` for an unknown target or one the robot
    does not fit (e.g. ros2-params for a robot without four modules)."""
    if target == "urdf":
        return render_urdf(exp)
    if target == "ros2-params":
        return render_ros2_params(exp)
    if target == "kinematics":
        return render_kinematics(exp)
    raise ValueError(f"unknown export target {target!r} (one of {', '.join(TARGETS)})")


def file_name(stem: str, target: str) -> str:
    """The export's file name: ``stem`` and the target's suffix."""
    return stem + TARGETS[target][0]
