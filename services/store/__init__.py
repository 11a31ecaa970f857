"""What the service keeps in its data dir: the run store (SQLite), the disk budget, the
locks that make it one service per data dir and CAN channel, structured log lines and
the provenance written into every kinematic file."""
