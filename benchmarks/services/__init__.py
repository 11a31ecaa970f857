"""Benchmarks of the service: HTTP, aborts under load, the fleet, disk, soak, the mocap bridge."""
