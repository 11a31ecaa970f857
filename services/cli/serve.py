"""``swpc serve``: run the calibration service (FastAPI on uvicorn).

With no CAN settings (``SWPC_CAN_INTERFACE`` unset) it runs on the in-process simulator:
the virtual robot in the service's process on a virtual bus, zenoh on loopback, in
simulated time.  Settings come from ``SWPC_*`` environment variables, an env file
(``--env-file``, which must exist) and the flags below, which override them.  With no
token set it binds to loopback only, keeping a generated token in
``<data dir>/api-token`` (mode 0600); never printed.  Log lines: :mod:`services.store.logs`.
"""

from __future__ import annotations

import argparse
import socket
from pathlib import Path
from typing import Any

from services.config.log_options import LOG_FORMATS, LOG_LEVELS


def register(sub: Any) -> None:
    p = sub.add_parser("serve", help="run the calibration service (HTTP API)")
    p.add_argument("--host", help="bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default 8080)")
    p.add_argument("--env-file", help="file of SWPC_* settings")
    p.add_argument("--data-dir", help="runs, datasets, logs, kinematic file")
    p.add_argument(
        "--time-scale", type=float, help="time scale of an external simulator (swpc sim)"
    )
    p.add_argument(
        "--sim-speed",
        type=float,
        help="in-process simulator: most simulated s per wall s (default 0: unbounded)",
    )
    p.add_argument(
        "--log-level",
        type=str.lower,
        choices=LOG_LEVELS,
        help="lowest level of swpc's and uvicorn's log lines (default info; SWPC_LOG_LEVEL)",
    )
    p.add_argument(
        "--log-format",
        type=str.lower,
        choices=LOG_FORMATS,
        help="text (default) or json: one object per line (SWPC_LOG_FORMAT)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging

    from pydantic import ValidationError

    from services.config.settings import ServiceSettings, SettingsError
    from services.http.app import create_app
    from services.http.edge.server import listen_socket, server
    from services.runtime.runtime import Runtime
    from services.store.logs import configure, event

    if args.env_file is not None and not Path(args.env_file).is_file():
        raise SettingsError(f"--env-file {args.env_file}: no such file")
    overrides: dict[str, Any] = {}
    for key in ("host", "port", "data_dir", "time_scale", "sim_speed", "log_level", "log_format"):
        value = getattr(args, key)
        if value is not None:
            overrides[key] = value
    try:
        settings = ServiceSettings(_env_file=args.env_file, **overrides)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(x) for x in first["loc"])
        raise SettingsError(f"setting {where}: {first['msg']}") from None
    configure(settings.log_level, settings.log_format)
    settings.check_token()  # a weak token, or none beyond loopback: before anything else
    generated = settings.token is None
    # The runtime is opened here, not in uvicorn's lifespan: an error (the data dir or the
    # CAN channel in use, an interface that cannot be opened, a zenoh endpoint taken) then
    # reaches the command's one-line handler, not a traceback and uvicorn's exit status 3.
    # The data dir's lock comes first: a second service stops before writing anything.
    runtime = Runtime(settings)
    sock: socket.socket | None = None
    try:
        app = create_app(settings, runtime_factory=lambda _s: runtime)
        log = logging.getLogger("swpc.service")
        if generated:
            event(log, logging.WARNING, "service.token_generated", file=str(settings.token_file))
        sock = listen_socket(settings.host, settings.port)
        runtime.open()
        host, port = sock.getsockname()[:2]
        event(log, logging.INFO, "service.listen", host=host, port=port)
        server(
            app,
            host=settings.host,
            port=settings.port,
            header_timeout=settings.header_timeout,
            max_connections=settings.max_connections,
            log_level=settings.log_level,
        ).run(sockets=[sock])
    finally:
        runtime.close()  # idempotent: the lifespan has closed it, unless it never ran
        if sock is not None:
            sock.close()
    return 0
