"""``swpc fleet``: the fleet view, every robot's state over zenoh (docs/fleet.md).

Subscribes to every robot's state (``swpc/fleet/*/state``) and liveliness token through a
zenoh router, keeps every robot's documents in ``<data dir>/fleet.sqlite`` and serves the
fleet page and its JSON (``GET /robots``, ``GET /robots/{name}``).  Settings come from
``SWPC_FLEET_*`` environment variables, an env file (``--env-file``) and the flags below,
which override them.  With ``--zenoh-mode router`` the fleet service is itself the router
the robots connect to (``--zenoh-config deploy/zenoh/fleet-router.json5``).  Read-only: it
binds to loopback unless told otherwise.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from services.config.log_options import LOG_FORMATS, LOG_LEVELS


def register(sub: Any) -> None:
    p = sub.add_parser(
        "fleet",
        help="the fleet view: every robot's state over zenoh, its status and drift",
        description=__doc__.split("\n\n", 1)[1] if __doc__ else None,
    )
    p.add_argument("--host", help="bind address (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="port (default 8090)")
    p.add_argument("--env-file", help="file of SWPC_FLEET_* settings")
    p.add_argument("--data-dir", help="where the fleet store is kept")
    p.add_argument("--zenoh-mode", dest="mode", choices=("peer", "client", "router"))
    p.add_argument("--zenoh-listen", dest="listen", nargs="*", metavar="ENDPOINT")
    p.add_argument("--zenoh-connect", dest="connect", nargs="*", metavar="ENDPOINT")
    p.add_argument("--zenoh-config", dest="config_file", help="zenoh JSON5 config file")
    p.add_argument("--zenoh-users-file", dest="users_file",
                   help="the robots' zenoh user:password file (mode router): each robot "
                        "publishes under its own name only")
    p.add_argument("--stale-periods", type=float,
                   help="fleet periods without a message before a robot is stale "
                        "(default 3)")
    p.add_argument("--log-level", type=str.lower, choices=LOG_LEVELS)
    p.add_argument("--log-format", type=str.lower, choices=LOG_FORMATS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import logging
    import socket

    from pydantic import ValidationError

    from services.config.fleet import FleetSettings
    from services.config.settings import SettingsError
    from services.fleet.service import FleetService, open_fleet_session
    from services.http.edge.server import listen_socket, server
    from services.http.fleet.app import create_fleet_app
    from services.store.fleet import FleetStore
    from services.store.logs import configure, event

    if args.env_file is not None and not Path(args.env_file).is_file():
        raise SettingsError(f"--env-file {args.env_file}: no such file")
    keys = ("host", "port", "data_dir", "mode", "listen", "connect", "config_file",
            "users_file", "stale_periods", "log_level", "log_format")  # fmt: skip
    overrides = {k: getattr(args, k) for k in keys if getattr(args, k) is not None}
    try:
        s = FleetSettings(_env_file=args.env_file, **overrides)
    except ValidationError as exc:
        first = exc.errors()[0]
        raise SettingsError(f"setting {'.'.join(map(str, first['loc']))}: {first['msg']}") from None
    configure(s.log_level, s.log_format)
    log = logging.getLogger("swpc.fleet")
    sock: socket.socket = listen_socket(s.host, s.port)
    store = FleetStore(s.data_dir / "fleet.sqlite")
    session: Any = None
    fleet = FleetService(store, stale_periods=s.stale_periods)
    try:
        fleet.sweep()  # a store written before today's checks keeps only what they pass
        session = open_fleet_session(s)
        fleet.subscribe(session)
        host, port = sock.getsockname()[:2]
        event(log, logging.INFO, "fleet.listen", host=host, port=port,
              store=str(store.path), robots=len(store.robots()))  # fmt: skip
        server(
            create_fleet_app(fleet), host=s.host, port=s.port, header_timeout=10.0,
            max_connections=128, log_level=s.log_level,
        ).run(sockets=[sock])  # fmt: skip
    finally:
        fleet.close()
        if session is not None:
            session.close()
        store.close()
        sock.close()
    return 0
