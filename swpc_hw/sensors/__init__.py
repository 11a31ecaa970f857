"""The sensors' messages as they arrive over zenoh: motion capture poses, gyro samples,
the zenoh session."""
