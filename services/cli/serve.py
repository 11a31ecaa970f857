"""``swpc serve``: run the calibration service (FastAPI on uvicorn).

With no CAN settings (``SWPC_CAN_INTERFACE`` unset) it runs on the in-process simulator:
the virtual robot in the service's process on a virtual bus, zenoh on loopback, in
simulated time.  Settings come from
``SWPC_*`` environment variables, an env file (``--env-file``) and the flags below.
"""

from __future__ import annotations

import argparse
from typing import Any


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
    p.add_argument("--log-level", default="info")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from services.api import create_app
    from services.settings import ServiceSettings

    overrides: dict[str, Any] = {}
    for key in ("host", "port", "data_dir", "time_scale", "sim_speed"):
        value = getattr(args, key)
        if value is not None:
            overrides[key] = value
    settings = ServiceSettings(_env_file=args.env_file, **overrides)
    fresh = settings.token is None
    token = settings.ensure_token()
    if fresh:
        print(f"swpc serve: no SWPC_TOKEN set; generated bearer token: {token}", flush=True)
    app = create_app(settings)
    uvicorn.run(app, host=settings.host, port=settings.port, log_level=args.log_level)
    return 0
