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
    CONSOLE_URL,
    CONSOLE_URL_RULE,
    MAX_FLEET_PERIOD_S,
    STATE_FORMAT,
    STATE_FORMAT_1,
    STATE_KEYS,
    FleetSettings,
    fleet_acl,
    fleet_period,
    fleet_period_field,
    fleet_users,
    robot_of_key,
)
from services.fleet.view import calibrations, drift, summary
from services.store.fleet import FleetStore, RobotRow
from services.store.logs import event
from swpc_hw.clock import SYSTEM_CLOCK, Clock
from swpc_hw.files.kinematic_file import BOUNDS
from swpc_hw.robot.model import PARAM_NAMES

log = logging.getLogger("swpc.fleet")
MAX_DOCUMENT_BYTES = 1 << 20
"""A state document larger than this is refused (a robot's years of calibrations fit:
a calibration is about 1.5 kB of it)."""
MAX_DEPTH = 12
"""Nesting of a state document's objects and lists (the format's deepest is 6)."""
MAX_MAGNITUDE = 1e12
"""Any number of a state document: finite and within +-this (a time stamp in epoch
seconds fits; 1e400 is infinity in JSON and never a robot's)."""
MAX_REFUSING_KEYS = 1024
"""Keys remembered as refusing (each logged once); beyond, refusals are only counted."""


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
            v = m.get(k)
            _number(v, f"{where}[{i}].{k}")
            lo, hi = BOUNDS[k]
            if v is not None and not lo <= v <= hi:
                raise DocumentError(f"{where}[{i}].{k}: {v!r} outside the plausible [{lo}, {hi}]")
        std = m.get("stddev")
        if std is not None:
            if not isinstance(std, dict):
                raise DocumentError(f"{where}[{i}].stddev: not a mapping")
            for k in PARAM_NAMES:
                _number(std.get(k), f"{where}[{i}].stddev.{k}")


def _shape(doc: Any) -> None:
    """Every value of ``doc`` (iteratively: a deep one cannot exhaust the stack): nested
    at most :data:`MAX_DEPTH` deep, every number finite and within :data:`MAX_MAGNITUDE`."""
    todo: list[tuple[Any, int, str]] = [(doc, 1, "")]
    while todo:
        v, depth, where = todo.pop()
        if isinstance(v, dict | list):
            if depth > MAX_DEPTH:
                raise DocumentError(f"nested more than {MAX_DEPTH} deep (at {where or '/'})")
            items = v.items() if isinstance(v, dict) else enumerate(v)
            todo.extend((x, depth + 1, f"{where}/{k}") for k, x in items)
        elif (
            isinstance(v, float | int)
            and not isinstance(v, bool)
            and not (math.isfinite(v) and abs(v) <= MAX_MAGNITUDE)
        ):
            raise DocumentError(f"{where}: {v!r} is not a finite number within "
                                f"{MAX_MAGNITUDE:g}")  # fmt: skip


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
    except RecursionError:
        raise DocumentError(f"nested more than {MAX_DEPTH} deep") from None
    if not isinstance(doc, dict):
        raise DocumentError("not a JSON object")
    _shape(doc)
    if doc.get("format") not in (STATE_FORMAT, STATE_FORMAT_1):
        raise DocumentError(f"format {doc.get('format')!r}, expected {STATE_FORMAT!r}")
    if doc.get("robot") != robot:
        raise DocumentError(f"robot {doc.get('robot')!r} published on {robot!r}'s key")
    period = fleet_period(doc)
    if not (isinstance(period, int | float) and 0 < period <= MAX_FLEET_PERIOD_S):
        raise DocumentError(
            f"{fleet_period_field(doc)} {period!r}: a number of seconds in (0, "
            f"{MAX_FLEET_PERIOD_S:g}] is needed"
        )
    url = doc.get("console_url")
    if url is not None and not (isinstance(url, str) and CONSOLE_URL.fullmatch(url)):
        raise DocumentError(f"console_url: {CONSOLE_URL_RULE} is needed")
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


_ViewInputs = tuple[int, dict[str, Any], int, list[dict[str, Any]], int]
"""A robot's view, read once per new document (:meth:`FleetService._view_inputs`)."""


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
        self._refusing: set[str] = set()  # keys whose last document was refused
        self._views: dict[str, _ViewInputs] = {}
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
                # logged once until the key is right again (counted always)
                if key not in self._refusing and len(self._refusing) < MAX_REFUSING_KEYS:
                    self._refusing.add(key)
                    event(log, logging.WARNING, "fleet.rejected", key=key[:200],
                          error=str(exc)[:500])  # fmt: skip
                return False
            self._refusing.discard(key)
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
        """Every robot ever heard, by name, as the fleet view shows it now.  A robot whose
        documents cannot be shown (a store written by an older service, say) is listed
        with the reason, never breaking the list."""
        out = []
        seqs = self.store.last_seq()
        for row in self.store.robots():
            try:
                got = self._view(row, seqs.get(row.robot), points=False)
            except Exception as exc:  # one robot's view, not everyone's
                log.warning("fleet: robot %s cannot be shown: %r", row.robot, exc)
                got = {"robot": row.robot, "status": "unknown", "error": repr(exc)[:300]}
            if got is not None:
                out.append(got)
        return out

    def robot(self, name: str, points: bool = True) -> dict[str, Any] | None:
        """One robot (``points``: each parameter's series); None: never heard."""
        row = self.store.robot(name)
        if row is None:
            return None
        return self._view(row, self.store.last_seq().get(name), points)

    def _view(self, row: RobotRow, seq: int | None, points: bool) -> dict[str, Any] | None:
        seen = None if seq is None else self._view_inputs(row.robot, seq)
        if seen is None:
            return None
        _, last, cals, dr, n = seen
        with self._lock:
            alive = self.alive.get(row.robot)
        out = summary(
            row.robot,
            last,
            cals,
            dr,
            n,
            first_seen=row.first_seen,
            last_seen=row.last_seen,
            alive=alive,
            now=self.clock.wall(),
            stale_periods=self.stale_periods,
            points=points,
        )
        if points:
            out["state"] = last
        return out

    def _view_inputs(
        self, name: str, seq: int
    ) -> _ViewInputs | None:
        """``(newest seq, newest document, calibrations, drift, documents)`` of ``name`` whose
        newest document is ``seq``, read from the store once per new document (``GET
        /robots`` would otherwise parse every robot's every document at each request)."""
        with self._lock:
            hit = self._views.get(name)
        if hit is not None and hit[0] == seq:
            return hit
        docs = [d.doc for d in self.store.documents(name)]
        if not docs:
            return None
        cals = calibrations(docs)
        got = (seq, docs[-1], len(cals), drift(cals), len(docs))
        with self._lock:
            self._views[name] = got
        return got

    def sweep(self) -> int:
        """Forget the stored documents today's checks refuse (a store written before them);
        returns how many.  Run once when the service opens its store."""
        bad = []
        for row in self.store.robots():
            for d in self.store.documents(row.robot):
                try:
                    check_document(row.robot, json.dumps(d.doc).encode())
                except (DocumentError, RecursionError, ValueError):
                    bad.append(d.seq)
        if bad:
            self.store.delete(bad)
            event(log, logging.WARNING, "fleet.swept", documents=len(bad))
        return len(bad)

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


def open_fleet_session(s: FleetSettings) -> Any:
    """The fleet service's zenoh session of settings ``s``: with ``users_file`` (mode
    router or peer: a listener) only its users connect and each robot publishes under its
    own key only (:func:`~services.config.fleet.fleet_acl`)."""
    from swpc_hw.sensors.zenoh_session import ZenohAuth, open_session

    auth = acl = None
    if s.users_file is not None:
        if s.mode == "client":
            raise DocumentError(
                "SWPC_FLEET_USERS_FILE: the robots' credentials are checked where they "
                "connect: the fleet service in mode router (--zenoh-mode router)"
            )
        auth = ZenohAuth(users_file=str(s.users_file))
        acl = fleet_acl(fleet_users(s.users_file))
    return open_session(
        mode=s.mode, listen=s.listen, connect=s.connect, config_file=s.config_file,
        auth=auth, acl=acl,
    )  # fmt: skip
