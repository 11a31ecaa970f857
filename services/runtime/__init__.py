"""What the service holds while it runs (:class:`.runtime.Runtime`): the clock, the CAN bus
and its drives, the sensors, the runs; its health, the run events pushed to the console,
and the in-process simulator it runs against when no CAN interface is set."""
