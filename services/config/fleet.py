"""The fleet: what a robot's service publishes about itself, and the fleet service's
settings (docs/fleet.md).

Every robot's service (``SWPC_FLEET_PUBLISH=true``) publishes its *state* (a JSON
document, :data:`STATE_FORMAT`) on :func:`state_key` and holds a zenoh liveliness token on
:func:`alive_key` while it runs; ``swpc fleet`` subscribes to both (:data:`STATE_KEYS`,
:data:`ALIVE_KEYS`) through a zenoh router.  The robot and the fleet service share these
names and nothing else.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from services.config.log_options import LogFormat, LogLevel
from swpc_hw.errors import SwpcError

STATE_FORMAT = "swpc-fleet-state/2"
"""The ``format`` of a robot's state document (docs/fleet.md: its fields)."""
STATE_FORMAT_1 = "swpc-fleet-state/1"
"""The format before: the same fields, the fleet period named ``heartbeat_s`` (the word of
the drives' CAN heartbeat); still read, from robots not yet updated and from the store."""
PREFIX = "swpc/fleet"
STATE_KEYS = f"{PREFIX}/*/state"
"""Every robot's state (the fleet service's subscription)."""
ALIVE_KEYS = f"{PREFIX}/*/alive"
"""Every robot's liveliness token."""
ROBOT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$")
"""A robot's name in the fleet: one zenoh key chunk, no wildcard or separator."""
CONSOLE_URL = re.compile(r"(?=.{1,500}\Z)https?://[^\s\x00-\x1f]+", re.DOTALL)
"""Where the lab reaches a robot's console (``SWPC_FLEET_CONSOLE_URL``, the state's
``console_url``): an http or https address of at most 500 characters, no space or control
character; the settings and the fleet service both refuse anything else."""
CONSOLE_URL_RULE = "an http or https address of at most 500 characters"
MAX_FLEET_PERIOD_S = 3600.0
"""The longest fleet period a robot may have (``SWPC_FLEET_PERIOD``; the fleet service
refuses a document that states a longer one)."""
STALE_PERIODS = 3
"""A robot is stale after this many of its fleet periods without a message (unless
``SWPC_FLEET_STALE_PERIODS`` says), or at once when its liveliness token goes."""


def fleet_period(doc: dict[str, Any]) -> Any:
    """The fleet period a state document states (s, as sent: :func:`check_document
    <services.fleet.service.check_document>` checks it): ``fleet_period_s``, or
    ``heartbeat_s`` in a :data:`STATE_FORMAT_1` document."""
    return doc.get("heartbeat_s" if doc.get("format") == STATE_FORMAT_1 else "fleet_period_s")


def fleet_period_field(doc: dict[str, Any]) -> str:
    """The name of the fleet period's field in ``doc``'s format."""
    return "heartbeat_s" if doc.get("format") == STATE_FORMAT_1 else "fleet_period_s"


class FleetNameError(SwpcError, ValueError):
    """A robot name that cannot be a fleet key (names the rule)."""


def check_robot_name(name: str) -> str:
    if not ROBOT_NAME.match(name):
        raise FleetNameError(
            f"fleet robot name {name!r}: 1-63 characters of letters, digits, '_', '.', '-' "
            "starting with a letter or digit (one zenoh key chunk; SWPC_FLEET_ROBOT or the "
            "robot config's robot:)"
        )
    return name


def state_key(robot: str) -> str:
    return f"{PREFIX}/{check_robot_name(robot)}/state"


def alive_key(robot: str) -> str:
    return f"{PREFIX}/{check_robot_name(robot)}/alive"


def robot_of_key(key: str) -> str | None:
    """The robot named by a state or alive key (None: not a fleet key)."""
    parts = key.split("/")
    if len(parts) != 4 or "/".join(parts[:2]) != PREFIX or parts[3] not in ("state", "alive"):
        return None
    return parts[2] if ROBOT_NAME.match(parts[2]) else None


def default_fleet_dir() -> Path:
    """``$XDG_STATE_HOME/swpc-fleet``, else ``~/.local/state/swpc-fleet`` (as the service's
    data dir, :func:`services.config.settings.default_data_dir`)."""
    state = os.environ.get("XDG_STATE_HOME", "")
    base = Path(state) if os.path.isabs(state) else Path.home() / ".local" / "state"
    return base / "swpc-fleet"


def fleet_users(path: Path) -> list[str]:
    """The user names of a zenoh user-password dictionary (``user:password`` lines): the
    robots of the fleet, each a robot name (:class:`FleetNameError` naming the line)."""
    users = []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        user, sep, password = line.partition(":")
        if not sep or not password:
            raise FleetNameError(f"{path}:{n}: not a user:password line")
        try:
            users.append(check_robot_name(user))
        except FleetNameError as exc:
            raise FleetNameError(f"{path}:{n}: {exc}") from None
    if not users:
        raise FleetNameError(f"{path}: no user:password line")
    return users


def fleet_acl(robots: Sequence[str]) -> dict[str, Any]:
    """zenoh access control of the fleet's router (the fleet service in mode router, with
    its user-password dictionary): every authenticated peer may subscribe to the fleet's
    keys and receive them; robot ``X`` (its zenoh user name) may put, delete and hold a
    liveliness token under ``swpc/fleet/X/**`` only; nothing outside the fleet's keys
    flows."""
    keys = [f"{PREFIX}/**", "@/**"]
    listen = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
    write = ["put", "delete", "liveliness_token"]

    def rule(rid: str, flows: list[str], messages: list[str], where: list[str]) -> dict[str, Any]:
        return {"id": rid, "permission": "allow", "flows": flows, "messages": messages,
                "key_exprs": where}  # fmt: skip

    rules = [rule("out", ["egress"], listen + write, keys), rule("in", ["ingress"], listen, keys)]
    subjects: list[dict[str, Any]] = [{"id": "anyone"}]
    policies = [{"rules": ["out", "in"], "subjects": ["anyone"]}]
    for name in robots:
        check_robot_name(name)
        rules.append(rule(f"own-{name}", ["ingress"], write, [f"{PREFIX}/{name}/**"]))
        subjects.append({"id": f"robot-{name}", "usernames": [name]})
        policies.append({"rules": [f"own-{name}"], "subjects": [f"robot-{name}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules,
            "subjects": subjects, "policies": policies}  # fmt: skip


class FleetSettings(BaseSettings):
    """``swpc fleet``'s settings: ``SWPC_FLEET_*`` variables, an env file, its flags."""

    model_config = SettingsConfigDict(env_prefix="SWPC_FLEET_", env_file=None, extra="ignore")

    host: str = Field("127.0.0.1", description="bind address of the fleet page and API")
    port: int = Field(8090, ge=0, le=65535)
    data_dir: Path = Field(
        default_factory=default_fleet_dir,
        description="the fleet store (fleet.sqlite); default $XDG_STATE_HOME/swpc-fleet",
    )
    mode: str = Field(
        "client",
        description="zenoh mode of the fleet's session: client (of the lab's router: the "
        "robots are peers of it, and two peers linked only through a router do not hear "
        "each other) or router (the fleet service is the router the robots connect to)",
    )
    connect: list[str] = Field(
        default_factory=list, description="zenoh endpoints of the router (the robots' too)"
    )
    listen: list[str] = Field(
        default_factory=list, description="zenoh endpoints to listen on (mode router)"
    )
    config_file: str | None = Field(
        None, description="zenoh JSON5 config (deploy/zenoh/fleet-router.json5)"
    )
    users_file: Path | None = Field(
        None,
        description="zenoh user-password dictionary of the robots (user:password lines, "
        "each user a robot's fleet name): with it (mode router) only they connect, and "
        "robot X may publish under swpc/fleet/X/ only (docs/fleet.md)",
    )
    stale_periods: float = Field(
        STALE_PERIODS,
        gt=1,
        le=100,
        description="a robot is stale after this many of its fleet periods without a "
        "message (at once when its liveliness token goes)",
    )
    log_level: LogLevel = "info"
    log_format: LogFormat = "text"
