"""The odometry fed by the CAN driver's feedback frames, as it would run on the robot."""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from swpc_hw.drives.interface import Drives
from swpc_hw.drives.types import AxisSigns, FeedbackSample, turned_sample
from swpc_hw.onboard.odometry import Odometry, OdometryOptions
from swpc_hw.robot.model import RobotParams
from swpc_hw.validation.errors import ValidationError

FloatArray = NDArray[np.float64]


class DriverOdometry:
    """:class:`Odometry` fed by a :class:`~swpc_hw.drives.interface.Drives`'s feedback frames.

    Clock.  A module's sample ``seq`` (the frame counter unwrapped by the driver) counts
    controller periods, so with free-running feedback at ``rate`` Hz its robot time is
    ``t = seq / rate + c_m``.  The offset ``c_m`` maps the module's counter onto the host:
    the smallest ``t_host - seq / rate`` seen so far (a frame can be late, never early),
    with ``t_host`` the frame's bus time stamp on the driver's clock (robot seconds).
    Bursty delivery from a loaded host therefore does not distort the step lengths (the
    robust weights are in m/s).  Without a feedback rate (SYNC mode) the bus time stamps are
    used directly.

    Alignment.  Modules need not sample at the same instants (free-running controllers):
    the odometry integrates at the sample times of the first module, the others linearly
    interpolated there (one sample of delay).  Runs in the driver's receive thread.  The
    track ``(t, x, y, yaw)`` and the slip indicator of each update are kept for the report.
    ``on_update(t, theta_hat, psi)``, when given, receives every aligned reading that was
    integrated (module order of ``params``), in the same thread: e.g. the ROS 2 stream of
    ``swpc odometry`` (:class:`swpc_hw.onboard.ros2.stream.Ros2OdometryStream`).

    Polarity.  ``polarity`` (the robot config's, :data:`~swpc_hw.drives.types.AxisSigns`)
    turns each axis' readings into the model's sense before anything else, as a run's
    readings are turned: the odometry of a robot with a motor mounted the other way round.
    """

    def __init__(
        self,
        driver: Drives,
        params: RobotParams,
        *,
        options: OdometryOptions | None = None,
        on_update: Callable[[float, list[float], list[float]], None] | None = None,
        polarity: AxisSigns | None = None,
    ) -> None:
        self._lock = threading.Lock()
        self._polarity = dict(polarity or {})
        self._on_update = on_update
        self._options = options
        self._odo = Odometry(params, options=options)
        self._ids = tuple(params.ids)
        cfg = driver.config
        self._rate = float(cfg.feedback_rate_hz) if not cfg.sync_mode else 0.0
        self._offset: dict[int, float] = {}
        self._buf: dict[int, deque[tuple[float, float, float]]] = {
            m: deque(maxlen=4096) for m in driver.modules()
        }
        self.track: list[tuple[float, float, float, float]] = []
        self.slip: list[float] = []  # max filtered residual of each update, m/s
        self.updates = 0
        driver.add_feedback_callback(self._on_sample)

    def _clock(self, module: int, s: FeedbackSample) -> float:
        """The sample's counter time ``seq / rate`` (updating the module's offset ``c_m``),
        or its bus time when there is no feedback rate (``c_m = 0``)."""
        t_host = s.t  # the bus stamp on the driver's clock (the driver maps it)
        if self._rate <= 0.0:
            self._offset[module] = 0.0
            return t_host
        t_seq = s.seq / self._rate
        self._offset[module] = min(self._offset.get(module, math.inf), t_host - t_seq)
        return t_seq

    def _on_sample(self, module: int, s: FeedbackSample) -> None:
        s = turned_sample(self._polarity, module, s)
        with self._lock:
            buf = self._buf.get(module)
            if buf is None:
                return
            x = self._clock(module, s)
            if buf and x <= buf[-1][0]:
                x = buf[-1][0] + 1e-9
            buf.append((x, s.theta_hat, s.psi))
            self._drain()

    def _drain(self) -> None:
        """Integrate every reading of the reference module that the others bracket.  Times
        ``x + c_m`` use the current offsets, so samples buffered before an offset settled
        are re-timed consistently."""
        ids = self._ids
        off = self._offset
        ref = self._buf[ids[0]]
        while ref:
            T = ref[0][0] + off.get(ids[0], 0.0)
            th: list[float] = [ref[0][1]]
            ps: list[float] = [ref[0][2]]
            for m in ids[1:]:
                b = self._buf[m]
                c = off.get(m, 0.0)
                if not b or b[-1][0] + c < T:
                    return  # wait for this module's next sample
                while len(b) >= 2 and b[1][0] + c <= T:
                    b.popleft()
                t0, th0, ps0 = b[0]
                t0 += c
                if t0 >= T or len(b) == 1:
                    th.append(th0)
                    ps.append(ps0)
                else:
                    t1, th1, ps1 = b[1]
                    f = (T - t0) / (t1 + c - t0)
                    th.append(th0 + f * (th1 - th0))
                    ps.append(ps0 + f * (ps1 - ps0))
            ref.popleft()
            last = self._odo.t
            if last is not None and last >= T:
                continue
            pose = self._odo.update(T, th, ps)
            self.updates += 1
            self.track.append((T, pose.x, pose.y, pose.yaw))
            step = self._odo.last
            self.slip.append(max(step.filtered_residuals) if step is not None else 0.0)
            if self._on_update is not None:
                self._on_update(T, th, ps)

    def set_params(self, params: RobotParams) -> None:
        """A fresh odometry on other parameters (readings restart; pose kept)."""
        with self._lock:
            if set(params.ids) != set(self._ids):
                raise ValidationError(
                    f"kinematic file has modules {params.ids}, the robot has {list(self._ids)}"
                )
            p = self._odo.pose
            self._odo = Odometry(params, pose=(p.x, p.y, p.yaw), options=self._options)
            self._ids = tuple(params.ids)

    def reset(self, pose: Sequence[float]) -> None:
        with self._lock:
            x, y, yaw = (float(v) for v in pose)
            self._odo.reset((x, y, yaw))

    @property
    def pose(self) -> tuple[float, float, float]:
        with self._lock:
            p = self._odo.pose
            return (p.x, p.y, p.yaw)

    @property
    def t(self) -> float | None:
        """Robot time of the last integrated reading."""
        with self._lock:
            return self._odo.t

    def mark(self) -> int:
        """Index into :attr:`track` / :attr:`slip` now."""
        with self._lock:
            return len(self.track)

    def track_since(self, mark: int) -> FloatArray:
        with self._lock:
            rows = self.track[mark:]
        return np.array(rows, dtype=float).reshape(-1, 4)

    def slip_since(self, mark: int) -> FloatArray:
        with self._lock:
            return np.array(self.slip[mark:], dtype=float)
