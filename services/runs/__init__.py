"""One calibration run: the protocol (:mod:`.protocol`) walks the states of :mod:`.state`
on the machinery of :mod:`.machine`, measures the robot's motion through its metrology
(motion capture, or the gyro and a tape measure: :mod:`.imu`), records everything as it
goes (:mod:`.journal`, :mod:`.recording`, :mod:`.mcap`) and ends by solving and installing
the kinematic file (:mod:`.install`)."""
