"""The ``odrive`` drive kind: ODrive axes over CAN Simple (:mod:`.driver`, :mod:`.tracking`)."""
