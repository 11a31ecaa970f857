"""The virtual robot's sensors over zenoh: ``mocap`` (motion capture, its truth) and
``gyro`` (the IMU's yaw rate, the tape measure's readings)."""
