"""The operator console: a web page served by ``swpc serve`` at ``/`` (see :mod:`.router`)."""

from services.http.console.router import console_router

__all__ = ["console_router"]
