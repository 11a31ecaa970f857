"""The robot's motion sensors as zenoh subscribers: motion capture (poses) and the gyro
(yaw rate), each sample checked and kept on the service clock."""
