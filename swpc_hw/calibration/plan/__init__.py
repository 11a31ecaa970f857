"""The plan: the protocol and spin torque that meet the targets and the square path's
budget in the least robot time, from each candidate's predicted information."""
