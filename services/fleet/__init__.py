"""``swpc fleet``'s core: every robot's state from zenoh into the fleet store, and what
the fleet view shows of it (status, drift).  See docs/fleet.md."""
