"""The files swpc reads and writes: the kinematic file, the dataset, the tape-measured
references."""
