"""Benchmarks of the calibration: the solvers' accuracy and honesty, the planner, the check."""
