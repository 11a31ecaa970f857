"""How the virtual robot moves: ``core`` (the casters' and the body's equations, shared with
the offline generator), ``robot`` (the whole robot under its drives, in time steps)."""
