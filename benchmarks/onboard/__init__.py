"""Benchmarks of what the robot runs on board: odometry, the drift monitor, the square path."""
