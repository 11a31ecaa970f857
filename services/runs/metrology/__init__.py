"""What measures the robot's motion in a run: ``base`` (the interface a run measures
through), ``mocap`` (motion capture: poses, with ``pose_motion``), ``imu`` (the gyro, the
encoders and a tape measure, with ``gyro_motion``)."""
