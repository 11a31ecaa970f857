"""A calibration in base_link, and the kinematic file export (pure; docs/ros2.md).

:func:`make_export` re-expresses a kinematic file's parameters and covariance in the
robot's base_link (:func:`swpc_hw.robot.frames.to_base_link`) and says in a header where they
came from and how base_link was placed; the renderers turn an :class:`Export` into text,
with no I/O:

* :func:`swpc_hw.onboard.export.urdf.render_urdf`: a URDF of the caster modules;
* :func:`swpc_hw.onboard.export.ros2_params.render_ros2_params`: a ROS 2 parameter file;
* :func:`render_kinematics`: the kinematic file itself, ``frame: base_link``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml

from swpc_hw.files.kinematic_file import KinematicFile, kinematics_document, parse_kinematics
from swpc_hw.robot.frames import (
    BASE_LINK,
    CENTROID,
    DESIGN_FIT,
    BaseLink,
    BaseLinkPose,
    to_base_link,
)
from swpc_hw.robot.model import RobotParams

FloatArray = np.ndarray[Any, np.dtype[np.float64]]


@dataclass(frozen=True)
class Export:
    """A calibration in base_link, ready to render."""

    params: RobotParams
    """The parameters in base_link (``frame: base_link``), std devs when known."""
    covariance: FloatArray | None
    """Their (5N, 5N) covariance in base_link, or None when the file has none."""
    header: tuple[str, ...]
    """Lines that say what this is: robot, source, how base_link was placed."""
    created: str
    """The source file's ``created``."""
    polarity: Mapping[int, tuple[int, int]] | None = field(default=None)
    """The robot config's polarity, module id -> (steer, wheel) (``swpc_hw.drives.types.
    AxisSigns``; a module left out is (1, 1)), or None when no robot config was given: which
    joints turn the other way round from what their drives report."""

    def signs(self, module: int) -> tuple[int, int] | None:
        """``module``'s (steer, wheel) polarity, or None when unknown."""
        if self.polarity is None:
            return None
        steer, wheel = self.polarity.get(module, (1, 1))
        return steer, wheel


def base_link_words(base_link: BaseLink | None, params_in_r: RobotParams) -> str:
    """How base_link was placed, in one line (the exports' headers)."""
    if params_in_r.frame == BASE_LINK:
        return "the source file is in base_link already (the robot config's base_link unused)"
    if base_link is None:
        words = "base_link = R, the identity: the robot config sets no base_link"
    elif base_link == CENTROID:
        cx, cy = (float(v) for v in params_in_r.arrays().P_s.mean(axis=0))
        words = (
            "base_link: centroid: origin at the centroid of the calibrated steering axes, "
            f"({cx!r}, {cy!r}) m in R, x along R's x"
        )
    else:
        assert isinstance(base_link, BaseLinkPose)
        words = (
            f"base_link's pose in R (robot config): x {base_link.x!r} m, y {base_link.y!r} m, "
            f"yaw {base_link.yaw!r} rad"
        )
    if params_in_r.frame == DESIGN_FIT:
        words += "; the source is in design-fit (no motion capture), taken as R"
    return words


def make_export(
    kf: KinematicFile,
    base_link: BaseLink | None,
    source: str,
    polarity: Mapping[int, tuple[int, int]] | None = None,
) -> Export:
    """The file ``kf`` (named ``source`` in the header) in base_link, with the robot
    config's ``polarity`` when given (:attr:`Export.polarity`).

    Raises ``ValueError`` for a file in a frame that is neither R, design-fit nor
    base_link (:func:`swpc_hw.robot.frames.to_base_link`).
    """
    params, cov = to_base_link(kf.params, kf.covariance, base_link)
    prov = kf.extra.get("provenance")
    origin = f"source: {source}, created {kf.created or 'unknown'}"
    if isinstance(prov, dict) and prov.get("run"):
        origin += f", run {prov['run']}"
    header = (
        f"swpc calibration of robot {params.robot}, frame {BASE_LINK} (SI units: m, rad)",
        origin,
        base_link_words(base_link, kf.params),
    )
    return Export(
        params=params,
        covariance=cov,
        header=header,
        created=kf.created,
        polarity=None if polarity is None else dict(polarity),
    )


def render_kinematics(exp: Export) -> str:
    """The kinematic file (docs/kinematic-file.md) in base_link, the header as
    ``exported`` lines; ``created`` is the source's.  Parsed back before it is returned."""
    doc = kinematics_document(
        exp.params,
        created=exp.created or None,
        covariance=exp.covariance,
        extra={"exported": list(exp.header)},
    )
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=False)
    parse_kinematics(yaml.safe_load(text), "export")
    return text
