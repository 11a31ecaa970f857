"""Zenoh session configuration shared by the simulator and the service.

Always explicit: peer (or client) mode, multicast scouting off, gossip off, explicit
``listen`` / ``connect`` endpoints (loopback ``tcp/127.0.0.1:<port>`` in tests and for the
in-process simulator).  Nothing here ever touches a multicast or non-loopback address by
itself: the endpoints are exactly the ones configured.

Who may talk to a session is zenoh's own business, configured here too:

* :class:`ZenohAuth`, zenoh's user-password authentication: a session with a
  ``users_file`` (``user:password`` lines) accepts links only from peers that present one
  of them; a session with ``user`` / ``password`` presents them when it connects;
* :func:`publishers_acl`, zenoh's access control: only the named (authenticated) users may
  put on the given keys of this session; everything else flows as before.
"""

from __future__ import annotations

import json
import re
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from swpc_hw.errors import SwpcError


class ZenohSessionError(SwpcError):
    """A zenoh session cannot be opened (an endpoint in use or malformed, a bad config
    file); the message names the endpoints and zenoh's reason."""


@dataclass(frozen=True)
class ZenohAuth:
    """zenoh's user-password authentication (module docstring)."""

    user: str | None = None
    password: str | None = None
    users_file: str | None = None
    """Peers allowed to connect: a file of ``user:password`` lines (zenoh's dictionary)."""


def _rule(rid: str, flows: list[str], messages: list[str], keys: list[str]) -> dict[str, Any]:
    return {"id": rid, "permission": "allow", "flows": flows, "messages": messages,
            "key_exprs": keys}  # fmt: skip


def publishers_acl(keys: Sequence[str], users: Sequence[str]) -> dict[str, Any]:
    """zenoh access control of a session: only ``users`` (authenticated usernames) may put
    on ``keys``; every other message, and the session's own, flow as before."""
    everything = ["put", "delete", "declare_subscriber", "query", "reply",
                  "declare_queryable", "liveliness_token", "declare_liveliness_subscriber",
                  "liveliness_query"]  # fmt: skip
    control = [m for m in everything if m not in ("put", "delete")]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            _rule("out", ["egress"], everything, ["**", "@/**"]),
            _rule("in", ["ingress"], control, ["**", "@/**"]),
            _rule("publishers", ["ingress"], ["put", "delete"], list(keys)),
        ],
        "subjects": [{"id": "anyone"}, {"id": "publishers", "usernames": list(users)}],
        "policies": [
            {"rules": ["out", "in"], "subjects": ["anyone"]},
            {"rules": ["publishers"], "subjects": ["publishers"]},
        ],
    }


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
    auth: ZenohAuth | None = None,
    acl: dict[str, Any] | None = None,
) -> Any:
    """A ``zenoh.Config`` with scouting off (and no wait for it) and explicit endpoints.

    ``config_file`` (JSON5, e.g. ``deploy/zenoh/robot-peer.json5``) is loaded first; the
    explicit arguments then override ``mode``, add endpoints, the authentication and the
    access control.
    """
    import zenoh

    cfg = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    # open() waits scouting/delay (500 ms) for what scouting finds; with scouting off there
    # is nothing to find, and the connect endpoints are linked before open() returns anyway
    cfg.insert_json5("scouting/delay", "0")
    if listen or not config_file:
        cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect or not config_file:
        cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if auth is not None:
        for key, value in (
            ("user", auth.user),
            ("password", auth.password),
            ("dictionary_file", auth.users_file),
        ):
            if value is not None:
                cfg.insert_json5(f"transport/auth/usrpwd/{key}", json.dumps(value))
    if acl is not None:
        cfg.insert_json5("access_control", json.dumps(acl))
    return cfg


def connect_endpoints(connect: Sequence[str], config_file: str | None = None) -> list[str]:
    """The endpoints a session opened with these arguments connects to: ``connect``, else
    those of its config file (as :func:`zenoh_config` merges them)."""
    if connect or not config_file:
        return list(connect)
    import zenoh

    try:
        found = json.loads(zenoh.Config.from_file(config_file).get_json("connect/endpoints"))
    except Exception:  # a file zenoh_config() refuses is refused there, with its reason
        return []
    return [str(e) for e in found] if isinstance(found, list) else []


def linked_sessions(session: Any) -> int:
    """How many zenoh sessions (peers and routers) ``session`` has a link with now."""
    info = session.info
    return len(list(info.peers_zid())) + len(list(info.routers_zid()))


def open_session(
    *,
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    config_file: str | None = None,
    auth: ZenohAuth | None = None,
    acl: dict[str, Any] | None = None,
) -> Any:
    """Open a zenoh session with :func:`zenoh_config`; :class:`ZenohSessionError` when
    it cannot be opened."""
    import zenoh

    try:
        return zenoh.open(
            zenoh_config(
                mode=mode,
                listen=listen,
                connect=connect,
                config_file=config_file,
                auth=auth,
                acl=acl,
            )
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
