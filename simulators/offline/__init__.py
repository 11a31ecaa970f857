"""Simulated data without a running robot: ``datagen`` (a calibration experiment written as
a dataset), ``datagen_imu`` (the same without motion capture: gyro and tape), ``random_robots``
(plausible robots and closed-form experiments), ``drift_path`` (driving with a drifted
calibration, for the drift monitor); ``phases`` (the generator's motion, piece by piece)."""
