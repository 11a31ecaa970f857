"""The kinematic file in force, its dated backups, install and roll back (HTTP).

* ``GET /kinematics``: the file in force (docs/kinematic-file.md); 404 when none is
  installed, 500 naming the backups that load when it is on disk but does not load.
* ``GET /kinematics/files``: the file in force and every backup kept beside it
  (``<stem>.<UTC time><suffix>``, :func:`services.runs.install.backup_kinematics`),
  newest first, each with the run it came from (its ``provenance.run``).
* ``POST /calibrations/{id}/install``: installs a finished run's own result file.
* ``POST /kinematics/rollback``: installs one of the backups again.
* ``GET /kinematics/changes``: every change of the file in force, newest first: a run's
  install at its end, an install of a run's result, a roll-back, each with the backup
  kept of the file it replaced (the run store keeps them,
  :meth:`services.store.runs.RunStore.add_change`).
* ``GET /calibrations/{id}/comparison``: a run's result against its reference, one
  verdict per parameter: once installed, the file its install replaced (the last
  install of it, at the run's end or later; none in force: nominal); never installed,
  the file in force (what an install would replace; none: nominal).

Both writes need the bearer token, are refused while a calibration runs (409), check the
file they install (a corrupt one is 422, shaped as FastAPI's own, and installs nothing)
and keep the file they replace as a new backup: a roll-back can itself be rolled back.
A write that fails (a full disk: 507, else 500) leaves the file in force untouched.
Each outcome is a structured log line on ``swpc.service`` (:mod:`services.store.logs`):
``kinematics.install`` / ``kinematics.rollback`` (INFO: the file installed, its sha256,
the backup kept, the client), ``kinematics.install_refused`` (WARNING: 409, 422) and
``kinematics.install_failed`` (ERROR).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import errno
import hashlib
import logging
import math
import os
import re
import sqlite3
from pathlib import Path
from typing import Any, Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field

from services.config.robot import TOLERANCE_OF, Tolerances
from services.http.deps import AUTH, GUARDED, FiniteJSONResponse, Problem, Rt, done_result, problems
from services.runs.install import BACKUP_STAMP, backup_kinematics, backups, read_replaced
from services.runs.state import now_iso
from services.runtime.runtime import Runtime
from services.store.logs import event
from swpc_hw.calibration.report import DISPLAY
from swpc_hw.errors import KinematicFileError
from swpc_hw.files.kinematic_file import (
    KinematicFile,
    atomic_write_text,
    load_kinematics,
    load_yaml,
    parse_kinematics,
)
from swpc_hw.robot.frames import (
    DESIGN_FIT,
    FloatArray,
    frame_of_metrology,
    params_in_design_fit,
)
from swpc_hw.robot.model import PARAM_NAMES, ModuleParams, ModuleStddev, RobotParams

log = logging.getLogger("swpc.service")

SIGNIFICANCE_K = 3.0
"""A change is significant when it exceeds this many standard deviations of the change."""

class FileInfo(BaseModel):
    """One kinematic file: the one in force or a backup."""

    name: str
    backup_time: str | None = Field(None, description="when it was replaced (backups), UTC")
    created: str | None = None
    robot: str | None = None
    run: str | None = Field(None, description="the calibration run it came from, if any")
    method: str | None = None
    sha256: str | None = Field(
        description="first 16 hex digits of the file's sha256 (None: it cannot be read)"
    )
    valid: bool
    error: str | None = None


class KinematicFiles(BaseModel):
    path: str
    in_force: FileInfo | None
    backups: list[FileInfo]


class RollbackRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    backup: str = Field(description="a backup's name, as GET /kinematics/files lists it")


class InstallResult(BaseModel):
    in_force: FileInfo
    backup: str | None = Field(None, description="the backup kept of the file it replaced")


class ComparisonRow(BaseModel):
    module: int
    param: str
    unit: str
    nominal: float
    calibrated: float
    stddev: float | None
    reference_value: float | None = Field(
        description="the reference file's value (None: the reference is nominal)"
    )
    change: float = Field(description="calibrated - the reference's value (else nominal)")
    significant: bool | None = Field(
        description=f"|change| > {SIGNIFICANCE_K:g} std devs of the change (None: unknown)"
    )
    tolerance: float
    within_tolerance: bool | None


class KinematicChange(BaseModel):
    """One change of the file in force (``GET /kinematics/changes``)."""

    time: str = Field(description="when (UTC)")
    action: Literal["run", "install", "rollback"] = Field(
        description="run: a run installed its result at its end; install: a run's result "
        "installed later; rollback: a backup installed again"
    )
    run: str | None = Field(description="the run whose result was installed (a roll-back: "
                            "the run the restored file came from, if any)")
    file: str = Field(description="the file installed: a run's result, or a backup")
    replaced: str | None = Field(
        description="the backup kept of the file it replaced (None: no file was in force)"
    )
    replaced_run: str | None = Field(description="the run the replaced file came from")


class Comparison(BaseModel):
    run: str
    reference: Literal["replaced file", "file in force", "nominal"] = Field(
        description="'replaced file': the file the run's last install replaced; 'file in "
        "force': never installed, the file an install would replace; 'nominal': neither "
        "(see reference_why)"
    )
    reference_why: str | None = Field(
        None, description="why the reference is nominal: no file was, or is, in force"
    )
    replaced: KinematicChange | None = Field(
        None, description="the run's last install (its time, the backup of the file replaced)"
    )
    in_force: FileInfo | None
    frame: str = Field(
        "R", description="the frame of the comparison: R (motion capture) or design-fit "
        "(a result without motion capture, or a reference from one: whichever of the two is "
        "in another frame is re-expressed in design-fit, as frame_note says)"
    )  # fmt: skip
    frame_note: str | None = Field(
        None, description="which of the two was re-expressed in design-fit, and how"
    )
    is_in_force: bool = Field(description="the file in force is this run's result")
    significance_k: float
    within_tolerance: bool
    installed: bool
    install_held: str | None = Field(
        None, description="why the default install (if within tolerance) did not install a "
        "result within tolerance: the file in force was in another frame"
    )  # fmt: skip
    rows: list[ComparisonRow]


class UnreadableFileProblem(Problem):
    """``GET /kinematics`` when the file in force is on disk but does not load (500)."""

    path: str
    reason: str = Field(description="why it does not load (the loader's message)")
    backups: list[str] = Field(
        description="the backups beside it that do load, newest first: what "
        "POST /kinematics/rollback can install"
    )


def unreadable_problem(path: Path, exc: Exception) -> UnreadableFileProblem:
    """The answer to a read of the file in force ``path`` that failed with ``exc``:
    what is wrong and what to do (roll back to the newest backup that loads)."""
    good = [b.name for b in backups(path) if describe(b, backup=True).valid]
    if good:
        fix = f'roll back to a backup: POST /kinematics/rollback {{"backup": "{good[0]}"}}'
    else:
        fix = "no backup beside it loads: install a run's result (POST /calibrations/<id>/install)"
    return UnreadableFileProblem(
        detail=f"the kinematic file in force cannot be loaded: {exc}; {fix} "
        "(GET /kinematics/files lists them)",
        path=str(path),
        reason=str(exc),
        backups=good,
    )


def present(path: Path) -> bool:
    """Something is at ``path``: a file, or anything else that then fails to load (a
    directory, a dangling symbolic link) rather than reading as "none installed"."""
    return os.path.lexists(path)


def describe(path: Path, backup: bool = False) -> FileInfo:
    """What a kinematic file says of itself (a corrupt one: ``valid`` false, the error)."""
    try:
        digest: str | None = hashlib.sha256(path.read_bytes()).hexdigest()[:16]
    except OSError:
        digest = None  # load_kinematics below says why
    info: dict[str, Any] = {"name": path.name, "sha256": digest, "valid": True}
    if backup:
        m = re.search(r"\.(\d{8}T\d{12}Z)\.[^.]*$", path.name)
        if m is not None:
            t = _dt.datetime.strptime(m.group(1), BACKUP_STAMP).replace(tzinfo=_dt.UTC)
            info["backup_time"] = t.isoformat(timespec="seconds").replace("+00:00", "Z")
    try:
        k = load_kinematics(path)
    except (KinematicFileError, OSError, UnicodeDecodeError) as exc:
        info.update(valid=False, error=str(exc))
        return FileInfo(**info)
    prov = k.extra.get("provenance")
    prov = prov if isinstance(prov, dict) else {}
    info.update(
        created=str(k.created) if k.created else None,
        robot=k.params.robot,
        run=str(prov["run"]) if prov.get("run") else None,
        method=str(prov["method"]) if prov.get("method") else None,
    )
    return FileInfo(**info)


def checked_text(source: Path) -> str:
    """The text of the kinematic file ``source`` once it loads (:class:`KinematicFileError`
    naming the problem otherwise)."""
    load_kinematics(source)
    try:
        return source.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:  # changed since it was loaded
        raise KinematicFileError(f"{source}: {exc}") from exc


def install_text(target: Path, text: str, keep: int) -> Path | None:
    """Install ``text`` at ``target`` (atomic replace, the file replaced kept as a backup,
    ``keep`` at the most, whose path is returned).  ``OSError`` or
    :class:`KinematicFileError` (no room for the backup): the file in force is untouched."""
    backup = backup_kinematics(target, keep)
    target.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(target, text)
    return backup


def _write_failure(exc: Exception) -> HTTPException:
    """A failed write of the file in force: 507 when the disk (or a quota) is full."""
    cause = exc if isinstance(exc, OSError) else exc.__cause__
    full = isinstance(cause, OSError) and cause.errno in (errno.ENOSPC, errno.EDQUOT)
    reason = cause.strerror if isinstance(cause, OSError) and cause.strerror else str(exc)
    return HTTPException(
        507 if full else 500,
        f"not installed: cannot write the kinematic file: {reason} (the file in force is "
        "untouched)",
    )


def _moved(what: str, frame: str, phi: float, t: FloatArray) -> str:
    return (
        f"{what} (frame {frame}) re-expressed in design-fit: its steering axes fitted to the "
        f"nominal ones, turned {math.degrees(phi):+.3f} deg and moved "
        f"{float(np.hypot(*t)) * 1e3:.1f} mm"
    )


def in_design_fit(ref: KinematicFile, nominal: RobotParams) -> tuple[KinematicFile, str]:
    """A reference file re-expressed in the design-fit frame of a result without motion
    capture (:func:`params_in_design_fit`), and a sentence saying so."""
    moved, phi, t = params_in_design_fit(ref.params, nominal)
    return dataclasses.replace(ref, params=moved), _moved("the reference", ref.params.frame, phi, t)


def result_in_design_fit(
    doc: dict[str, Any], nominal: RobotParams
) -> tuple[dict[str, Any], str]:
    """A result in frame R (motion capture) re-expressed in design-fit, to be compared with
    a reference in that frame (a calibration without motion capture: its frame R is not
    known, so the result goes to it), and a sentence saying so."""
    mods = [
        ModuleParams(
            id=int(m["id"]), **{k: m[k] for k in PARAM_NAMES},
            stddev=None if m.get("stddev") is None else ModuleStddev(**m["stddev"]),
        )
        for m in doc["modules"]
    ]  # fmt: skip
    moved, phi, t = params_in_design_fit(RobotParams(modules=mods), nominal)
    out = []
    for m, new in zip(doc["modules"], moved.modules, strict=True):
        sd = None if new.stddev is None else new.stddev.model_dump()
        out.append({**m, **{k: getattr(new, k) for k in PARAM_NAMES}, "stddev": sd})
    return {**doc, "modules": out}, _moved("this result", "R", phi, t)


def compare(
    run_id: str, doc: dict[str, Any], reference: KinematicFile | None, tol: Tolerances
) -> list[ComparisonRow]:
    """One row per module and parameter (display units,
    :data:`~swpc_hw.calibration.report.DISPLAY`), against the ``reference`` file (None:
    nominal)."""
    rows = []
    for m in doc["modules"]:
        ref = None
        if reference is not None:
            try:
                ref = reference.params.module(int(m["id"]))
            except (KeyError, ValueError):
                ref = None
        for p in PARAM_NAMES:
            unit, f = DISPLAY[p]
            sd = (m.get("stddev") or {}).get(p)
            sd = None if sd is None or not math.isfinite(sd) else float(sd)
            ref_v = None if ref is None else float(getattr(ref, p))
            base = ref_v if ref_v is not None else float(m["nominal"][p])
            change = float(m[p]) - base
            ref_sd = None
            if ref is not None and ref.stddev is not None:
                ref_sd = float(getattr(ref.stddev, p))
            significant = None
            if sd is not None:
                sigma = math.hypot(sd, ref_sd or 0.0)
                significant = abs(change) > SIGNIFICANCE_K * sigma
            t = float(getattr(tol, TOLERANCE_OF[p]))
            rows.append(
                ComparisonRow(
                    module=int(m["id"]),
                    param=p,
                    unit=unit,
                    nominal=float(m["nominal"][p]) * f,
                    calibrated=float(m[p]) * f,
                    stddev=None if sd is None else sd * f,
                    reference_value=None if ref_v is None else ref_v * f,
                    change=change * f,
                    significant=significant,
                    tolerance=t * f,
                    within_tolerance=None if sd is None else sd <= t,
                )
            )
    return rows


WRITE_RESPONSES = {
    **GUARDED,
    **problems(
        404,
        409,
        _500="the file could not be written (untouched)",
        _507="no room on disk for the file (untouched)",
    ),
}


def files(rt: Runtime) -> KinematicFiles:
    path = rt.settings.kinematics_file
    return KinematicFiles(
        path=str(path),
        in_force=describe(path) if present(path) else None,
        backups=[describe(p, backup=True) for p in backups(path)],
    )


def install_checked(rt: Runtime, source: Path, request: Request, **what: Any) -> InstallResult:
    """Install ``source`` (module docstring); ``what`` names it in the log lines (``run=``
    for a run's result, ``restored=`` for a backup rolled back to)."""
    action = "rollback" if "restored" in what else "install"
    client = request.client.host if request.client is not None else None
    fields: dict[str, Any] = {"action": action, **what, "client": client}
    path = rt.settings.kinematics_file
    with rt.lock:  # the runtime's: no run starts during an install
        if rt.running():
            why = "a calibration is running: the file is not changed"
            event(log, logging.WARNING, "kinematics.install_refused", **fields, reason=why)
            raise HTTPException(409, why)
        try:
            text = checked_text(source)
        except KinematicFileError as exc:
            event(log, logging.WARNING, "kinematics.install_refused", **fields, reason=str(exc))
            # the shape of FastAPI's own 422 (one schema for 422)
            raise RequestValidationError(
                [{"loc": ["body"], "msg": f"not installed: {exc}", "type": "value_error"}]
            ) from exc
        old = describe(path) if present(path) else None
        old_text = read_replaced(path) if old is not None else None
        try:
            backup = install_text(path, text, rt.settings.kinematics_backups)
        except (OSError, KinematicFileError) as exc:
            failure = _write_failure(exc)
            event(
                log, logging.ERROR, "kinematics.install_failed", **fields,
                path=str(path), status=failure.status_code, error=str(exc),
            )  # fmt: skip
            raise failure from exc
        info = describe(path)
        event(
            log, logging.INFO, f"kinematics.{action}", **what, path=str(path),
            sha256=info.sha256, source_run=info.run,
            backup=None if backup is None else backup.name, client=client,
        )  # fmt: skip
        change = {
            "time": now_iso(),
            "action": action,
            "run": info.run,
            "file": source.name if action == "rollback" else f"runs/{what['run']}/{source.name}",
            "replaced": None if backup is None else backup.name,
            "replaced_run": None if old is None else old.run,
        }
        try:
            rt.store.add_change(change, old_text)
        except sqlite3.Error as exc:  # installed all the same: the history misses it
            event(log, logging.ERROR, "kinematics.change_unrecorded", **fields, error=str(exc))
        return InstallResult(in_force=info, backup=None if backup is None else backup.name)


router = APIRouter()


@router.get(
    "/kinematics",
    responses={
        404: {"model": Problem, "description": "no kinematic file installed"},
        500: {
            "model": UnreadableFileProblem,
            "description": "the file in force is on disk but does not load (damaged, "
            "not UTF-8, not a file): a fault of the server's data that lasts until a "
            "file is installed or rolled back, named with the backups that load; "
            "GET /health is then degraded",
        },
    },
)
def kinematics_in_force(rt: Rt) -> Any:
    """The kinematic file in force (docs/kinematic-file.md)."""
    try:
        doc = rt.kinematics_document()
    except KinematicFileError as exc:
        problem = unreadable_problem(rt.settings.kinematics_file, exc)
        return FiniteJSONResponse(problem.model_dump(), status_code=500)
    if doc is None:
        raise HTTPException(404, f"no kinematic file installed at {rt.settings.kinematics_file}")
    return doc


@router.get("/kinematics/files", response_model=KinematicFiles)
def list_files(rt: Rt) -> KinematicFiles:
    return files(rt)


@router.get("/kinematics/changes", response_model=list[KinematicChange])
def list_changes(rt: Rt) -> list[dict[str, Any]]:
    """Every change of the file in force, newest first (module docstring)."""
    return rt.store.changes()


@router.post(
    "/kinematics/rollback",
    response_model=InstallResult,
    dependencies=AUTH,
    responses=WRITE_RESPONSES,
)
def rollback(body: RollbackRequest, rt: Rt, request: Request) -> InstallResult:
    path = rt.settings.kinematics_file
    chosen = next((p for p in backups(path) if p.name == body.backup), None)
    if chosen is None:
        raise HTTPException(404, f"no backup {body.backup!r} beside {path}")
    return install_checked(rt, chosen, request, restored=chosen.name)


@router.post(
    "/calibrations/{run_id}/install",
    response_model=InstallResult,
    dependencies=AUTH,
    responses=WRITE_RESPONSES,
)
def install(run_id: str, rt: Rt, request: Request) -> InstallResult:
    got = rt.result(run_id, "calibration")
    if got is None:
        raise HTTPException(404, f"no calibration {run_id}")
    state, doc = got
    source = Path(rt.settings.data_dir) / "runs" / run_id / "kinematics.yaml"
    if state != "DONE" or doc is None or not source.is_file():
        raise HTTPException(409, f"calibration {run_id} is {state}: no result to install")
    return install_checked(rt, source, request, run=run_id)


@router.get(
    "/calibrations/{run_id}/comparison",
    response_model=Comparison,
    responses=problems(404, 409),
)
def comparison(run_id: str, rt: Rt) -> Comparison:
    doc = done_result(rt, run_id)
    path = rt.settings.kinematics_file
    info = describe(path) if present(path) else None
    in_force = load_kinematics(path) if info is not None and info.valid else None
    tol = Tolerances.model_validate(doc.get("tolerances") or rt.config.tolerances.model_dump())
    got = rt.store.replaced_by(run_id)
    why = None
    replaced = None
    if got is not None:  # installed: against the file its last install replaced
        replaced, text = KinematicChange(**got[0]), got[1]
        ref = None if text is None else _parse(text, replaced.replaced or "replaced file")
        reference = "replaced file" if ref is not None else "nominal"
        if text is None:
            why = "no file was in force when it was installed"
        elif ref is None:
            why = f"the file it replaced ({replaced.replaced}) does not load"
    elif bool(doc.get("installed")) or (info is not None and info.run == run_id):
        ref, reference = None, "nominal"  # installed before installs were recorded
        why = "the file its install replaced was not recorded"
    else:  # never installed: against what an install would replace
        ref = in_force
        reference = "file in force" if ref is not None else "nominal"
        if ref is None:
            why = "no file is in force" if info is None else "the file in force does not load"
    quality = doc.get("quality")
    frame = frame_of_metrology(quality.get("mode") if isinstance(quality, dict) else None)
    note = None
    if ref is not None and frame == DESIGN_FIT and ref.params.frame != DESIGN_FIT:
        ref, note = in_design_fit(ref, rt.config.nominal)
    elif ref is not None and frame != DESIGN_FIT and ref.params.frame == DESIGN_FIT:
        doc, note = result_in_design_fit(doc, rt.config.nominal)
        frame = DESIGN_FIT
    return Comparison(
        run=run_id,
        reference=reference,
        reference_why=why,
        frame=frame,
        frame_note=note,
        replaced=replaced,
        in_force=info,
        is_in_force=info is not None and info.run == run_id,
        significance_k=SIGNIFICANCE_K,
        within_tolerance=bool(doc.get("within_tolerance")),
        installed=bool(doc.get("installed")),
        install_held=doc.get("install_held"),
        rows=compare(run_id, doc, ref, tol),
    )


def _parse(text: str, name: str) -> KinematicFile | None:
    """A kinematic file's text, loaded; None when it does not load."""
    try:
        return parse_kinematics(load_yaml(text, name), name)
    except KinematicFileError:
        return None
