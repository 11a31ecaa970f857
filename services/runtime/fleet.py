"""This robot in the fleet: its state document, published over zenoh (docs/fleet.md).

:func:`fleet_document` builds the document (:data:`services.config.fleet.STATE_FORMAT`)
from the service's runtime: the file in force (parameters, std devs, created, the run that
made it), the last check (``None`` until the service has checks), the history of its
calibrations (every DONE run of the run store: time, run, installed, parameters and std
devs) and its health.  It is the one place that says what the fleet is told.

:class:`FleetPublisher` puts it on ``swpc/fleet/<robot>/state`` from a thread of its own,
on a zenoh session of its own (``SWPC_FLEET_CONNECT``: the fleet's router, apart from the
sensors' session, which may be guarded or linked to the mocap PC only), and holds the
liveliness token ``swpc/fleet/<robot>/alive`` while it runs:

* on a change, within :data:`POLL_S` host seconds: a run's state changed (the runtime's
  event bus counts them) or the file in force was replaced (its modification time);
* else every ``SWPC_FLEET_PERIOD`` host seconds (the fleet period), the document as it is
  (a repeat).

Nothing here runs on a run's thread or blocks one: the run only counts an event, which the
publisher reads; a failure to build or put is logged and the publisher goes on.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import threading
from typing import Any

from services.config.fleet import STATE_FORMAT, alive_key, check_robot_name, state_key
from services.runs.state import now_iso
from services.runtime.health import service_health
from services.runtime.history import last_check
from services.runtime.runtime import Runtime
from services.store.logs import event
from services.store.provenance import tool_version
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.errors import SwpcError
from swpc_hw.robot.model import PARAM_NAMES
from swpc_hw.sensors.zenoh_session import ZenohAuth, open_session

log = logging.getLogger("swpc.fleet")
POLL_S = 0.5
"""Host seconds between two looks for a change (a run's state, the file in force)."""


def robot_name(rt: Runtime) -> str:
    """This robot's name in the fleet: ``SWPC_FLEET_ROBOT``, else the config's ``robot:``."""
    return check_robot_name(rt.settings.fleet_robot or rt.config.robot)


def _num(x: Any) -> float | None:
    v = None if x is None else float(x)
    return v if v is not None and math.isfinite(v) else None


def _module(m: dict[str, Any]) -> dict[str, Any]:
    """A module's parameters and std devs (None: unknown), as the fleet shows them."""
    std = m.get("stddev")
    return {
        "id": m["id"],
        **{k: _num(m[k]) for k in PARAM_NAMES},
        "stddev": None if not std else {k: _num(std.get(k)) for k in PARAM_NAMES},
    }


def file_in_force(rt: Runtime) -> dict[str, Any] | None:
    """The kinematic file in force: created, the run that made it (None: made by hand or
    by another tool), its modules; ``{"error": ...}`` when it does not load."""
    try:
        doc = rt.kinematics_document()
    except SwpcError as exc:
        return {"error": str(exc)}
    if doc is None:
        return None
    prov = doc.get("provenance")
    return {
        "created": doc.get("created"),
        "run": prov.get("run") if isinstance(prov, dict) else None,
        "modules": [_module(m) for m in doc["modules"]],
    }


def history_summary(rt: Runtime) -> dict[str, Any]:
    """Every calibration of this robot that ended with a result (DONE), oldest first:
    when it finished, the run, whether it was installed, each module's parameters and std
    devs; and every check that ended (DONE): when, its id, its verdict and action."""
    checks = []
    for st in rt.list_runs("check"):
        if st.get("state") != "DONE":
            continue
        got = rt.result(str(st["id"]), "check")
        found = {} if got is None or got[1] is None else got[1]
        checks.append({
            "time": st.get("finished") or st.get("created"),
            "check": st["id"],
            "verdict": st.get("verdict") or found.get("verdict"),
            "action": found.get("action"),
        })  # fmt: skip
    out = []
    for st in rt.list_runs("calibration"):
        if st.get("state") != "DONE":
            continue
        got = rt.result(str(st["id"]))
        doc = None if got is None else got[1]
        if not doc or "modules" not in doc:
            continue
        out.append(
            {
                "time": st.get("finished") or st.get("created"),
                "run": st["id"],
                "installed": bool(st.get("installed")),
                "metrology": st.get("metrology", "mocap"),
                "modules": [_module(m) for m in doc["modules"]],
            }
        )
    return {"calibrations": out, "checks": checks}


def fleet_document(rt: Runtime, period: float | None = None) -> dict[str, Any]:
    """This robot's state document (module docstring; docs/fleet.md lists the fields).
    ``last_check``: :func:`services.runtime.history.last_check` (None before the first)."""
    status, health = service_health(rt)
    return {
        "format": STATE_FORMAT,
        "robot": robot_name(rt),
        "version": tool_version(),
        "time": now_iso(),
        "fleet_period_s": rt.settings.fleet_period if period is None else period,
        "console_url": rt.settings.fleet_console_url,
        "file_in_force": file_in_force(rt),
        "last_check": last_check(rt),
        "history": history_summary(rt),
        "health": {
            "status": status,
            "problems": list(health["problems"]),
            "running": bool(health["running"]),
        },
    }


class FleetPublisher:
    """Publishes :func:`fleet_document` (module docstring); :meth:`close` is idempotent."""

    def __init__(self, rt: Runtime, session: Any, *, clock: Clock = SYSTEM_CLOCK) -> None:
        self.rt = rt
        self.session = session
        self.clock = clock
        self.robot = robot_name(rt)
        self.key = state_key(self.robot)
        self.period = float(rt.settings.fleet_period)
        self.published = 0
        self.failures = 0
        self._token: Any = None
        self._seen: tuple[int, int] | None = None
        self._last = -float("inf")
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @classmethod
    def open(cls, rt: Runtime) -> FleetPublisher:
        """The publisher of ``rt``'s settings, on a session of its own, started."""
        s = rt.settings
        auth = None
        if s.fleet_password is not None:
            user = s.fleet_user or robot_name(rt)
            auth = ZenohAuth(user, s.fleet_password.get_secret_value())
        session = open_session(
            mode=s.fleet_mode, connect=s.fleet_connect, config_file=s.fleet_config_file,
            auth=auth,
        )  # fmt: skip
        try:
            pub = cls(rt, session)
        except BaseException:
            session.close()
            raise
        return pub.start()

    def start(self) -> FleetPublisher:
        self._token = self.session.liveliness().declare_token(alive_key(self.robot))
        self._thread = threading.Thread(target=self._loop, name="swpc-fleet", daemon=True)
        self._thread.start()
        event(log, logging.INFO, "fleet.publish", key=self.key, period=self.period)
        return self

    def _fingerprint(self) -> tuple[int, int]:
        """What changes when the state does: the runs' events, the file in force."""
        try:
            mtime = os.stat(self.rt.settings.kinematics_file).st_mtime_ns
        except OSError:
            mtime = 0
        return self.rt.events.published, mtime

    def due(self) -> bool:
        """A change since the last publication, or a fleet period gone (a repeat)."""
        return self._fingerprint() != self._seen or (
            self.clock.now() - self._last >= self.period
        )

    def publish(self) -> dict[str, Any]:
        """Build the document and put it now; returns it."""
        seen = self._fingerprint()
        doc = fleet_document(self.rt, self.period)
        self.session.put(self.key, json.dumps(doc, allow_nan=False))
        self._seen, self._last = seen, self.clock.now()
        self.published += 1
        return doc

    def _loop(self) -> None:
        while not self._stop.is_set():
            if self.due():
                try:
                    self.publish()
                except Exception as exc:  # the fleet never takes the service down
                    self.failures += 1
                    self._last = self.clock.now()  # retried at the next repeat
                    event(log, logging.WARNING, "fleet.publish_failed", error=str(exc))
            self._stop.wait(min(POLL_S, self.period))

    def close(self) -> None:
        """Stop publishing, withdraw the token, close the session (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        token, self._token = self._token, None
        if token is not None:
            with contextlib.suppress(Exception):
                token.undeclare()
        with contextlib.suppress(Exception):
            self.session.close()
