"""A robot's history: every calibration and check with its time, per parameter a time
series with std devs and its trend (``GET /history``, the console's Drift view; the
fleet view reads :func:`history_document` and :func:`last_check`).

The points are the run store's finished runs (:meth:`services.store.runs.RunStore.finished`,
and this service's runs in memory over them): a DONE calibration's estimate (installed or
not: it measured the robot all the same) and a DONE check's, each at the time it finished,
with its std devs.  Per module and parameter the trend is the weighted line of
:func:`swpc_hw.calibration.check.trend.linear_trend` and the date it leaves
``reference +- tolerance``: the reference is the file in force's value (none in force: the
newest calibration's), the tolerance the robot config's (``tolerances``: position for
``x_s``, ``y_s``, ``b``; ``beta``; ``radius`` for ``r``; the largest std dev a calibration
may have, here the largest change the file may be off by).  ``x_s``, ``y_s`` and ``beta``
depend on the frame of the parameters (a calibration without motion capture is in its
design-fit frame): a point of another frame than the reference's is re-expressed in it when
it can be (a motion-capture point, frame R, in design-fit: :func:`in_reference_frame`), else
neither drawn nor in the trend (``value`` null, ``other_frame`` true: a design-fit point
has no frame R); ``b`` and ``r`` do not depend on it.  A check without motion capture
(frame ``file-fit``: fitted to the file it checked, its scales the file's) is shown but
enters no trend: it measures changes of the robot's shape, not values.

Values are in display units (mm, deg; slopes per week): :data:`swpc_hw.calibration.report.DISPLAY`.
"""

from __future__ import annotations

import datetime as _dt
import math
import time
from dataclasses import dataclass
from typing import Any

from services.config.robot import TOLERANCE_OF, RobotConfig
from services.runtime.errors import NoFileError
from services.runtime.runtime import Runtime
from swpc_hw.calibration.check.trend import linear_trend
from swpc_hw.calibration.report import DISPLAY
from swpc_hw.robot.frames import (
    DESIGN_FIT,
    FILE_FIT,
    FRAME_FREE,
    frame_of_metrology,
    params_in_design_fit,
)
from swpc_hw.robot.model import PARAM_NAMES, ModuleParams, ModuleStddev, RobotParams

WEEK = 7 * 86400.0


def epoch(iso: str) -> float:
    """An ISO 8601 UTC time (``...Z``) in Unix seconds."""
    return _dt.datetime.fromisoformat(iso.replace("Z", "+00:00")).timestamp()


def iso(t: float) -> str:
    return (
        _dt.datetime.fromtimestamp(t, _dt.UTC).isoformat(timespec="seconds").replace("+00:00", "Z")
    )


@dataclass(frozen=True)
class Point:
    """One run's measurement of one robot: every module's parameters and std devs (SI)."""

    run: str
    kind: str
    time: str
    frame: str
    installed: bool | None
    verdict: str | None
    modules: dict[int, dict[str, tuple[float, float]]]
    """module id -> parameter -> (value, std dev)."""


def point_of(status: dict[str, Any], doc: dict[str, Any]) -> Point | None:
    """A finished run's point: a calibration's result (``modules``) or a check's
    (``estimate``); None when the document holds no estimate or no time."""
    kind = str(status.get("kind") or "calibration")
    when = status.get("finished") or status.get("created")
    rows = doc.get("estimate") if kind == "check" else doc.get("modules")
    if not when or not isinstance(rows, list):
        return None
    quality = doc.get("quality")
    mode = quality.get("mode") if isinstance(quality, dict) else None
    frame = str(doc.get("frame") or frame_of_metrology(mode))
    modules: dict[int, dict[str, tuple[float, float]]] = {}
    for m in rows:
        sd = m.get("stddev") or {}
        modules[int(m["id"])] = {
            k: (float(m[k]), float(sd[k]) if sd.get(k) is not None else float("nan"))
            for k in PARAM_NAMES
        }
    return Point(
        run=str(status["id"]), kind=kind, time=str(when), frame=frame,
        installed=status.get("installed"), verdict=status.get("verdict"), modules=modules,
    )  # fmt: skip


def points(rt: Runtime, since: str | None = None) -> list[Point]:
    """Every finished run's point, oldest first (from ``since``, ISO, if given)."""
    found: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {}
    for st, doc in rt.store.finished():
        found[str(st["id"])] = (st, doc)
    for rid, run in list(rt.runs.items()):
        if run.status.state == "DONE" and run.result_doc is not None:
            found[rid] = (run.status.to_dict(), run.result_doc)
    out = [p for st, doc in found.values() if (p := point_of(st, doc)) is not None]
    if since is not None:
        t0 = epoch(since)
        out = [p for p in out if epoch(p.time) >= t0]
    return sorted(out, key=lambda p: epoch(p.time))


def in_reference_frame(
    p: Point, frame: str, nominal: RobotParams
) -> dict[int, dict[str, tuple[float, float]]] | None:
    """``p``'s modules in ``frame``: as they are in it; a point in R re-expressed in
    design-fit (:func:`swpc_hw.robot.frames.params_in_design_fit`, as the result's
    comparison does); None when it cannot be."""
    if p.frame == frame:
        return p.modules
    if not (p.frame == "R" and frame == DESIGN_FIT):
        return None
    ids = [m for m in sorted(p.modules) if m in nominal.ids]
    if len(ids) < 2:
        return None
    sds = {m: [p.modules[m][k][1] for k in PARAM_NAMES] for m in ids}
    params = RobotParams(modules=[
        ModuleParams(
            id=m, **{k: p.modules[m][k][0] for k in PARAM_NAMES},
            stddev=ModuleStddev.of(sds[m]) if all(map(math.isfinite, sds[m])) else None,
        )
        for m in ids
    ])  # fmt: skip
    moved, _, _ = params_in_design_fit(params, nominal)
    nan = [float("nan")] * len(PARAM_NAMES)
    return {
        m.id: dict(zip(PARAM_NAMES, zip(m.values(), m.stddev.values() if m.stddev else nan,
                                        strict=True), strict=True))
        for m in moved.modules
    }  # fmt: skip


def parameter_series(
    pts: list[Point],
    reference: dict[int, dict[str, float]] | None,
    reference_frame: str,
    config: RobotConfig,
    now: float,
) -> list[dict[str, Any]]:
    """Per module and parameter: its points, the reference and tolerance, the trend
    (module docstring), display units.  The trend weighs each point by its std dev and
    the robot's repeatability together (``check.repeatability``: two runs of an unchanged
    robot differ by that much more than their std devs say, docs/check.md)."""
    ids = sorted({m for p in pts for m in p.modules} | set(reference or {}))
    rep = dict(zip(PARAM_NAMES, config.check.repeatability.per_parameter(), strict=True))
    placed = {p.run: in_reference_frame(p, reference_frame, config.nominal) for p in pts}
    nan = (float("nan"), float("nan"))
    out = []
    for mid in ids:
        mine = [p for p in pts if mid in p.modules]
        for k in PARAM_NAMES:
            unit, f = DISPLAY[k]
            free = k in FRAME_FREE
            values = [
                p.modules[mid][k] if free or p.frame == FILE_FIT
                else (placed[p.run] or {}).get(mid, {}).get(k, nan)
                for p in mine
            ]  # fmt: skip
            other = [not (free or p.frame == FILE_FIT) and placed[p.run] is None for p in mine]
            ref = None if reference is None or mid not in reference else reference[mid][k] * f
            if ref is None:  # none in force: the newest calibration's
                cal = [v for p, v in zip(mine, values, strict=True) if p.kind == "calibration"]
                ref = cal[-1][0] * f if cal else None
            tol = float(getattr(config.tolerances, TOLERANCE_OF[k])) * f
            used = [
                (epoch(p.time), v * f, math.hypot(sd, rep[k]) * f)
                for p, (v, sd), o in zip(mine, values, other, strict=True)
                if p.frame != FILE_FIT and not o
            ]
            tr = None
            if ref is not None and used:
                t, y, s = zip(*used, strict=True)
                tr = linear_trend(t, y, s, reference=ref, tolerance=tol, now=now)
            trend = None
            if tr is not None:
                trend = {
                    "points": tr.points,
                    "per_week": tr.slope * WEEK,
                    "per_week_std": tr.slope_std * WEEK,
                    "significant": tr.significant,
                    "value_now": tr.at(now),
                    "birge": tr.birge,
                    "leaves_tolerance": None if tr.leaves_at is None else iso(tr.leaves_at),
                    "outside": tr.outside,
                    "line": [{"time": iso(t), "value": tr.at(t)} for t in (used[0][0], now)],
                }
            series = [
                {
                    "time": p.time, "run": p.run, "kind": p.kind, "frame": p.frame,
                    "value": None if o else v * f, "stddev": None if o else sd * f,
                    "other_frame": o,
                    "re_expressed": not (o or free or p.frame in (FILE_FIT, reference_frame)),
                }
                for p, (v, sd), o in zip(mine, values, other, strict=True)
            ]  # fmt: skip
            out.append(
                {
                    "module": mid, "param": k, "unit": unit, "reference": ref,
                    "tolerance": tol, "points": series, "trend": trend,
                }
            )  # fmt: skip
    return out


def last_check(rt: Runtime) -> dict[str, Any] | None:
    """The robot's newest check: its id, state, time, and once DONE its verdict, action,
    summary and drifted modules; None before the first."""
    checks = rt.list_runs("check")
    if not checks:
        return None
    st = checks[-1]
    out: dict[str, Any] = {
        "id": st["id"], "state": st["state"], "created": st.get("created"),
        "finished": st.get("finished"), "verdict": st.get("verdict"), "reason": st.get("reason"),
    }  # fmt: skip
    got = rt.result(str(st["id"]), "check")
    doc = None if got is None else got[1]
    if doc is not None:
        for key in ("action", "summary", "drifted_modules", "file"):
            out[key] = doc.get(key)
    return out


def history_document(rt: Runtime, since: str | None = None) -> dict[str, Any]:
    """``GET /history`` (module docstring): the runs it holds, the last check, the file
    in force it is judged against, and per module and parameter the series and trend."""
    now = time.time()
    pts = points(rt, since)
    reference: dict[int, dict[str, float]] | None = None
    frame = "R"
    file: dict[str, Any] | None = None
    try:
        kf, info, _ = rt.file_in_force()
    except NoFileError:  # none in force, or it does not load: the newest calibration's
        kf = None
    cals = [p for p in pts if p.kind == "calibration"]
    if cals:  # none in force: the newest calibration's values, in its frame
        frame = cals[-1].frame
    if kf is not None:
        frame = kf.params.frame
        reference = {
            m.id: {k: float(getattr(m, k)) for k in PARAM_NAMES} for m in kf.params.modules
        }
        file = info
    runs = [
        {
            "run": p.run, "kind": p.kind, "time": p.time, "frame": p.frame,
            "installed": p.installed, "verdict": p.verdict,
        }
        for p in pts
    ]  # fmt: skip
    return {
        "robot": rt.config.robot,
        "now": iso(now),
        "since": since,
        "file_in_force": file,
        "tolerances": rt.config.tolerances.model_dump(),
        "runs": runs,
        "last_check": last_check(rt),
        "parameters": parameter_series(pts, reference, frame, rt.config, now),
    }
