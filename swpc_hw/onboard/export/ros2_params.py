"""The calibration as a ROS 2 parameter file, in base_link (pure; docs/ros2.md).

Two nodes' parameters:

* ``swerve_drive_controller``: the layout of ros2_controllers' ``swerve_drive_controller``
  (ros-controls/ros2_controllers pull request 1694,
  ``swerve_drive_controller/src/swerve_drive_controller_parameter.yaml``): four modules
  named front/rear left/right, their joints, ``wheelbase``, ``trackwidth`` and one
  ``wheel_radius``.  That controller places the wheels at ``(+-wheelbase/2,
  +-trackwidth/2)`` about base_link's origin, under their steering axes, and takes a
  steering position of 0 as a wheel along base_link's x.  From the calibration, with the
  modules sorted into quadrants about the steering axes' centroid ``c``::

      wheelbase    = (x_FL + x_FR)/2 - (x_RL + x_RR)/2
      trackwidth   = (y_FL + y_RL)/2 - (y_FR + y_RR)/2
      wheel_radius = (1/4) sum_i r_i

  Each is linear in the parameters, ``q = g . X``, and its std dev is
  ``sqrt(g^T C g)`` with the file's covariance ``C`` (or, without one, the modules'
  std devs taken as independent; the file says which).  What the layout cannot hold
  is written as comments: each steering axis' distance from its rectangle corner, the
  steering zeros ``beta``, the caster offsets ``b`` and the spread of the radii.
* ``swpc_kinematics``: every module's calibrated ``x_s``, ``y_s``, ``beta``, ``b``,
  ``r`` as arrays in module order, with their std devs as comments: the whole
  calibration, for a node that uses the caster model.  With the robot config
  (``swpc export --robot-config``), also ``steer_polarity`` and ``wheel_polarity`` in
  module order: -1 for a joint that turns the other way round from what its drive reports
  (docs/commissioning.md), which the robot's hardware interface turns in what it reads
  and commands; ``swerve_drive_controller`` has no such parameter, so a comment names
  those joints there.
"""

from __future__ import annotations

import math

import numpy as np

from swpc_hw.onboard.export.core import Export
from swpc_hw.onboard.export.urdf import steer_joint, wheel_joint
from swpc_hw.robot.frames import BASE_LINK
from swpc_hw.robot.model import PARAM_NAMES

CONTROLLER = "swerve_drive_controller"
"""The node name of the controller layout followed."""
KINEMATICS_NODE = "swpc_kinematics"
"""The node name of the full calibration's parameters."""
CORNERS = ("front_left", "front_right", "rear_left", "rear_right")
_UNITS = {"x_s": "m", "y_s": "m", "beta": "rad", "b": "m", "r": "m"}


def quadrants(P_s: np.ndarray) -> dict[str, int]:
    """Each corner's module index: front = x above the centroid's, left = y above it.
    Raises ``ValueError`` unless there are four modules, one in each quadrant."""
    P = np.asarray(P_s, dtype=float).reshape(-1, 2)
    if P.shape[0] != 4:
        raise ValueError(
            f"ros2-params: the {CONTROLLER} layout has four modules (this robot has {P.shape[0]})"
        )
    c = P.mean(axis=0)
    out: dict[str, int] = {}
    for i, (x, y) in enumerate(P):
        corner = f"{'front' if x > c[0] else 'rear'}_{'left' if y > c[1] else 'right'}"
        if corner in out:
            raise ValueError(
                f"ros2-params: the {CONTROLLER} layout needs one module in each quadrant "
                f"about the steering axes' centroid; modules {out[corner] + 1} and {i + 1} "
                f"(in file order) are both {corner}"
            )
        out[corner] = i
    return out


def _std(g: np.ndarray, exp: Export) -> str:
    """``sqrt(g^T C g)`` as a comment, C from the covariance or the std devs."""
    if exp.covariance is not None:
        return f"std dev {math.sqrt(max(float(g @ exp.covariance @ g), 0.0)):.3g} m"
    if all(m.stddev is not None for m in exp.params.modules):
        var = np.array(
            [v**2 for m in exp.params.modules if m.stddev is not None for v in m.stddev.values()]
        )
        return f"std dev {math.sqrt(float(g**2 @ var)):.3g} m (modules taken as independent)"
    return "std dev unknown"


def _floats(values: list[float]) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _polarity_words(exp: Export) -> list[str]:
    """A line per joint that turns the other way round from what its drive reports."""
    out = []
    for m in exp.params.modules:
        joints = (steer_joint(m.id), wheel_joint(m.id))
        for sign, joint in zip(exp.signs(m.id) or (1, 1), joints, strict=True):
            if sign == -1:
                out.append(
                    f"{joint}: polarity -1 (it turns the other way round from what its drive "
                    "reports: the hardware interface turns it)"
                )
    return out


def render_ros2_params(exp: Export) -> str:
    """The parameter file (module docstring).  Raises ``ValueError`` when the robot does
    not have four modules, one per quadrant (:func:`quadrants`)."""
    p = exp.params
    a = p.arrays()
    n = a.n
    q = quadrants(a.P_s)
    k = len(PARAM_NAMES)

    def grad(weights: dict[int, float], param: int) -> np.ndarray:
        g = np.zeros(k * n)
        for i, w in weights.items():
            g[k * i + param] += w
        return g

    fl, fr, rl, rr = (q[c] for c in CORNERS)
    g_wb = grad({fl: 0.5, fr: 0.5, rl: -0.5, rr: -0.5}, 0)
    g_tw = grad({fl: 0.5, rl: 0.5, fr: -0.5, rr: -0.5}, 1)
    g_r = grad({i: 1.0 / n for i in range(n)}, 4)
    X = a.matrix().reshape(-1)
    wheelbase, trackwidth, radius = float(g_wb @ X), float(g_tw @ X), float(g_r @ X)
    c = [float(v) for v in a.P_s.mean(axis=0)]

    lines = [f"# {h}" for h in exp.header]
    lines += [
        f"# {CONTROLLER}: the layout of ros2_controllers' swerve_drive_controller",
        "#   (ros-controls/ros2_controllers pull request 1694, not in a release yet:",
        "#   swerve_drive_controller/src/swerve_drive_controller_parameter.yaml).",
        "#   It places the wheels at (+-wheelbase/2, +-trackwidth/2) about base_link's origin,",
        "#   under the steering axes, with one radius, and takes steering position 0 as the",
        "#   wheel along base_link's x. What it cannot hold is in the comments below and in",
        f"#   {KINEMATICS_NODE}; swpc's URDF (swpc export --to urdf) holds all of it.",
        f"#   The steering axes' centroid is at ({c[0]!r}, {c[1]!r}) m in base_link",
        "#   (0, 0 with the robot config's base_link: centroid).",
        f"{CONTROLLER}:",
        "  ros__parameters:",
    ]
    for corner in CORNERS:
        lines.append(f"    {corner}_wheel_joint: {wheel_joint(int(a.ids[q[corner]]))}")
    for corner in CORNERS:
        lines.append(f"    {corner}_axle_joint: {steer_joint(int(a.ids[q[corner]]))}")
    lines += [
        f"    wheelbase: {wheelbase!r}  # {_std(g_wb, exp)}",
        f"    trackwidth: {trackwidth!r}  # {_std(g_tw, exp)}",
        f"    wheel_radius: {radius!r}  # mean of the {n} radii; {_std(g_r, exp)}",
        "    # Per module, what the layout leaves out:",
    ]
    lines += [f"    #   {w}" for w in _polarity_words(exp)]
    for corner in CORNERS:
        i = q[corner]
        sx = 1.0 if corner.startswith("front") else -1.0
        sy = 1.0 if corner.endswith("left") else -1.0
        dev = math.hypot(
            a.P_s[i, 0] - (c[0] + sx * wheelbase / 2), a.P_s[i, 1] - (c[1] + sy * trackwidth / 2)
        )
        lines.append(
            f"    #   {corner} (module {int(a.ids[i])}): steering axis {dev:.3g} m from the "
            f"rectangle's corner; beta {a.beta[i]:.6g} rad (steering zero), b {a.b[i]:.6g} m "
            f"(caster offset), r {a.r[i]:.6g} m"
        )
    lines += [
        f"{KINEMATICS_NODE}:",
        "  ros__parameters:",
        f"    frame_id: {BASE_LINK}",
        f"    module_ids: [{', '.join(str(int(i)) for i in a.ids)}]",
        f"    steer_joints: [{', '.join(steer_joint(int(i)) for i in a.ids)}]",
        f"    wheel_joints: [{', '.join(wheel_joint(int(i)) for i in a.ids)}]",
    ]
    signs = [exp.signs(int(i)) for i in a.ids]
    if all(sg is not None for sg in signs):
        for axis, label in ((0, "steer"), (1, "wheel")):
            column = ", ".join(str(sg[axis]) for sg in signs if sg is not None)
            lines.append(f"    {label}_polarity: [{column}]  # robot config polarity")
    else:
        lines.append("    # polarity: no robot config given (swpc export --robot-config adds it)")
    for j, name in enumerate(PARAM_NAMES):
        values = [float(X[k * i + j]) for i in range(n)]
        lines.append(f"    {name}: {_floats(values)}  # {_UNITS[name]}")
        if all(m.stddev is not None for m in p.modules):
            sds = ", ".join(f"{getattr(m.stddev, name):.3g}" for m in p.modules)
            lines.append(f"    #   std devs: [{sds}] {_UNITS[name]}")
        else:
            lines.append("    #   std devs unknown")
    return "\n".join(lines) + "\n"
