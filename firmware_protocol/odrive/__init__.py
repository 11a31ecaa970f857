"""ODrive's CAN Simple protocol (ODrive v3.6 on firmware 0.5.x, S1 and Pro on 0.6.x).

The frames are ODrive's own DBCs, as the maintained ``odrive-can`` package ships them
(MIT; ``odrive-cansimple-0.5.6.dbc`` is byte for byte ODrive's ``tools/odrive-cansimple.dbc``
of firmware 0.5.6, ``odrive-cansimple-0.6.10.dbc`` the 0.6.x one), read with cantools:
:mod:`firmware_protocol.odrive.can_simple`.  Nothing here packs a byte by hand.
"""
