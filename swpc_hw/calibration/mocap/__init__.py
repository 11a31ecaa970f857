"""The motion-capture solver: the joint least squares over poses and encoders, its clock
offset and covariance, and the paper's own procedure (the baseline)."""
