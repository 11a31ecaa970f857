"""The calibration service: what runs a calibration on a robot and serves it over HTTP.

Its rooms, each importing only the rooms below it (import-linter contract
``services-rooms`` in ``pyproject.toml``)::

    demo       make demo: the service and an operator's calibration, end to end
    cli        the swpc command, one module per subcommand
    http       the HTTP API (FastAPI), one router per resource, the operator console
    runtime    what the service holds while it runs: clock, bus, drives, sensors, runs
    runs       one calibration: the protocol, its state machine, its metrology, what it
               records and how its result is solved and installed
    sensors    motion-capture and gyro ingest (zenoh subscribers)
    store      what the service keeps on disk: the run store, the disk budget, locks,
               log lines, provenance
    config     the service's settings, the robot config and the timing budget
"""
