"""The robot's odometry as a ROS 2 stream: readings in, ``/odom`` and ``/tf`` messages out.

:class:`Ros2OdometryStream` owns the :class:`~swpc_hw.onboard.odometry.Odometry` on a kinematic
file, the covariances (:mod:`swpc_hw.onboard.ros2.covariance`) and the messages
(:mod:`swpc_hw.onboard.ros2.messages`).  Every reading of all modules (:meth:`update`) is one
odometry step and one message on each topic, handed to a *sink* (the zenoh publisher of
:mod:`swpc_hw.onboard.ros2.publisher`, or a list in a test): the stream publishes at the
odometry's update rate.

Reload.  The stream compares the kinematic file's (mtime, size, inode) with the last
load's (a calibration installs a new file by an atomic rename, which changes the inode).  A
changed file is loaded (the loader's checks: :func:`~swpc_hw.files.kinematic_file.load_kinematics`,
the service's own) and swapped in between two steps, pose and readings kept; a file that
does not load, or describes other modules, is reported once (:attr:`reload_error`, the log)
and the old parameters stay.  A file rewritten in place (its inode kept) is loaded only once
it has not changed for :data:`SETTLE_S`, and a file that changed while it was read is read
again later: a writer's half-written file, which may still parse (a radius cut short), is
never used.  With :meth:`Ros2OdometryStream.watch` the file is looked at and parsed on a
thread of its own and :meth:`~Ros2OdometryStream.update` only swaps in what it loaded (a
1 MiB file takes about a second to parse); without it (a replay, a test) the look is made
before every step.

Drift.  Given :class:`~swpc_hw.onboard.drift.DriftOptions`, the stream feeds every step to a
:class:`~swpc_hw.onboard.drift.DriftMonitor` (the odometry's outputs unchanged); each calibration
suspect raised or cleared is handed to ``on_suspect`` (the caller's log line) and published
on ``/diagnostics`` (:func:`~swpc_hw.onboard.ros2.messages.diagnostic_cdr`: every standing
suspect's evidence).  A reloaded file restarts the monitor: its estimate is of the file's
errors.

Stamps.  Readings carry the odometry's time ``t`` (robot seconds); the messages' header
stamps and rmw_zenoh's source timestamps are ``t + stamp_offset`` (epoch seconds minus
robot seconds, given by the caller from its clock; 0 for a replay).
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

from swpc_hw.clock import Clock
from swpc_hw.errors import SwpcError
from swpc_hw.files.kinematic_file import load_kinematics
from swpc_hw.onboard.drift import DriftMonitor, DriftOptions, SuspectChange
from swpc_hw.onboard.odometry import Odometry, OdometryError, OdometryOptions, file_signature
from swpc_hw.onboard.ros2.covariance import (
    OdometryCovariance,
    contact_points,
    measurement_covariance,
    parameter_covariance,
    ros_covariance,
    twist_sensitivity,
)
from swpc_hw.onboard.ros2.messages import (
    DIAGNOSTIC_ARRAY,
    ODOMETRY,
    TF_MESSAGE,
    PlanarState,
    diagnostic_cdr,
    odometry_cdr,
    tf_cdr,
)
from swpc_hw.robot.frames import BaseLink, to_base_link
from swpc_hw.robot.model import FloatArray, RobotParams

log = logging.getLogger(__name__)

Sink = Callable[[str, str, float, bytes], None]
"""``sink(topic, ros_type, stamp_seconds, cdr_payload)``."""

SETTLE_S = 0.5
"""s (of the readings' time, or the watcher's clock) a kinematic file rewritten in place
must stay unchanged before it is loaded (module docstring)."""
Loaded = tuple[RobotParams, "FloatArray | None"]

ODOM_TOPIC = "/odom"
TF_TOPIC = "/tf"
DIAGNOSTICS_TOPIC = "/diagnostics"


def load_in_base_link(
    path: Path, base_link: BaseLink | None
) -> tuple[RobotParams, FloatArray | None]:
    """A kinematic file's parameters and covariance re-expressed in base_link
    (:func:`swpc_hw.robot.frames.to_base_link`): an odometry on them integrates base_link's own
    motion, so its pose and twist are base_link's (``odom -> base_link``).  Raises
    :class:`~swpc_hw.errors.SwpcError` / ``OSError`` / ``ValueError`` (another frame)."""
    kf = load_kinematics(path)
    return to_base_link(kf.params, kf.covariance, base_link)


def _parameter_covariance(params: RobotParams, covariance: FloatArray | None) -> FloatArray:
    mods = params.modules
    sds = [
        None if m.stddev is None else
        list(m.stddev.values())
        for m in mods
    ]  # fmt: skip
    return parameter_covariance(len(mods), covariance, sds)


class Ros2OdometryStream:
    """Readings -> odometry -> ``/odom`` and ``/tf`` (module docstring)."""

    def __init__(
        self,
        kinematics: str | os.PathLike[str],
        sink: Sink,
        *,
        stamp_offset: float = 0.0,
        options: OdometryOptions | None = None,
        base_link: BaseLink | None = None,
        drift: DriftOptions | None = None,
        on_suspect: Callable[[SuspectChange], None] | None = None,
    ) -> None:
        """``base_link``: the robot config's (:func:`load_in_base_link`; None: base_link is
        the file's frame R).  ``drift``: watch the calibration (module docstring)."""
        self.path = Path(kinematics)
        self.base_link = base_link
        self._sink = sink
        self.stamp_offset = float(stamp_offset)
        self._signature = file_signature(self.path)
        params, cov = load_in_base_link(self.path, base_link)
        self.odometry = Odometry(params, options=options)
        self.covariance = OdometryCovariance(_parameter_covariance(params, cov))
        self.reloads = 0
        self.reload_error: str | None = None
        self.published = 0
        self._prev: tuple[list[float], list[float]] | None = None
        self.drift = DriftMonitor(params, drift) if drift is not None else None
        self._on_suspect = on_suspect
        self._changing: tuple[tuple[int, int, int], float] | None = None
        self._last_t = 0.0
        self._pending: Loaded | None = None
        self._watcher: threading.Thread | None = None
        self._stop = threading.Event()

    @property
    def ids(self) -> tuple[int, ...]:
        """Module ids in the order :meth:`update` expects readings."""
        return self.odometry.ids

    def _load_if_changed(self, now: float) -> Loaded | None:
        """The file's parameters if it changed and may be used at ``now`` (module
        docstring); None otherwise (a file that does not load: :attr:`reload_error`)."""
        sig = file_signature(self.path)
        if sig is None or sig == self._signature:
            self._changing = None
            return None
        if self._signature is not None and sig[2] == self._signature[2]:  # rewritten in place
            if self._changing is None or self._changing[0] != sig:
                self._changing = (sig, now)
                return None
            if now - self._changing[1] < SETTLE_S:
                return None
        self._changing = None
        try:
            params, cov = load_in_base_link(self.path, self.base_link)
            if tuple(m.id for m in params.modules) != self.ids:
                raise OdometryError(
                    f"odometry: {self.path} has module ids {list(params.ids)}, the running "
                    f"robot {list(self.ids)}"
                )
        except (SwpcError, OSError, ValueError) as exc:
            if file_signature(self.path) != sig:
                return None  # it changed while read: judged again at the next look
            self._signature = sig
            self.reload_error = str(exc)
            log.warning("odometry: kept the running parameters: %s", exc)
            return None
        if file_signature(self.path) != sig:
            return None
        self._signature = sig
        return params, cov

    def _apply(self, loaded: Loaded) -> bool:
        params, cov = loaded
        self.odometry.set_params(params)
        self.covariance.set_parameter_covariance(_parameter_covariance(params, cov))
        if self.drift is not None:
            self.drift.restart()
        self.reloads += 1
        self.reload_error = None
        log.info("odometry: reloaded %s", self.path)
        return True

    def reload_if_changed(self, now: float | None = None) -> bool:
        """Load the kinematic file again if it changed (module docstring), now; ``now``:
        the time judged against :data:`SETTLE_S` (default: the last reading's).  True if
        swapped."""
        loaded = self._load_if_changed(self._last_t if now is None else now)
        return loaded is not None and self._apply(loaded)

    def watch(self, clock: Clock, period: float = 0.25) -> None:
        """Look at the kinematic file every ``period`` s of ``clock`` on a thread of its
        own (module docstring) until :meth:`close`."""
        if self._watcher is not None:
            return

        def run() -> None:
            while not self._stop.is_set():
                loaded = self._load_if_changed(clock.now())
                if loaded is not None:
                    self._pending = loaded
                clock.sleep(period)

        self._watcher = threading.Thread(target=run, name="swpc-kinematics-watch", daemon=True)
        self._watcher.start()

    def close(self) -> None:
        """Stop the watcher (idempotent)."""
        self._stop.set()
        if self._watcher is not None:
            self._watcher.join(timeout=5.0)

    def update(self, t: float, theta_hat: Sequence[float], psi: Sequence[float]) -> None:
        """One reading of all modules (module order :attr:`ids`): step, then publish."""
        self._last_t = t
        if self._watcher is None:
            self.reload_if_changed(t)
        else:
            loaded, self._pending = self._pending, None
            if loaded is not None:
                self._apply(loaded)
        odo = self.odometry
        p0 = odo.pose
        odo.update(t, theta_hat, psi)
        th = [float(a) for a in theta_hat]
        ps = [float(a) for a in psi]
        prev, self._prev = self._prev, (th, ps)
        step = odo.last
        if self.drift is not None:
            self._watch(t, self.drift.feed(odo, th, ps))
        if prev is None or step is None or step.t != t:
            return  # the first reading only stores
        rows = odo.rows
        sol = odo._last[2] if odo._last is not None else None
        if sol is not None and len(sol.contacts[0]) == len(rows):
            qx, qy = sol.contacts[0], sol.contacts[1]  # the odometry's, of these readings
        else:
            qx, qy = contact_points(rows, step.dt, prev[0], th, prev[1], ps)
        meas = measurement_covariance(qx, qy, step.weights, step.sigma)
        J = twist_sensitivity(rows, step.dt, prev[0], th, prev[1], ps, step.weights)
        p1 = odo.pose
        self.covariance.step((p0.x, p0.y, p0.yaw), (p1.x, p1.y, p1.yaw), step.dt, meas, J)
        vx, vy, om = step.twist
        s = PlanarState(p1.x, p1.y, p1.yaw, vx, vy, om)  # base_link's: load_in_base_link
        stamp = t + self.stamp_offset
        self._sink(ODOM_TOPIC, ODOMETRY, stamp, odometry_cdr(
            stamp, s, ros_covariance(self.covariance.pose), ros_covariance(self.covariance.twist)
        ))  # fmt: skip
        self._sink(TF_TOPIC, TF_MESSAGE, stamp, tf_cdr(stamp, s))
        self.published += 1


    def _watch(self, t: float, changes: list[SuspectChange]) -> None:
        if not changes or self.drift is None:
            return
        for c in changes:
            if self._on_suspect is not None:
                self._on_suspect(c)
        stamp = t + self.stamp_offset
        evidence = [s.fields() for s in self.drift.suspects.values()]
        self._sink(DIAGNOSTICS_TOPIC, DIAGNOSTIC_ARRAY, stamp, diagnostic_cdr(stamp, evidence))


__all__ = ["DIAGNOSTICS_TOPIC", "ODOM_TOPIC", "TF_TOPIC", "Ros2OdometryStream", "Sink"]
