"""``swpc fleet``'s HTTP side: the fleet page and its JSON (see :mod:`.app`)."""
