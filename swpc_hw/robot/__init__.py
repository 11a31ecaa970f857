"""The robot model and its frames: a module's five parameters, the no-slip kinematics, R, W,
base_link and the fitted frames, the paper's robot."""
