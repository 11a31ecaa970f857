"""The operator console: a web page served by ``swpc serve`` at ``/`` (see :mod:`.router`)."""
