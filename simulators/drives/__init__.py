"""The virtual robot's drives, one module per drive kind (as ``swpc_hw.drives``): ``swpc``
(this project's firmware), ``cia402`` (CiA 402 over CANopen), ``odrive`` (ODrive CAN
Simple); ``base`` is what they share, ``factory`` the one place that knows the kinds."""
