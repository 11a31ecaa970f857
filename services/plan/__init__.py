"""A calibration planned from the information it yields (docs/plan.md): ``planner`` (the
robot config's plan, made in the background and kept), ``predict`` (a candidate's std devs
before the robot moves, played through the offline generator)."""
