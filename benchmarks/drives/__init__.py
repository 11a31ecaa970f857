"""Benchmarks of the drives: the CAN kinds' bus load and latency, the virtual robot, and
commissioning against miswired robots."""
