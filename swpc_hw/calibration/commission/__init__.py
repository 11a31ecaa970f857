"""Commissioning: what a robot's drives really move, measured before the first calibration
(docs/commissioning.md): the probes' observations and what they say
(:mod:`swpc_hw.calibration.commission.analysis`)."""
