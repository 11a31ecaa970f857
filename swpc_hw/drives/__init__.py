"""The robot's drives, whatever their kind: the robot-side library's API (docs/drives.md).

* :mod:`.interface` -- :class:`~.interface.Drives`, what a run sees of the drives;
  :mod:`.robot_io` -- :class:`~.robot_io.RobotIO`, what the calibration state machine sees;
* :mod:`.registry` -- the kinds by name (built-in, registered, entry points ``swpc.drives``)
  and :func:`~.registry.open_drives`;
* :mod:`.base` (with :mod:`.observation`) -- :class:`~.base.DriverBase`, the one base of
  every kind: lifecycle, I/O step, supervision, fault path, events;
* shared by the kinds: :mod:`.types`, :mod:`.errors`, :mod:`.bus` (the bus and timing
  settings, the drive facts), :mod:`.tracking`, :mod:`.periodic` (the kernel's refresh
  with its dead-man), :mod:`.recording`;
* the kinds, each only its protocol, none importing another: :mod:`.swpc`,
  :mod:`.cia402`, :mod:`.odrive`.
"""
