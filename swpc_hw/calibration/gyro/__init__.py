"""The gyro solver (the imu metrology): encoders, the gyro and tape-measured references,
without motion capture (docs/imu.md)."""
