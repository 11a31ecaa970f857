"""Kinematic file (``format: swpc-kinematics/1``): load with validation, save atomically.

Schema (docs/kinematic-file.md)::

    format: swpc-kinematics/1
    robot: <robot id>
    frame: <frame name>
    created: <ISO 8601 UTC>
    units: {length: m, angle: rad}    # optional on load; always written
    modules:
      - {id, x_s, y_s, beta, b, r, stddev: {x_s, y_s, beta, b, r}}   # stddev optional
    covariance:                                  # optional: all parameters' covariance
      order: [x_s, y_s, beta, b, r]              # within a module; modules in file order
      matrix: [[...], ...]                       # (5N, 5N), SI units (m, rad)

Unknown keys are ignored on load (and preserved in ``extra`` of :class:`KinematicFile`);
missing required keys, non-finite values, ``b <= 0``, ``r <= 0``, duplicate ids, N < 2,
a ``units`` other than SI and a ``provenance`` that is not a mapping raise
:class:`~swpc_hw.errors.KinematicFileError` naming the key.  A ``covariance`` must be
square of size 5N, symmetric, positive semi-definite and agree with the modules'
``stddev``.  Files are written with the mode a new file gets (``0666`` less the umask),
not the temporary file's ``0600``: the robot's odometry, another user, reads them.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import math
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from swpc_hw.errors import KinematicFileError
from swpc_hw.robot.model import PARAM_NAMES, ModuleParams, ModuleStddev, RobotParams

FORMAT = "swpc-kinematics/1"
UNITS = {"length": "m", "angle": "rad"}
"""The format's units (SI); a file may say so in ``units:``, never anything else."""
COVARIANCE_KEY = "covariance"


@dataclass
class KinematicFile:
    """A loaded kinematic file: the robot parameters plus header and extra keys."""

    params: RobotParams
    created: str
    extra: dict[str, Any] = field(default_factory=dict)
    covariance: list[list[float]] | None = None
    """(5N, 5N) covariance of the parameters (order: modules, then x_s, y_s, beta, b, r)."""


def _now_iso() -> str:
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def _number(value: Any, key: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise KinematicFileError(f"{where}: {key}: must be a number (got {value!r})")
    x = float(value)
    if not math.isfinite(x):
        raise KinematicFileError(f"{where}: {key}: must be finite (got {value!r})")
    return x


def parse_kinematics(doc: Any, where: str = "<kinematics>") -> KinematicFile:
    """Validate a parsed YAML document; ``where`` names the source in error messages."""
    if not isinstance(doc, dict):
        raise KinematicFileError(f"{where}: top level must be a mapping")
    for key in ("format", "robot", "frame", "modules"):
        if key not in doc:
            raise KinematicFileError(f"{where}: missing key '{key}'")
    if doc["format"] != FORMAT:
        raise KinematicFileError(f"{where}: format: expected '{FORMAT}' (got {doc['format']!r})")
    units = doc.get("units")
    if units is not None:
        if not isinstance(units, dict):
            raise KinematicFileError(f"{where}: units: must be a mapping (got {units!r})")
        for key, unit in UNITS.items():
            if units.get(key, unit) != unit:
                raise KinematicFileError(
                    f"{where}: units.{key}: {FORMAT} is in {unit} (got {units[key]!r})"
                )
    if "provenance" in doc and not isinstance(doc["provenance"], dict):
        raise KinematicFileError(f"{where}: provenance: must be a mapping")
    mods = doc["modules"]
    if not isinstance(mods, list):
        raise KinematicFileError(f"{where}: modules: must be a list")
    if len(mods) < 2:
        raise KinematicFileError(f"{where}: modules: an SWPC robot needs N >= 2 (got {len(mods)})")
    modules: list[ModuleParams] = []
    seen: set[int] = set()
    for i, m in enumerate(mods):
        loc = f"modules[{i}]"
        if not isinstance(m, dict):
            raise KinematicFileError(f"{where}: {loc}: must be a mapping")
        if "id" not in m:
            raise KinematicFileError(f"{where}: missing key '{loc}.id'")
        mid = m["id"]
        if isinstance(mid, bool) or not isinstance(mid, int) or mid < 0:
            raise KinematicFileError(f"{where}: {loc}.id: must be a non-negative integer")
        if mid in seen:
            raise KinematicFileError(f"{where}: {loc}.id: duplicate module id {mid}")
        seen.add(mid)
        vals: dict[str, float] = {}
        for key in PARAM_NAMES:
            if key not in m:
                raise KinematicFileError(f"{where}: missing key '{loc}.{key}'")
            vals[key] = _number(m[key], f"{loc}.{key}", where)
        for key in ("b", "r"):
            if vals[key] <= 0.0:
                raise KinematicFileError(f"{where}: {loc}.{key}: must be > 0 (got {vals[key]!r})")
        std = None
        if m.get("stddev") is not None:
            sd = m["stddev"]
            if not isinstance(sd, dict):
                raise KinematicFileError(f"{where}: {loc}.stddev: must be a mapping")
            sdv: dict[str, float] = {}
            for key in PARAM_NAMES:
                if key not in sd:
                    raise KinematicFileError(f"{where}: missing key '{loc}.stddev.{key}'")
                sdv[key] = _number(sd[key], f"{loc}.stddev.{key}", where)
                if sdv[key] < 0:
                    raise KinematicFileError(f"{where}: {loc}.stddev.{key}: must be >= 0")
            std = ModuleStddev(**sdv)
        modules.append(ModuleParams(id=mid, stddev=std, **vals))
    known = {"format", "robot", "frame", "created", "units", "modules", COVARIANCE_KEY}
    extra = {k: v for k, v in doc.items() if k not in known}
    params = RobotParams(robot=str(doc["robot"]), frame=str(doc["frame"]), modules=modules)
    cov = None
    if doc.get(COVARIANCE_KEY) is not None:
        cov = parse_covariance(doc[COVARIANCE_KEY], modules, where)
    return KinematicFile(
        params=params, created=str(doc.get("created", "")), extra=extra, covariance=cov
    )


def parse_covariance(doc: Any, modules: list[ModuleParams], where: str) -> list[list[float]]:
    """Validate a ``covariance`` document against the modules; returns the matrix."""
    key = COVARIANCE_KEY
    if not isinstance(doc, dict):
        raise KinematicFileError(f"{where}: {key}: must be a mapping with order and matrix")
    if doc.get("order") != list(PARAM_NAMES):
        raise KinematicFileError(
            f"{where}: {key}.order: expected {list(PARAM_NAMES)} (got {doc.get('order')!r})"
        )
    size = len(PARAM_NAMES) * len(modules)
    rows = doc.get("matrix")
    if not isinstance(rows, list) or len(rows) != size:
        raise KinematicFileError(f"{where}: {key}.matrix: must be {size} rows of {size} numbers")
    matrix: list[list[float]] = []
    for i, row in enumerate(rows):
        if not isinstance(row, list) or len(row) != size:
            raise KinematicFileError(f"{where}: {key}.matrix[{i}]: must be {size} numbers")
        matrix.append([_number(v, f"{key}.matrix[{i}][{j}]", where) for j, v in enumerate(row)])
    a = np.array(matrix)
    diag = np.diag(a)
    if np.any(diag < 0):
        raise KinematicFileError(f"{where}: {key}.matrix: negative variance on the diagonal")
    scale = np.sqrt(np.outer(diag, diag))
    if np.any(np.abs(a - a.T) > 1e-9 * scale + 1e-300):
        raise KinematicFileError(f"{where}: {key}.matrix: not symmetric")
    d = np.where(diag > 0, np.sqrt(diag), 1.0)
    if np.linalg.eigvalsh(a / np.outer(d, d)).min() < -1e-8:
        raise KinematicFileError(f"{where}: {key}.matrix: not positive semi-definite")
    for i, m in enumerate(modules):
        if m.stddev is None:
            continue
        for k, name in enumerate(PARAM_NAMES):
            std = float(getattr(m.stddev, name))
            got = math.sqrt(diag[len(PARAM_NAMES) * i + k])
            if abs(got - std) > 1e-6 * std + 1e-15:
                raise KinematicFileError(
                    f"{where}: {key}.matrix: variance of module {m.id} {name} gives a std dev "
                    f"of {got!r}, its stddev.{name} says {std!r}"
                )
    return matrix


def load_kinematics(path: str | os.PathLike[str]) -> KinematicFile:
    """Load and validate a kinematic file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise KinematicFileError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    except UnicodeDecodeError as exc:
        raise KinematicFileError(
            f"{p}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}): "
            "a damaged or foreign file"
        ) from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise KinematicFileError(f"{p}: not valid YAML: {exc}".splitlines()[0]) from exc
    return parse_kinematics(doc, str(p))


def load_robot(path: str | os.PathLike[str]) -> RobotParams:
    """Load just the parameters of a kinematic file (e.g. a dataset's ``robot.yaml``)."""
    return load_kinematics(path).params


def kinematics_document(
    params: RobotParams,
    *,
    created: str | None = None,
    extra: dict[str, Any] | None = None,
    covariance: Any = None,
) -> dict[str, Any]:
    """The YAML document for ``params`` (plain Python types only).

    ``covariance``: optional (5N, 5N) array-like, written under ``covariance``.
    """
    modules = []
    for m in params.modules:
        d: dict[str, Any] = {"id": m.id}
        d.update({k: float(getattr(m, k)) for k in PARAM_NAMES})
        if m.stddev is not None:
            d["stddev"] = {k: float(getattr(m.stddev, k)) for k in PARAM_NAMES}
        modules.append(d)
    doc: dict[str, Any] = {
        "format": FORMAT,
        "robot": params.robot,
        "frame": params.frame,
        "created": created or _now_iso(),
        "units": dict(UNITS),
        "modules": modules,
    }
    if covariance is not None:
        doc[COVARIANCE_KEY] = {
            "order": list(PARAM_NAMES),
            "matrix": [[float(v) for v in row] for row in np.asarray(covariance, dtype=float)],
        }
    for k, v in (extra or {}).items():
        if k not in doc:
            doc[k] = v
    return doc


def current_umask() -> int:
    """The process's umask, read without changing it (``/proc/self/status``; else set and
    restored at once)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` to ``path`` atomically: temp file in the same directory, fsync, rename.

    On any failure the temp file is removed and ``path`` is untouched.  The file gets the
    mode a new file gets (``0666`` less the umask), not the temporary file's ``0600``.
    """
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """:func:`atomic_write_text` for bytes."""
    p = Path(path)
    directory = p.parent if str(p.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=directory)
    try:
        os.fchmod(fd, 0o666 & ~current_umask())  # what open() would have made, not 0600
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # persist the rename itself
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def save_kinematics(
    path: str | os.PathLike[str],
    params: RobotParams,
    *,
    created: str | None = None,
    extra: dict[str, Any] | None = None,
    covariance: Any = None,
) -> None:
    """Save ``params`` (with their (5N, 5N) ``covariance`` if given), atomically."""
    doc = kinematics_document(params, created=created, extra=extra, covariance=covariance)
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=False)
    parse_kinematics(yaml.safe_load(text), str(path))  # never write what we cannot load
    try:
        atomic_write_text(path, text)
    except OSError as exc:
        raise KinematicFileError(f"{path}: cannot write: {exc.strerror or exc}") from exc
