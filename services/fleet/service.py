"""``swpc fleet``'s core: the robots' state documents from zenoh into the fleet store.

:class:`FleetService` subscribes to every robot's state (``swpc/fleet/*/state``) and
liveliness token (``swpc/fleet/*/alive``, with zenoh's history: the tokens already there
when it starts are reported too).  Each state document is checked
(:func:`check_document`); a malformed one is logged, counted and skipped, never kept,
and never stops the service.  Time is the injected clock's wall time (epoch seconds): when
a document was received, and the ``now`` the status is judged at (:mod:`.view`).

Liveliness is not kept in the store: after a restart a robot's token is unknown (None)
until zenoh reports it, and its status is judged by its fleet period alone until then.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import threading
from typing import Any

from services.config.fleet import (
    ALIVE_KEYS,
    STATE_FORMAT,
    STATE_FORMAT_1,
    STATE_KEYS,
    fleet_period,
    fleet_period_field,
    robot_of_key,
)
from services.fleet.view import summary
from services.store.fleet import FleetStore
from services.store.logs import event
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.robot.model import PARAM_NAMES

log = logging.getLogger("swpc.fleet")
MAX_DOCUMENT_BYTES = 4 << 20
"""A state document larger than this is refused (a robot's years of calibrations fit)."""


class DocumentError(ValueError):
    """A state document that is not one (names what is wrong)."""


def _number(x: Any, where: str) -> None:
    if x is not None and not (isinstance(x, int | float) and math.isfinite(x)):
        raise DocumentError(f"{where}: {x!r} is not a finite number")


def _modules(mods: Any, where: str) -> None:
    if not isinstance(mods, list):
        raise DocumentError(f"{where}: not a list of modules")
    for i, m in enumerate(mods):
        if not isinstance(m, dict) or not isinstance(m.get("id"), int):
            raise DocumentError(f"{where}[{i}]: a module needs an integer id")
        for k in PARAM_NAMES:
            _number(m.get(k), f"{where}[{i}].{k}")
        std = m.get("stddev")
        if std is not None:
            if not isinstance(std, dict):
                raise DocumentError(f"{where}[{i}].stddev: not a mapping")
            for k in PARAM_NAMES:
                _number(std.get(k), f"{where}[{i}].stddev.{k}")


def check_document(robot: str, payload: bytes) -> dict[str, Any]:
    """The state document of ``robot`` in ``payload``; :class:`DocumentError` saying what
    is wrong (not JSON, another format, another robot's name, a bad fleet period, a
    calibration without run or modules, a parameter that is not a finite number)."""
    if len(payload) > MAX_DOCUMENT_BYTES:
        raise DocumentError(f"{len(payload)} bytes, more than {MAX_DOCUMENT_BYTES}")
    try:
        doc = json.loads(payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise DocumentError(f"not JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise DocumentError("not a JSON object")
    if doc.get("format") not in (STATE_FORMAT, STATE_FORMAT_1):
        raise DocumentError(f"format {doc.get('format')!r}, expected {STATE_FORMAT!r}")
    if doc.get("robot") != robot:
        raise DocumentError(f"robot {doc.get('robot')!r} published on {robot!r}'s key")
    period = fleet_period(doc)
    if not (isinstance(period, int | float) and math.isfinite(period) and period > 0):
        raise DocumentError(
            f"{fleet_period_field(doc)} {period!r}: a positive number of seconds is needed"
        )
    fif = doc.get("file_in_force")
    if fif is not None:
        if not isinstance(fif, dict):
            raise DocumentError("file_in_force: not a mapping")
        if "error" not in fif:
            _modules(fif.get("modules"), "file_in_force.modules")
    check = doc.get("last_check")
    if check is not None and not isinstance(check, dict):
        raise DocumentError("last_check: not a mapping")
    hist = doc.get("history")
    if not isinstance(hist, dict) or not isinstance(hist.get("calibrations"), list):
        raise DocumentError("history.calibrations: not a list")
    for i, c in enumerate(hist["calibrations"]):
        if not isinstance(c, dict) or not isinstance(c.get("run"), str):
            raise DocumentError(f"history.calibrations[{i}]: a calibration needs its run id")
        _modules(c.get("modules"), f"history.calibrations[{i}].modules")
    return doc


class FleetService:
    """Every robot's documents from zenoh (or :meth:`receive`) into ``store``."""

    def __init__(
        self, store: FleetStore, *, clock: Clock = SYSTEM_CLOCK, stale_periods: float = 3.0
    ) -> None:
        self.store = store
        self.clock = clock
        self.stale_periods = float(stale_periods)
        self.alive: dict[str, bool] = {}
        self.received = 0
        self.rejected = 0
        self.last_rejection: str | None = None
        self._lock = threading.Lock()
        self._subs: list[Any] = []

    # ---------------------------------------------------------------- input
    def receive(self, key: str, payload: bytes) -> bool:
        """One state message; returns whether it was accepted (a malformed one is logged
        and counted)."""
        robot = robot_of_key(key)
        with self._lock:
            self.received += 1
            try:
                if robot is None:
                    raise DocumentError(f"key {key!r} is not swpc/fleet/<robot>/state")
                doc = check_document(robot, payload)
            except DocumentError as exc:
                self.rejected += 1
                self.last_rejection = f"{key}: {exc}"
                event(log, logging.WARNING, "fleet.rejected", key=key, error=str(exc))
                return False
            self.store.record(robot, self.clock.wall(), doc)
            return True

    def liveliness(self, key: str, alive: bool) -> None:
        robot = robot_of_key(key)
        if robot is None:
            return
        with self._lock:
            self.alive[robot] = alive
        event(log, logging.INFO, "fleet.alive" if alive else "fleet.gone", robot=robot)

    def subscribe(self, session: Any) -> None:
        """Subscribe to every robot's state and liveliness on ``session``."""
        import zenoh

        def on_state(sample: Any) -> None:
            self.receive(str(sample.key_expr), sample.payload.to_bytes())

        def on_alive(sample: Any) -> None:
            self.liveliness(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        self._subs.append(session.declare_subscriber(STATE_KEYS, on_state))
        self._subs.append(
            session.liveliness().declare_subscriber(ALIVE_KEYS, on_alive, history=True)
        )

    def close(self) -> None:
        """Undeclare the subscribers (idempotent; the session is the caller's)."""
        subs, self._subs = self._subs, []
        for s in subs:
            with contextlib.suppress(Exception):
                s.undeclare()

    # ---------------------------------------------------------------- the view
    def robots(self) -> list[dict[str, Any]]:
        """Every robot ever heard, by name, as the fleet view shows it now."""
        out = []
        for row in self.store.robots():
            got = self.robot(row.robot, points=False)
            if got is not None:
                out.append(got)
        return out

    def robot(self, name: str, points: bool = True) -> dict[str, Any] | None:
        """One robot (``points``: each parameter's series); None: never heard."""
        row = self.store.robot(name)
        if row is None:
            return None
        docs = [d.doc for d in self.store.documents(name)]
        if not docs:
            return None
        with self._lock:
            alive = self.alive.get(name)
        out = summary(
            name,
            docs,
            first_seen=row.first_seen,
            last_seen=row.last_seen,
            alive=alive,
            now=self.clock.wall(),
            stale_periods=self.stale_periods,
            points=points,
        )
        if points:
            out["state"] = docs[-1]
        return out

    def counts(self) -> dict[str, Any]:
        rows = self.store.robots()
        view = self.robots()
        return {
            "robots": len(rows),
            "live": sum(1 for r in view if r["status"] == "live"),
            "stale": sum(1 for r in view if r["status"] == "stale"),
            "documents": sum(r.documents for r in rows),
            "received": self.received,
            "rejected": self.rejected,
            "last_rejection": self.last_rejection,
        }
