"""The caster modules as a URDF, in base_link (pure; docs/ros2.md).

Per module ``i`` (id ``k``), with the model of docs/model-and-frames.md in base_link::

    base_link --steer_k (continuous, axis z)--> steer_k_link
              origin xyz (x_s, y_s, 0), rpy (0, 0, beta)
    steer_k_link --wheel_k (continuous, axis y)--> wheel_k_link
              origin xyz (b, 0, r)

base_link's z = 0 is the floor (the model is planar).  The steering joint's position is
the reported steering angle ``theta_hat``: its zero is at ``beta`` from base_link's x, so
``steer_k_link``'s x axis is at ``theta = theta_hat + beta``, along ``u(theta)``.  The
wheel's centre is then at ``P_s + b u(theta)`` at height ``r``, and its contact point,
the centre less ``r`` along z, is the model's ``P_w = P_s + b u(theta)`` on the floor.
The wheel joint's position is the wheel angle ``psi``: a positive rotation about the
steering link's y moves the wheel centre along ``+u`` by ``r dpsi`` when it rolls without
slip, the model's ``r psi_dot u``.  ``wheel_k_link`` carries a cylinder of radius ``r``
(its width is for display only: the model has none).
"""

from __future__ import annotations

import math
from xml.sax.saxutils import quoteattr

from swpc_hw.onboard.export.core import Export
from swpc_hw.robot.frames import BASE_LINK

WHEEL_WIDTH = 0.02
"""The wheel cylinders' width, m: for display only (the model has no width)."""


def steer_joint(module_id: int) -> str:
    """The steering joint's name for module ``module_id``."""
    return f"steer_{module_id}"


def wheel_joint(module_id: int) -> str:
    """The wheel joint's name for module ``module_id``."""
    return f"wheel_{module_id}"


def _num(x: float) -> str:
    return repr(float(x))  # round-trips exactly


def _comment(text: str) -> str:
    return text.replace("--", "- -")


def render_urdf(exp: Export, wheel_width: float = WHEEL_WIDTH) -> str:
    """The URDF of ``exp``'s modules (module docstring); numbers as Python's ``repr``, so
    a parser reads back the exact floats."""
    p = exp.params
    lines = ['<?xml version="1.0"?>', "<!--"]
    lines += [f"  {_comment(h)}" for h in exp.header]
    lines += [
        "  Per module k: joint steer_k (position: the reported steering angle, 0 at beta),",
        "  joint wheel_k (position: the wheel angle); base_link z = 0 is the floor.",
        f"  Wheel width {wheel_width!r} m: display only.",
        "-->",
        f"<robot name={quoteattr(p.robot)}>",
        f'  <link name="{BASE_LINK}"/>',
    ]
    half_pi = _num(math.pi / 2)
    for m in p.modules:
        steer, wheel = steer_joint(m.id), wheel_joint(m.id)
        if m.stddev is not None:
            s = m.stddev
            lines.append(
                f"  <!-- module {m.id}: std devs x_s {s.x_s:.3g} m, y_s {s.y_s:.3g} m, "
                f"beta {s.beta:.3g} rad, b {s.b:.3g} m, r {s.r:.3g} m -->"
            )
        else:
            lines.append(f"  <!-- module {m.id}: std devs unknown -->")
        for sign, joint in zip(exp.signs(m.id) or (1, 1), (steer, wheel), strict=True):
            if sign == -1:
                lines.append(
                    f"  <!-- {joint}: polarity -1 in the robot config: the joint turns the "
                    "other way round from what its drive reports -->"
                )
        cylinder = (
            f'<origin xyz="0 0 0" rpy="{half_pi} 0 0"/>'
            f'<geometry><cylinder radius="{_num(m.r)}" length="{_num(wheel_width)}"/></geometry>'
        )
        lines += [
            f'  <joint name="{steer}" type="continuous">',
            f'    <parent link="{BASE_LINK}"/>',
            f'    <child link="{steer}_link"/>',
            f'    <origin xyz="{_num(m.x_s)} {_num(m.y_s)} 0.0" rpy="0.0 0.0 {_num(m.beta)}"/>',
            '    <axis xyz="0 0 1"/>',
            "  </joint>",
            f'  <link name="{steer}_link"/>',
            f'  <joint name="{wheel}" type="continuous">',
            f'    <parent link="{steer}_link"/>',
            f'    <child link="{wheel}_link"/>',
            f'    <origin xyz="{_num(m.b)} 0.0 {_num(m.r)}" rpy="0.0 0.0 0.0"/>',
            '    <axis xyz="0 1 0"/>',
            "  </joint>",
            f'  <link name="{wheel}_link">',
            f"    <visual>{cylinder}</visual>",
            f"    <collision>{cylinder}</collision>",
            "  </link>",
        ]
    lines.append("</robot>")
    return "\n".join(lines) + "\n"
