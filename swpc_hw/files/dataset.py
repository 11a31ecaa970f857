"""Offline calibration dataset (directory format of docs/dataset-format.md).

::

    robot.yaml      nominal robot (kinematic-file schema; beta may be 0)
    poses.csv       t,x,y,yaw                  pose of R in W (s, m, m, rad)
    encoders.csv    t,module,steer,wheel       reported theta_hat and psi (s, id, rad, rad)
    segments.csv    static_module,start,end    windows (s) of steady spinning

A dataset without motion capture has no ``poses.csv`` but (docs/dataset-format.md)::

    imu.csv         t,wz                       yaw rate of a gyro fixed to R (s, rad/s)
    references.yaml references: [...]          known quantities (:mod:`swpc_hw.files.references`)

``poses.csv`` may be absent only when ``imu.csv`` is present.  Rows need not be sorted
(they are sorted on load); poses may have gaps.  Every problem raises
:class:`~swpc_hw.errors.DatasetError` with a one-line message naming the file.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from swpc_hw.errors import DatasetError, KinematicFileError
from swpc_hw.files.kinematic_file import atomic_write_text, load_robot, save_kinematics
from swpc_hw.files.references import Reference, load_references, save_references
from swpc_hw.robot.model import RobotParams

FloatArray = NDArray[np.float64]

POSES_COLUMNS = ("t", "x", "y", "yaw")
IMU_COLUMNS = ("t", "wz")
ENCODERS_COLUMNS = ("t", "module", "steer", "wheel")
SEGMENTS_COLUMNS = ("static_module", "start", "end")


@dataclass(frozen=True)
class Segment:
    """A window ``[start, end]`` (s) of steady spinning about the locked ``static_module``."""

    static_module: int
    start: float
    end: float


@dataclass
class Dataset:
    """One calibration run, in memory.

    ``poses``: (M, 4) rows ``t, x, y, yaw`` sorted by t; (0, 4) without motion capture.
    ``encoders``: dict module id -> (K, 3) rows ``t, steer, wheel`` sorted by t.
    ``imu``: (K, 2) rows ``t, wz`` sorted by t, or None (no ``imu.csv``).
    ``references``: the entries of ``references.yaml`` (empty without the file).
    """

    robot: RobotParams
    poses: FloatArray
    encoders: dict[int, FloatArray]
    segments: list[Segment]
    imu: FloatArray | None = None
    references: list[Reference] = field(default_factory=list)

    @property
    def has_poses(self) -> bool:
        """Motion capture present (the mocap solver's dataset)."""
        return bool(self.poses.shape[0] > 0)

    @property
    def is_imu(self) -> bool:
        """No poses, a gyro: the IMU solver's dataset."""
        return not self.has_poses and self.imu is not None

    def encoder_table(self) -> FloatArray:
        """All encoder rows as (K, 4) ``t, module, steer, wheel``."""
        parts = [
            np.column_stack([e[:, 0], np.full(len(e), float(mid)), e[:, 1], e[:, 2]])
            for mid, e in self.encoders.items()
        ]
        table = np.vstack(parts) if parts else np.zeros((0, 4))
        return table[np.lexsort((table[:, 1], table[:, 0]))]


def _read_csv(path: Path, columns: tuple[str, ...]) -> FloatArray:
    if not path.is_file():
        raise DatasetError(f"{path}: missing file")
    try:
        with path.open(encoding="utf-8") as fh:
            header = fh.readline().strip()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    names = [h.strip() for h in header.split(",")] if header else []
    missing = [c for c in columns if c not in names]
    if missing:
        raise DatasetError(f"{path}: missing column(s) {', '.join(missing)} (header: {header!r})")
    idx = [names.index(c) for c in columns]
    if not _has_data_rows(path):  # before numpy, which warns about an empty file
        raise DatasetError(f"{path}: no data rows (only the header)")
    try:
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=float)
    except ValueError as exc:
        raise DatasetError(f"{path}: unreadable row: {str(exc).splitlines()[0]}") from exc
    if data.shape[1] != len(names):
        raise DatasetError(f"{path}: rows have {data.shape[1]} fields, header has {len(names)}")
    out = data[:, idx]
    bad = ~np.isfinite(out)
    if bad.any():
        row = int(np.argwhere(bad)[0, 0])
        col = columns[int(np.argwhere(bad)[0, 1])]
        raise DatasetError(f"{path}: non-finite value in column {col} at data row {row + 1}")
    return np.asarray(out, dtype=float)


def _has_data_rows(path: Path) -> bool:
    with path.open(encoding="utf-8") as fh:
        fh.readline()
        return any(line.strip() for line in fh)


def check_one_clock(t: FloatArray, path: Path, what: str) -> None:
    """Refuse a time column (in file order) whose clock jumped back into recorded times.

    Rows need not be sorted, so a backward step alone is no error: shuffled rows have
    many, chunks written out of order have steps that land before everything already
    written.  A clock that jumps back has few backward steps, each landing *inside* the
    time span already recorded (by more than 10 sample periods): the rows after it
    overlap earlier ones, and no sorting can separate the two.
    """
    if t.size < 3:
        return
    dt = np.diff(t)
    back = np.flatnonzero(dt < 0)
    if back.size == 0 or back.size > max(3, 0.01 * t.size):
        return
    period = float(np.median(np.abs(dt[dt != 0]))) if np.any(dt != 0) else 0.0
    low = np.minimum.accumulate(t)
    for i in back.tolist():
        if -dt[i] > 10 * period and t[i + 1] > low[i] + 10 * period:
            raise DatasetError(
                f"{path}: {what}: the clock jumps back {-dt[i]:.3f} s at data row {i + 2} "
                f"({t[i + 1]:.6f} s after {t[i]:.6f} s) into times already recorded: "
                "not one monotonic clock"
            )


def load_dataset(directory: str | os.PathLike[str]) -> Dataset:
    """Load and check a dataset directory."""
    d = Path(directory)
    if not d.is_dir():
        raise DatasetError(f"{d}: not a directory")
    try:
        robot = load_robot(d / "robot.yaml")
    except KinematicFileError as exc:
        raise DatasetError(str(exc)) from exc
    imu = None
    if (d / "imu.csv").exists():
        imu = _read_csv(d / "imu.csv", IMU_COLUMNS)
        check_one_clock(imu[:, 0], d / "imu.csv", "t")
        imu = imu[np.argsort(imu[:, 0], kind="stable")]
    if (d / "poses.csv").exists() or imu is None:
        if not (d / "poses.csv").exists():
            raise DatasetError(
                f"{d / 'poses.csv'}: missing file (and no imu.csv: a dataset needs poses.csv "
                "for the motion-capture solver or imu.csv and references.yaml without it)"
            )
        poses = _read_csv(d / "poses.csv", POSES_COLUMNS)
        check_one_clock(poses[:, 0], d / "poses.csv", "t")
        poses = poses[np.argsort(poses[:, 0], kind="stable")]
    else:
        poses = np.zeros((0, 4))
    enc = _read_csv(d / "encoders.csv", ENCODERS_COLUMNS)
    seg = _read_csv(d / "segments.csv", SEGMENTS_COLUMNS)
    ids = set(robot.ids)
    encoders: dict[int, FloatArray] = {}
    mod_col = enc[:, 1]
    unknown = sorted({int(m) for m in np.unique(mod_col)} - ids)
    if unknown:
        raise DatasetError(
            f"{d / 'encoders.csv'}: module id(s) {unknown} not in robot.yaml {sorted(ids)}"
        )
    for mid in robot.ids:
        rows = enc[mod_col == mid]
        if rows.shape[0] == 0:
            raise DatasetError(f"{d / 'encoders.csv'}: no rows for module {mid}")
        check_one_clock(rows[:, 0], d / "encoders.csv", f"t of module {mid}")
        rows = rows[np.argsort(rows[:, 0], kind="stable")]
        encoders[mid] = np.ascontiguousarray(rows[:, [0, 2, 3]])
    segments: list[Segment] = []
    for i, (m, s, e) in enumerate(seg):
        if int(m) != m or int(m) not in ids:
            raise DatasetError(
                f"{d / 'segments.csv'}: row {i + 1}: static_module {m:g} not in robot.yaml"
            )
        if not e > s:
            raise DatasetError(f"{d / 'segments.csv'}: row {i + 1}: end {e} <= start {s}")
        segments.append(Segment(int(m), float(s), float(e)))
    segments.sort(key=lambda g: (g.static_module, g.start))
    refs = load_references(d / "references.yaml", ids) if (d / "references.yaml").exists() else []
    return Dataset(
        robot=robot, poses=poses, encoders=encoders, segments=segments, imu=imu, references=refs
    )


def _csv_text(header: tuple[str, ...], rows: FloatArray, fmts: list[str]) -> str:
    lines = [",".join(header)]
    fmt = ",".join(fmts)
    lines.extend(fmt % tuple(row) for row in rows)
    return "\n".join(lines) + "\n"


def save_dataset(directory: str | os.PathLike[str], ds: Dataset) -> None:
    """Write ``ds`` as a dataset directory (each file written atomically).

    ``poses.csv`` is written when there are poses or no gyro; an IMU dataset
    removes a stale ``poses.csv`` (it would make the directory a motion-capture dataset).
    ``imu.csv`` when there is a gyro, ``references.yaml`` when there are references.
    """
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    save_kinematics(d / "robot.yaml", ds.robot)
    if ds.has_poses or ds.imu is None:
        atomic_write_text(
            d / "poses.csv", _csv_text(POSES_COLUMNS, ds.poses, ["%.6f", "%.9f", "%.9f", "%.9f"])
        )
    else:
        (d / "poses.csv").unlink(missing_ok=True)
    if ds.imu is not None:
        atomic_write_text(d / "imu.csv", _csv_text(IMU_COLUMNS, ds.imu, ["%.6f", "%.10f"]))
    if ds.references:
        save_references(d / "references.yaml", ds.references)
    atomic_write_text(
        d / "encoders.csv",
        _csv_text(ENCODERS_COLUMNS, ds.encoder_table(), ["%.6f", "%d", "%.10f", "%.10f"]),
    )
    seg_rows = np.array([[s.static_module, s.start, s.end] for s in ds.segments], dtype=float)
    atomic_write_text(
        d / "segments.csv",
        _csv_text(SEGMENTS_COLUMNS, seg_rows.reshape(-1, 3), ["%d", "%.6f", "%.6f"]),
    )
