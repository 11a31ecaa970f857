"""swpc_hw — robot-side library for SWPC robots.

Kinematic model, kinematic file I/O, offline datasets, calibration solver,
odometry and the CAN driver for the dual-axis motor controllers.
Conventions (units, frames, formats): ``docs/`` at the repository root.
"""

__version__ = "0.1.0"
