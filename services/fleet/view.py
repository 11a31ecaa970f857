"""What the fleet view shows of a robot, as pure functions of its stored documents and
the time: its status (live or stale) and the drift of its parameters.

* Status: ``stale`` when its liveliness token went (the robot's zenoh session closed or
  its process died: at once) or when no message came for ``stale_periods`` of its own
  fleet periods (a service that hangs with its session open); else ``live``.
* Drift: each module's parameters across the robot's calibrations (merged by run from
  every document kept, so a calibration is never lost when a robot's history is cut or
  its store replaced), first and last, the change, and the change per week.
"""

from __future__ import annotations

import datetime as _dt
import math
from collections.abc import Sequence
from typing import Any

from services.config.fleet import fleet_period
from swpc_hw.calibration.check.trend import MIN_SPAN
from swpc_hw.robot.frames import FRAME_FREE, frame_of_metrology
from swpc_hw.robot.model import PARAM_NAMES

WEEK_S = 7 * 86400.0


def iso(t: float) -> str:
    """Epoch seconds as ISO 8601 UTC to the second."""
    return (
        _dt.datetime.fromtimestamp(t, _dt.UTC).isoformat(timespec="seconds").replace("+00:00", "Z")
    )


def epoch(text: str) -> float | None:
    """An ISO 8601 time as epoch seconds (None: not one)."""
    try:
        t = _dt.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except (ValueError, AttributeError):
        return None
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.UTC)
    return t.timestamp()


def status(
    last_seen: float, alive: bool | None, period: float, now: float, stale_periods: float
) -> tuple[str, str | None]:
    """``(live | stale, why stale)``; ``alive``: its liveliness token (None: unknown)."""
    age = now - last_seen
    if alive is False:
        return "stale", "its liveliness token went (session closed or process ended)"
    if age > stale_periods * period:
        return "stale", (
            f"no message for {age:.0f} s ({stale_periods:g} fleet periods of {period:g} s)"
        )
    return "live", None


def calibrations(docs: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Every calibration named in ``docs``' histories, one per run, oldest first."""
    by_run: dict[str, dict[str, Any]] = {}
    for d in docs:
        for c in (d.get("history") or {}).get("calibrations") or []:
            by_run[str(c["run"])] = c
    return sorted(by_run.values(), key=lambda c: (epoch(str(c.get("time"))) or 0.0, c["run"]))


def frame_of(c: dict[str, Any]) -> str:
    """A published calibration's frame (by its metrology)."""
    return frame_of_metrology(c.get("metrology"))


def drift(cals: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per module and parameter: the series (time, run, value, std dev) over ``cals``,
    first, last, change (last - first) and change per week (None over less than
    :data:`~swpc_hw.calibration.check.trend.MIN_SPAN`: a day).
    Positions and ``beta`` over the calibrations in the newest one's frame only (``frame``):
    a change between frames is the frames' turn and offset, not the robot's drift."""
    series: dict[tuple[int, str], list[dict[str, Any]]] = {}
    newest = frame_of(cals[-1]) if cals else "R"
    for c in cals:
        t = epoch(str(c.get("time")))
        for m in c["modules"]:
            std = m.get("stddev") or {}
            for k in PARAM_NAMES:
                if k not in FRAME_FREE and frame_of(c) != newest:
                    continue
                v = m.get(k)
                if v is None or not math.isfinite(float(v)):
                    continue
                series.setdefault((int(m["id"]), k), []).append(
                    {
                        "time": c.get("time"),
                        "t": t,
                        "run": c["run"],
                        "value": float(v),
                        "stddev": std.get(k),
                    }
                )
    out = []
    order = sorted(series, key=lambda mk: (mk[0], PARAM_NAMES.index(mk[1])))
    for module, param in order:
        pts = series[(module, param)]
        first, last = pts[0], pts[-1]
        span = None if first["t"] is None or last["t"] is None else last["t"] - first["t"]
        change = last["value"] - first["value"]
        out.append(
            {
                "module": module,
                "param": param,
                "first": first["value"],
                "last": last["value"],
                "change": change,
                "per_week": change / span * WEEK_S if span and span >= MIN_SPAN else None,
                "frame": "any" if param in FRAME_FREE else newest,
                "points": [{k: p[k] for k in ("time", "run", "value", "stddev")} for p in pts],
            }
        )
    return out


def summary(
    robot: str,
    last: dict[str, Any],
    cals: int,
    dr: Sequence[dict[str, Any]],
    documents: int,
    *,
    first_seen: float,
    last_seen: float,
    alive: bool | None,
    now: float,
    stale_periods: float,
    points: bool = False,
) -> dict[str, Any]:
    """One robot in the fleet view (``points``: with each parameter's series): ``last``
    its newest document, ``cals`` how many :func:`calibrations` all of them name, ``dr``
    their :func:`drift`, ``documents`` how many are kept."""
    st, why = status(last_seen, alive, float(fleet_period(last)), now, stale_periods)
    fif = last.get("file_in_force") or {}
    check = last.get("last_check")
    if not points:
        dr = [{k: v for k, v in p.items() if k != "points"} for p in dr]
    return {
        "robot": robot,
        "status": st,
        "stale_reason": why,
        "alive": alive,
        "last_seen": iso(last_seen),
        "age_s": max(0.0, now - last_seen),
        "first_seen": iso(first_seen),
        "version": last.get("version"),
        "console_url": last.get("console_url"),
        "fleet_period_s": fleet_period(last),
        "file_in_force": None
        if not fif
        else {"created": fif.get("created"), "run": fif.get("run"), "error": fif.get("error")},
        "last_check": check,
        "health": last.get("health"),
        "calibrations": cals,
        "documents": documents,
        "drift": dr,
    }
