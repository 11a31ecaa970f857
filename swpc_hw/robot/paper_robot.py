"""Reference robots from the paper (Kim, Park, Park 2023), Table 4.

``PAPER_NOMINAL`` is the design ("without calibration") and ``PAPER_CALIBRATED`` the
paper's calibrated values, used as the simulator's default hidden truth.
"""

from __future__ import annotations

import math

from swpc_hw.robot.model import ModuleParams, RobotParams

_DEG = math.pi / 180.0

PAPER_NOMINAL = RobotParams(
    robot="swpc",
    frame="R",
    modules=[
        ModuleParams(id=1, x_s=0.215, y_s=0.125, beta=0.0, b=0.020, r=0.055),
        ModuleParams(id=2, x_s=0.215, y_s=-0.125, beta=0.0, b=0.020, r=0.055),
        ModuleParams(id=3, x_s=-0.215, y_s=-0.125, beta=0.0, b=0.020, r=0.055),
        ModuleParams(id=4, x_s=-0.215, y_s=0.125, beta=0.0, b=0.020, r=0.055),
    ],
)

PAPER_CALIBRATED = RobotParams(
    robot="swpc",
    frame="R",
    modules=[
        ModuleParams(id=1, x_s=0.21616, y_s=0.12696, beta=0.6349 * _DEG, b=0.0203907, r=0.0543960),
        ModuleParams(id=2, x_s=0.21652, y_s=-0.12474, beta=1.5247 * _DEG, b=0.0202223, r=0.0547413),
        ModuleParams(
            id=3, x_s=-0.21622, y_s=-0.12526, beta=0.9764 * _DEG, b=0.0203055, r=0.0559731
        ),
        ModuleParams(id=4, x_s=-0.21667, y_s=0.12647, beta=1.2154 * _DEG, b=0.0202897, r=0.0556682),
    ],
)
