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
missing required keys, non-finite values, values outside :data:`BOUNDS`, duplicate ids,
N < 2, a ``units`` other than SI and a ``provenance`` that is not a mapping raise
:class:`~swpc_hw.errors.KinematicFileError` naming the key.

What is read (:func:`read_kinematics_text`, for every reader: the service, the odometry,
the command line) is a regular file (a link to one is followed; a FIFO, a device or a
directory is refused without waiting on it) of at most :data:`MAX_BYTES`, UTF-8, YAML
without aliases (:func:`load_yaml`: an alias can make a few kB into gigabytes).

A ``covariance`` must be square of size 5N, symmetric, positive semi-definite and agree
with the modules' ``stddev``.  Files are written with the mode a new file gets (``0666``
less the umask), not the temporary file's ``0600``: the robot's odometry, another user,
reads them.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import math
import os
import stat
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from swpc_hw.errors import KinematicFileError
from swpc_hw.robot.model import PARAM_NAMES, ModuleParams, ModuleStddev, RobotParams

FORMAT = "swpc-kinematics/1"
MAX_BYTES = 1 << 20
"""Largest kinematic file read (1 MiB: a robot of 40 modules with its covariance)."""
BOUNDS: dict[str, tuple[float, float]] = {
    "x_s": (-50.0, 50.0),
    "y_s": (-50.0, 50.0),
    "beta": (-2 * math.pi, 2 * math.pi),
    "b": (1e-4, 1.0),
    "r": (1e-3, 1.0),
}
"""Plausible values (m, rad; inclusive): a steering axis within 50 m of the robot's
origin, a homing error within a turn, a caster offset of 0.1 mm to 1 m, a wheel radius of
1 mm to 1 m.  Anything else is a damaged file, never a robot (``r = b = 1e-300`` once
divided the odometry by zero)."""
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
        for key, (lo, hi) in BOUNDS.items():
            if not lo <= vals[key] <= hi:
                raise KinematicFileError(
                    f"{where}: {loc}.{key}: must be within [{lo:g}, {hi:g}] (got {vals[key]!r})"
                )
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


class _NoAliasLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses an alias (``*name``) where it meets one."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            mark = self.peek_event().start_mark  # type: ignore[no-untyped-call]
            raise yaml.YAMLError(
                f"YAML alias at line {mark.line + 1}: a kinematic file has no aliases"
            )
        return super().compose_node(parent, index)


def load_yaml(text: str, where: str) -> Any:
    """``text`` as YAML without aliases; :class:`KinematicFileError` naming ``where``."""
    try:
        return yaml.load(text, Loader=_NoAliasLoader)
    except yaml.YAMLError as exc:
        raise KinematicFileError(f"{where}: not valid YAML: {exc}".splitlines()[0]) from exc


def read_kinematics_text(path: str | os.PathLike[str]) -> str:
    """The text of the file at ``path`` (module docstring: a regular file of at most
    :data:`MAX_BYTES`, UTF-8); :class:`KinematicFileError` with the reason otherwise.

    Opened without blocking (a FIFO's open waits for a writer), then judged on the open
    file, so what is read is what was checked."""
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as exc:
        raise KinematicFileError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise KinematicFileError(f"{p}: not a regular file ({_file_kind(st.st_mode)})")
        if st.st_size > MAX_BYTES:
            raise KinematicFileError(
                f"{p}: {st.st_size} bytes: a kinematic file is at most {MAX_BYTES} bytes"
            )
        with os.fdopen(os.dup(fd), "rb") as fh:
            data = fh.read(MAX_BYTES + 1)
    except OSError as exc:
        raise KinematicFileError(f"{p}: cannot read: {exc.strerror or exc}") from exc
    finally:
        os.close(fd)
    if len(data) > MAX_BYTES:
        raise KinematicFileError(f"{p}: grew past {MAX_BYTES} bytes while read")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise KinematicFileError(
            f"{p}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}): "
            "a damaged or foreign file"
        ) from exc


def _file_kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a file"


def load_kinematics(path: str | os.PathLike[str]) -> KinematicFile:
    """Load and validate a kinematic file (module docstring)."""
    text = read_kinematics_text(path)
    return parse_kinematics(load_yaml(text, str(path)), str(path))


def module_mismatch(modules: Sequence[int], ids: Sequence[int]) -> str | None:
    """Why a kinematic file's module ids ``modules`` are not the robot's ``ids`` (the
    robot config's), or None: every module of the robot, and no other (in any order)."""
    have, want = sorted(modules), sorted(ids)
    if have == want:
        return None
    missing = [m for m in want if m not in have]
    extra = [m for m in have if m not in want]
    parts = [f"no module {missing}" if missing else "", f"modules {extra} the robot has not"
             if extra else ""]  # fmt: skip
    return (
        f"its modules {have} are not the robot's {want} ("
        + "; ".join(p for p in parts if p)
        + ")"
    )


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
    parse_kinematics(load_yaml(text, str(path)), str(path))  # never write what we cannot load
    try:
        atomic_write_text(path, text)
    except OSError as exc:
        raise KinematicFileError(f"{path}: cannot write: {exc.strerror or exc}") from exc
