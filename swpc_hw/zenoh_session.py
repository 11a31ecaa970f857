"""Zenoh session configuration shared by the simulator and the service.

Always explicit: peer (or client) mode, multicast scouting off, gossip off, explicit
``listen`` / ``connect`` endpoints (loopback ``tcp/127.0.0.1:<port>`` in tests and for the
in-process simulator).  Nothing here ever touches a multicast or non-loopback address by
itself: the endpoints are exactly the ones configured.
"""

from __future__ import annotations

import json
import re
import socket
from collections.abc import Sequence
from typing import Any

from swpc_hw.errors import SwpcError


class ZenohSessionError(SwpcError):
    """A zenoh session cannot be opened (an endpoint in use or malformed, a bad config
    file); the message names the endpoints and zenoh's reason."""


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/<host>:<port>`` endpoint on a currently free loopback port."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        port = s.getsockname()[1]
    return f"tcp/{host}:{port}"


def zenoh_config(
    *,
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | None = None,
) -> Any:
    """A ``zenoh.Config`` with multicast scouting off and explicit endpoints.

    ``config_file`` (JSON5, e.g. ``deploy/zenoh/robot-peer.json5``) is loaded first; the
    explicit arguments then override ``mode`` and add endpoints.
    """
    import zenoh

    cfg = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    if listen or not config_file:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect or not config_file:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return cfg


def open_session(
    *,
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | None = None,
) -> Any:
    """Open a zenoh session with :func:`zenoh_config`; :class:`ZenohSessionError` when
    it cannot be opened."""
    import zenoh

    try:
        return zenoh.open(
            zenoh_config(mode=mode, listen=listen, connect=connect, config_file=config_file)
        )
    except zenoh.ZError as exc:
        # zenoh's messages end with the Rust source file and line of each cause: not ours
        reason = re.sub(r" at \S+\.rs:\d+\.?", "", str(exc)).strip(" .")
        where = [f"{k}={list(v)}" for k, v in (("listen", listen), ("connect", connect)) if v]
        if config_file:
            where.append(f"config {config_file}")
        raise ZenohSessionError(
            f"cannot open the zenoh session ({', '.join(where) or 'no endpoints'}): {reason}"
        ) from exc
