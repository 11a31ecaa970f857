"""Square-path validation drive: the seed's odometry test (paper Table 5, Figure 13).

The robot drives a square of side ``L`` (default 2.5 m) with a 90 deg turn in place at each
corner, clockwise and counter-clockwise, ``runs`` times each, at about 0.2 m/s, with one
kinematic file used for *both* control (:class:`swpc_hw.twist_controller.TwistController`) and
odometry (:class:`swpc_hw.odometry.Odometry`); the end pose of the odometry is compared
with the true end pose (simulator truth key, or motion capture on a real robot).  Doing
this for the nominal and the calibrated file shows what calibration buys.

Everything goes through CAN exactly as on the robot:

* commands: per module, steering VELOCITY ``theta_hat_dot`` and wheel VELOCITY ``psi_dot``
  from the inverse kinematics of the commanded body twist at the reported steering
  (:meth:`TwistController.command`), refreshed at ``control_rate`` Hz of robot time (the
  driver itself keeps the controllers' watchdog fed);
* odometry: :class:`DriverOdometry` consumes the driver's feedback frames (``theta_hat``,
  ``psi`` per module, timed by the frames' bus timestamps like
  :mod:`services.robot_io`), one update per feedback cycle of all modules;
* truth: :class:`ZenohTruth` on the simulator's ``sim/<robot>/truth/pose`` (JSON) or on
  the motion-capture pose key ``mocap/<robot>/pose`` (:func:`swpc_hw.mocap.decode_pose`),
  averaged over a still window at the start and end of every run.

Path following happens in the odometry frame (the robot believes its odometry, as it would
in use).  Odometry is reset to the true start pose at the start of every run, so the errors
of one run are ``e_p = |p_odo,end - p_true,end|`` and
``e_yaw = |wrap(yaw_odo,end - yaw_true,end)|``; the report gives their means per file and
direction (mean absolute errors, as the paper).

Follower (per control step of ``dt`` robot seconds, world frame = odometry frame):

* line ``A -> B`` with heading ``h``: along-track remaining distance ``s_r = (B - p) . d``,
  lateral offset ``e_l = (p - A) . n`` (``d = (B - A)/|B - A|``, ``n = z x d``);
  speed target ``sign(s_r) min(v_max, sqrt(2 a |s_r|), k_p |s_r|)``, slew-limited by
  ``a dt``; world velocity ``s d - k_l e_l n``, yaw rate ``k_h wrap(h - yaw)``;
* turn in place to yaw ``h``: ``e = h - yaw``, yaw-rate target
  ``sign(e) min(w_max, sqrt(2 alpha |e|), k_p |e|)`` slew-limited by ``alpha dt``; the
  position is held with ``-k_l (p - corner)``;
* body twist ``v_R = R(-yaw) v_W``; the controller scales the whole twist down if a wheel
  or steering rate limit would be exceeded (re-orienting casters), and the follower's
  speed memory takes the applied (scaled) value.

Imports numpy and the CAN driver; zenoh only through a session object that the caller
opens; matplotlib only inside :meth:`ValidationReport.plot`.
"""

from __future__ import annotations

import contextlib
import json
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from firmware_protocol.codec import Axis
from swpc_hw.can import CanDriver, DriverEvent, FeedbackSample, Lifecycle, Severity
from swpc_hw.errors import SwpcError
from swpc_hw.model import RobotParams, wrap_angle
from swpc_hw.odometry import Odometry, OdometryOptions
from swpc_hw.twist_controller import TwistController

FloatArray = NDArray[np.float64]
Direction = Literal["cw", "ccw"]


class ValidationError(SwpcError, RuntimeError):
    """The validation drive could not run or complete (fault, no truth, timeout)."""


# --------------------------------------------------------------------------- options


@dataclass(frozen=True)
class SquareOptions:
    """The test (SI units, robot time)."""

    side: float = 2.5  # m
    speed: float = 0.2  # m/s along the legs
    accel: float = 0.2  # m/s^2
    yaw_rate: float = 0.3  # rad/s at the corners
    yaw_accel: float = 0.4  # rad/s^2
    runs: int = 4  # per direction and file
    directions: tuple[Direction, ...] = ("cw", "ccw")
    control_rate: float = 25.0  # Hz of robot time
    k_position: float = 2.5  # 1/s, final approach along the leg / to the target yaw
    k_lateral: float = 1.0  # 1/s, cross-track and corner hold
    k_heading: float = 1.5  # 1/s, heading hold on the legs
    position_tol: float = 3e-3  # m, leg done
    yaw_tol: float = 2e-3  # rad, turn done
    settle: float = 0.6  # s still before and after each run (truth averaged over it)
    max_wheel_rate: float | None = 16.0  # rad/s (controller scales the twist)
    max_steer_rate: float | None = 0.8  # rad/s
    lead_time: float | None = None
    """s, steering prediction of the inverse kinematics (default: half a control period
    plus 5 ms of feedback age and command delay)."""

    def __post_init__(self) -> None:
        if not (self.side > 0 and self.speed > 0 and self.accel > 0 and self.yaw_rate > 0
                and self.yaw_accel > 0 and self.control_rate > 0 and self.settle > 0):
            raise ValueError("square options: side, speeds, accelerations, rates must be > 0")
        if self.runs < 1:
            raise ValueError("square options: runs must be >= 1")
        bad = [d for d in self.directions if d not in ("cw", "ccw")]
        if bad or not self.directions:
            raise ValueError(f"square options: directions must be cw and/or ccw (got {bad})")


# --------------------------------------------------------------------------- path


@dataclass(frozen=True)
class Leg:
    """One piece of the path in the odometry frame: a straight line or a turn in place."""

    kind: Literal["line", "turn"]
    start: tuple[float, float]
    end: tuple[float, float]
    yaw: float  # heading held on a line; target (continuous) yaw of a turn


def square_plan(pose: Sequence[float], side: float, direction: Direction) -> list[Leg]:
    """The square from ``pose = (x, y, yaw)``: 4 x (line of ``side`` ahead, turn of +-90 deg).

    Counter-clockwise (``ccw``) turns left (+pi/2), clockwise right; the path ends at the
    start point with yaw ``yaw +- 2 pi`` (continuous).
    """
    x, y, h = (float(v) for v in pose)
    sgn = 1.0 if direction == "ccw" else -1.0
    legs: list[Leg] = []
    p = (x, y)
    for _ in range(4):
        q = (p[0] + side * math.cos(h), p[1] + side * math.sin(h))
        legs.append(Leg("line", p, q, h))
        h_new = h + sgn * math.pi / 2.0
        legs.append(Leg("turn", q, q, h_new))
        p, h = q, h_new
    return legs


def _profile(err: float, vmax: float, acc: float, k: float) -> float:
    """``sign(err) min(vmax, sqrt(2 0.8 acc |err|), k |err|)``: stop at ``err = 0``.

    The braking curve uses 80 % of the acceleration limit, so that the slew limit never
    binds while braking and the discrete loop does not overshoot (no reversal at the end
    of a leg, which would swing the casters round)."""
    a = abs(err)
    return math.copysign(min(vmax, math.sqrt(1.6 * acc * a), k * a), err)


def _slew(target: float, prev: float, step: float) -> float:
    return min(prev + step, max(prev - step, target))


def _clip_norm(vx: float, vy: float, limit: float) -> tuple[float, float]:
    n = math.hypot(vx, vy)
    if n > limit:
        return vx * limit / n, vy * limit / n
    return vx, vy


def follow_step(
    leg: Leg, pose: Sequence[float], speed: float, dt: float, opt: SquareOptions
) -> tuple[tuple[float, float, float], float, bool]:
    """One control step of the follower (module docstring).

    ``speed`` is the follower's memory (signed leg speed, or yaw rate on a turn) from the
    previous step.  Returns the body twist ``(v_x, v_y, omega)``, the new memory and whether
    the leg is done (then the twist is zero).
    """
    x, y, yaw = (float(v) for v in pose)
    if leg.kind == "line":
        ax, ay = leg.start
        bx, by = leg.end
        length = math.hypot(bx - ax, by - ay)
        dx, dy = (bx - ax) / length, (by - ay) / length
        rem = (bx - x) * dx + (by - y) * dy
        lat = (x - ax) * -dy + (y - ay) * dx
        if abs(rem) < opt.position_tol and abs(speed) <= 2.0 * opt.accel * dt:
            return (0.0, 0.0, 0.0), 0.0, True
        s = _slew(_profile(rem, opt.speed, opt.accel, opt.k_position), speed, opt.accel * dt)
        cx, cy = _clip_norm(-opt.k_lateral * lat * -dy, -opt.k_lateral * lat * dx, 0.05)
        vwx, vwy = s * dx + cx, s * dy + cy
        om = max(-opt.yaw_rate, min(opt.yaw_rate, opt.k_heading * float(wrap_angle(leg.yaw - yaw))))
        new = s
    else:
        e = leg.yaw - yaw
        if abs(e) < opt.yaw_tol and abs(speed) <= 2.0 * opt.yaw_accel * dt:
            return (0.0, 0.0, 0.0), 0.0, True
        om = _slew(_profile(e, opt.yaw_rate, opt.yaw_accel, opt.k_position), speed,
                   opt.yaw_accel * dt)
        cx_, cy_ = leg.start
        vwx, vwy = _clip_norm(-opt.k_lateral * (x - cx_), -opt.k_lateral * (y - cy_), 0.05)
        new = om
    c, s_ = math.cos(yaw), math.sin(yaw)
    return (c * vwx + s_ * vwy, -s_ * vwx + c * vwy, om), new, False


# --------------------------------------------------------------------------- odometry feed


class DriverOdometry:
    """:class:`Odometry` fed by a :class:`CanDriver`'s feedback frames.

    Clock.  A module's sample ``seq`` (the frame counter unwrapped by the driver) counts
    controller periods, so with free-running feedback at ``rate`` Hz its robot time is
    ``t = seq / rate + c_m``.  The offset ``c_m`` maps the module's counter onto the host:
    the smallest ``t_host - seq / rate`` seen so far (a frame can be late, never early),
    with ``t_host`` the frame's bus timestamp on the monotonic clock times ``time_scale``
    (robot seconds against a time-scaled simulator).  Bursty delivery from a loaded host
    therefore does not distort the step lengths (the robust weights are in m/s).  Without
    a feedback rate (SYNC mode) the bus timestamps are used directly.

    Alignment.  Modules need not sample at the same instants (free-running controllers):
    the odometry integrates at the sample times of the first module, the others linearly
    interpolated there (one sample of delay).  Runs in the driver's receive thread.  The
    track ``(t, x, y, yaw)`` and the slip indicator of each update are kept for the report.
    """

    def __init__(
        self,
        driver: CanDriver,
        params: RobotParams,
        *,
        time_scale: float = 1.0,
        options: OdometryOptions | None = None,
    ) -> None:
        self._lock = threading.Lock()
        self._options = options
        self._odo = Odometry(params, options=options)
        self._ids = tuple(params.ids)
        cfg = driver.config
        self._rate = float(cfg.feedback_rate_hz) if not cfg.sync_mode else 0.0
        self._offset: dict[int, float] = {}
        self._buf: dict[int, deque[tuple[float, float, float]]] = {
            m: deque(maxlen=4096) for m in driver.modules()
        }
        self.time_scale = float(time_scale)
        self._wall_minus_mono = time.time() - time.monotonic()
        self.track: list[tuple[float, float, float, float]] = []
        self.slip: list[float] = []  # max filtered residual of each update, m/s
        self.updates = 0
        driver.add_feedback_callback(self._on_sample)

    def _clock(self, module: int, s: FeedbackSample) -> float:
        """The sample's counter time ``seq / rate`` (updating the module's offset ``c_m``),
        or its host time when there is no feedback rate (``c_m = 0``)."""
        t_host = s.t_bus - self._wall_minus_mono
        if not math.isfinite(t_host) or abs(t_host - s.t) > 5.0:
            t_host = s.t
        t_host *= self.time_scale
        if self._rate <= 0.0:
            self._offset[module] = 0.0
            return t_host
        t_seq = s.seq / self._rate
        self._offset[module] = min(self._offset.get(module, math.inf), t_host - t_seq)
        return t_seq

    def _on_sample(self, module: int, s: FeedbackSample) -> None:
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


# --------------------------------------------------------------------------- truth


def sim_truth_decoder(payload: bytes) -> tuple[float, float, float, float]:
    """``(t, x, y, yaw)`` of a simulator truth document (``sim/<robot>/truth/pose``)."""
    doc = json.loads(payload)
    x, y, yaw = (float(v) for v in doc["pose"])
    return float(doc["t"]), x, y, yaw


def mocap_decoder(payload: bytes) -> tuple[float, float, float, float]:
    """``(t, x, y, yaw)`` of a motion-capture pose (native or ROS 2 CDR)."""
    from swpc_hw.mocap import decode_pose

    p = decode_pose(payload)
    return float(p.t), float(p.x), float(p.y), float(p.yaw)


class ZenohTruth:
    """The true pose from a zenoh key: rows ``(t_host, t_source, x, y, yaw)``."""

    def __init__(
        self,
        session: Any,
        key: str,
        decode: Callable[[bytes], tuple[float, float, float, float]] = sim_truth_decoder,
        maxlen: int = 1_000_000,
    ) -> None:
        self.key = key
        self._decode = decode
        self._rows: deque[tuple[float, float, float, float, float]] = deque(maxlen=maxlen)
        self._cond = threading.Condition()
        self.errors = 0
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            t, x, y, yaw = self._decode(bytes(sample.payload.to_bytes()))
        except Exception:  # a bad sample is counted, never fatal
            self.errors += 1
            return
        with self._cond:
            self._rows.append((time.monotonic(), t, x, y, yaw))
            self._cond.notify_all()

    def close(self) -> None:
        with contextlib.suppress(Exception):  # closing twice / session gone
            self._sub.undeclare()

    def wait_first(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        with self._cond:
            while not self._rows:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise ValidationError(f"no true pose on {self.key!r} within {timeout} s")
                self._cond.wait(left)

    def since(self, t_host: float) -> FloatArray:
        """Rows received at host time >= ``t_host`` (K, 5)."""
        with self._cond:
            rows = [r for r in self._rows if r[0] >= t_host]
        return np.array(rows, dtype=float).reshape(-1, 5)

    def mean_pose(self, t_host: float) -> tuple[float, float, float]:
        """Mean pose of the rows received since ``t_host`` (the robot is still)."""
        rows = self.since(t_host)
        if rows.shape[0] == 0:
            raise ValidationError(f"no true pose on {self.key!r} in the still window")
        yaw = np.unwrap(rows[:, 4])
        return (float(rows[:, 2].mean()), float(rows[:, 3].mean()), float(yaw.mean()))


# --------------------------------------------------------------------------- results


@dataclass
class RunResult:
    """One square: true and odometry end poses, errors, and both paths (start frame)."""

    label: str
    direction: Direction
    run: int
    start: tuple[float, float, float]  # true (= odometry) start pose, W
    end_true: tuple[float, float, float]
    end_odometry: tuple[float, float, float]
    duration: float  # robot s
    true_path: FloatArray = field(repr=False)  # (K, 2) in the start frame
    odometry_path: FloatArray = field(repr=False)
    max_slip: float = 0.0  # largest filtered module residual (m/s), the slip indicator

    @property
    def position_error(self) -> float:
        return math.hypot(self.end_odometry[0] - self.end_true[0],
                          self.end_odometry[1] - self.end_true[1])

    @property
    def heading_error(self) -> float:
        return abs(float(wrap_angle(self.end_odometry[2] - self.end_true[2])))

    def to_dict(self) -> dict[str, Any]:
        return {
            "label": self.label, "direction": self.direction, "run": self.run,
            "start": list(self.start), "end_true": list(self.end_true),
            "end_odometry": list(self.end_odometry), "duration": self.duration,
            "position_error": self.position_error, "heading_error": self.heading_error,
            "max_slip": self.max_slip,
        }


def to_start_frame(start: Sequence[float], xy: FloatArray) -> FloatArray:
    """Points of W expressed in the frame of ``start = (x, y, yaw)``: ``R(-yaw)(p - p0)``."""
    x0, y0, h = (float(v) for v in start)
    c, s = math.cos(h), math.sin(h)
    d = np.asarray(xy, dtype=float).reshape(-1, 2) - np.array([x0, y0])
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])


@dataclass
class ValidationReport:
    """All runs; ``labels`` in report order (the reference first: nominal, then calibrated)."""

    labels: list[str]
    results: list[RunResult]
    options: SquareOptions
    files: dict[str, str] = field(default_factory=dict)

    def summary(self) -> dict[str, dict[str, dict[str, float]]]:
        """``{label: {direction or "all": {position, heading, runs}}}`` (mean absolute)."""
        out: dict[str, dict[str, dict[str, float]]] = {}
        for label in self.labels:
            mine = [r for r in self.results if r.label == label]
            groups: dict[str, list[RunResult]] = {
                d: [r for r in mine if r.direction == d] for d in self.options.directions
            }
            groups["all"] = mine
            out[label] = {
                g: {
                    "position": float(np.mean([r.position_error for r in rs])) if rs else math.nan,
                    "heading": float(np.mean([r.heading_error for r in rs])) if rs else math.nan,
                    "runs": float(len(rs)),
                }
                for g, rs in groups.items()
            }
        return out

    def reduction(self) -> dict[str, float] | None:
        """``1 - mean error(last label) / mean error(first label)`` for position and heading."""
        if len(self.labels) < 2:
            return None
        s = self.summary()
        ref, new = s[self.labels[0]]["all"], s[self.labels[-1]]["all"]
        return {k: 1.0 - new[k] / ref[k] if ref[k] > 0 else math.nan
                for k in ("position", "heading")}

    def table(self) -> str:
        """The Table-5-like comparison (mm and degrees)."""
        s = self.summary()
        groups = [*self.options.directions, "all"]
        head = f"{'file':<12}{'direction':<11}{'runs':>5}{'position error':>17}" \
               f"{'heading error':>16}"
        lines = [head, "-" * len(head)]
        for label in self.labels:
            for g in groups:
                v = s[label][g]
                lines.append(
                    f"{label:<12}{g.upper() if g != 'all' else 'mean':<11}{int(v['runs']):>5}"
                    f"{v['position'] * 1e3:>14.2f} mm{math.degrees(v['heading']):>12.3f} deg"
                )
        red = self.reduction()
        if red is not None:
            lines.append("-" * len(head))
            lines.append(
                f"{'reduction':<12}{self.labels[-1] + ' vs ' + self.labels[0]:<16}"
                f"{red['position'] * 100:>12.1f} %{red['heading'] * 100:>14.1f} %"
            )
        return "\n".join(lines)

    def to_document(self) -> dict[str, Any]:
        from dataclasses import asdict

        return {
            "labels": self.labels,
            "files": self.files,
            "options": asdict(self.options),
            "summary": self.summary(),
            "reduction": self.reduction(),
            "runs": [r.to_dict() for r in self.results],
        }

    def plot(self, path: str) -> None:
        """PNG like the paper's Figure 13: true (solid) and odometry (dashed) paths of every
        run, in its start frame; one panel per file and direction."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        dirs = list(self.options.directions)
        fig, axes = plt.subplots(len(dirs), len(self.labels),
                                 figsize=(5.2 * len(self.labels), 5.0 * len(dirs)),
                                 squeeze=False)
        colors = plt.get_cmap("tab10")
        summ = self.summary()
        for i, d in enumerate(dirs):
            for j, label in enumerate(self.labels):
                ax = axes[i][j]
                runs = [r for r in self.results if r.label == label and r.direction == d]
                for r in runs:
                    c = colors(r.run % 10)
                    ax.plot(r.true_path[:, 0], r.true_path[:, 1], "-", color=c, lw=1.2,
                            label=f"run {r.run + 1} true")
                    ax.plot(r.odometry_path[:, 0], r.odometry_path[:, 1], "--", color=c,
                            lw=1.0, label=f"run {r.run + 1} odometry")
                    ax.plot(r.true_path[-1:, 0], r.true_path[-1:, 1], "o", color=c, ms=4)
                    ax.plot(r.odometry_path[-1:, 0], r.odometry_path[-1:, 1], "x", color=c,
                            ms=6)
                v = summ[label][d]
                ax.set_title(f"{label}, {d.upper()}: end error {v['position'] * 1e3:.1f} mm, "
                             f"{math.degrees(v['heading']):.2f} deg", fontsize=10)
                ax.set_aspect("equal")
                ax.grid(True, lw=0.3)
                ax.set_xlabel("x (m, start frame)")
                ax.set_ylabel("y (m)")
                if i == 0 and j == 0:
                    ax.legend(fontsize=7, loc="center")
        fig.suptitle(f"{self.options.side:g} m square, true (solid) vs odometry (dashed)")
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)


# --------------------------------------------------------------------------- the drive


class SquareDrive:
    """Drives squares through a :class:`CanDriver` (activated, homed) and measures them.

    ``time_scale``: robot seconds per host second (a time-scaled simulator; 1 on a robot).
    """

    def __init__(
        self,
        driver: CanDriver,
        truth: ZenohTruth,
        params: RobotParams,
        options: SquareOptions | None = None,
        *,
        time_scale: float = 1.0,
        odometry_options: OdometryOptions | None = None,
        log: Callable[[str], None] | None = None,
    ) -> None:
        self.driver = driver
        self.truth = truth
        self.options = opt = options or SquareOptions()
        self.time_scale = float(time_scale)
        self.controller = TwistController(
            params, max_wheel_rate=opt.max_wheel_rate, max_steer_rate=opt.max_steer_rate
        )
        self.odometry = DriverOdometry(
            driver, params, time_scale=time_scale, options=odometry_options
        )
        self._faults: list[str] = []
        self._flock = threading.Lock()
        driver.add_event_callback(self._on_event)
        self._log = log or (lambda _msg: None)

    def _on_event(self, ev: DriverEvent) -> None:
        if ev.severity is Severity.FAULT:
            with self._flock:
                self._faults.append(ev.message)

    def _check(self) -> None:
        with self._flock:
            faults = list(self._faults)
        if faults:
            raise ValidationError(f"driver fault: {faults[0]}")
        if self.driver.state is not Lifecycle.ACTIVE:
            raise ValidationError(f"driver is {self.driver.state.value}, not active")
        if self.driver.last_exception is not None:
            raise ValidationError(f"driver error: {self.driver.last_exception}")

    # ------------------------------------------------------------------ low level
    def set_params(self, params: RobotParams) -> None:
        """Use another kinematic file for control and odometry."""
        self.controller = TwistController(
            params, max_wheel_rate=self.options.max_wheel_rate,
            max_steer_rate=self.options.max_steer_rate,
        )
        self.odometry.set_params(params)

    def _command(self, twist: Sequence[float]) -> tuple[float, float, float]:
        """Send the rates realising ``twist``; returns the applied (rate-limited) twist.

        The inverse kinematics is evaluated at the steering predicted for the middle of the
        interval the command will act over, ``theta_hat + theta_hat_dot * lead`` (reported
        steering rate of the feedback, ``lead = lead_time``): commands stay consistent
        with the no-slip model while the casters re-orient (to second order in the step).
        """
        ids = self.controller.params.ids
        opt = self.options
        lead = opt.lead_time if opt.lead_time is not None else 0.5 / opt.control_rate + 0.005
        th = []
        for m in ids:
            fb = self.driver.module_state(m).feedback
            if fb is None:
                raise ValidationError(f"module {m}: no feedback")
            rate = fb.steer_velocity if math.isfinite(fb.steer_velocity) else 0.0
            th.append(fb.theta_hat + rate * lead)
        cmd = self.controller.command(th, twist)
        for i, m in enumerate(ids):
            self.driver.set_velocity(m, Axis.STEER, float(cmd.theta_hat_dot[i]))
            self.driver.set_velocity(m, Axis.WHEEL, float(cmd.psi_dot[i]))
        return cmd.twist

    def stand_still(self, duration: float) -> None:
        """Zero twist for ``duration`` robot seconds."""
        self._command((0.0, 0.0, 0.0))
        end = time.monotonic() + duration / self.time_scale
        while time.monotonic() < end:
            self._check()
            time.sleep(min(0.02, max(0.0, end - time.monotonic())))

    def _robot_now(self) -> float:
        """Robot time of the latest odometry reading (host time x scale before any)."""
        t = self.odometry.t
        return t if t is not None else time.monotonic() * self.time_scale

    def _pace(self) -> Iterator[None]:
        """Yield once per control period (``1 / (control_rate * time_scale)`` host s)."""
        period = 1.0 / (self.options.control_rate * self.time_scale)
        nxt = time.monotonic()
        while True:
            yield
            nxt += period
            wait = nxt - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            elif wait < -period:
                nxt = time.monotonic()

    def follow(self, legs: Sequence[Leg]) -> float:
        """Drive the legs (odometry frame); returns the robot time taken."""
        opt = self.options
        t_start = self._robot_now()
        for leg in legs:
            if leg.kind == "line":
                limit = 3.0 * math.dist(leg.start, leg.end) / opt.speed + 30.0
            else:
                turn = abs(leg.yaw - self.odometry.pose[2])
                limit = 3.0 * turn / opt.yaw_rate + 30.0
            t_leg = t_prev = self._robot_now()
            memory = 0.0
            for _ in self._pace():
                self._check()
                now = self._robot_now()
                dt, t_prev = min(max(now - t_prev, 0.0), 5.0 / opt.control_rate), now
                twist, memory, done = follow_step(leg, self.odometry.pose, memory, dt, opt)
                applied = self._command(twist)
                if done:
                    break
                if leg.kind == "line":
                    if abs(twist[0]) + abs(twist[1]) > 1e-12:
                        k = math.hypot(*applied[:2]) / math.hypot(*twist[:2])
                        memory *= min(1.0, k)
                elif abs(twist[2]) > 1e-12:
                    memory *= min(1.0, abs(applied[2] / twist[2]))
                if now - t_leg > limit:
                    raise ValidationError(
                        f"{leg.kind} leg not completed within {limit:.0f} s (robot time)"
                    )
        self._command((0.0, 0.0, 0.0))
        return self._robot_now() - t_start

    # ------------------------------------------------------------------ one square
    def run_square(self, label: str, direction: Direction, run: int) -> RunResult:
        opt = self.options
        self.stand_still(opt.settle / 2)
        w0 = time.monotonic()
        self.stand_still(opt.settle)
        start = self.truth.mean_pose(w0)
        self.odometry.reset(start)
        mark = self.odometry.mark()
        t_path = time.monotonic()
        legs = square_plan(start, opt.side, direction)
        duration = self.follow(legs)
        self.stand_still(opt.settle / 2)
        w1 = time.monotonic()
        self.stand_still(opt.settle)
        end_true = self.truth.mean_pose(w1)
        end_odo = self.odometry.pose
        tr = self.truth.since(t_path)
        od = self.odometry.track_since(mark)
        slip = self.odometry.slip_since(mark)
        res = RunResult(
            label=label, direction=direction, run=run, start=start, end_true=end_true,
            end_odometry=end_odo, duration=duration,
            true_path=to_start_frame(start, tr[:, 2:4]),
            odometry_path=to_start_frame(start, od[:, 1:3]),
            max_slip=float(slip.max()) if slip.size else 0.0,
        )
        self._log(
            f"{label:<11} {direction.upper():<4} run {run + 1}: end error "
            f"{res.position_error * 1e3:8.2f} mm {math.degrees(res.heading_error):7.3f} deg "
            f"({duration:.0f} s, max slip indicator {res.max_slip * 1e3:.1f} mm/s)"
        )
        return res


def validate(
    drive: SquareDrive, files: Sequence[tuple[str, RobotParams]]
) -> ValidationReport:
    """Every file x direction x run on ``drive`` (stop_all on any error)."""
    opt = drive.options
    results: list[RunResult] = []
    try:
        for label, params in files:
            drive.set_params(params)
            for direction in opt.directions:
                for k in range(opt.runs):
                    results.append(drive.run_square(label, direction, k))
    finally:
        drive.driver.stop_all()
    return ValidationReport(labels=[lab for lab, _ in files], results=results, options=opt)


def prepare_driver(driver: CanDriver, timeout: float = 10.0) -> None:
    """Activate (if needed), clear errors, enable both axes and home unhomed steering."""
    if driver.state is not Lifecycle.ACTIVE:
        driver.activate()
    for m in driver.modules():
        driver.clear_errors(m)
        driver.enable(m, Axis.STEER)
        driver.enable(m, Axis.WHEEL)
    for m in driver.modules():
        if not driver.module_state(m).homed:
            driver.start_homing(m)
    for m in driver.modules():
        driver.wait_for(m, lambda s: s.homed and s.feedback is not None, timeout, "homed")


__all__ = [
    "DriverOdometry",
    "Leg",
    "RunResult",
    "SquareDrive",
    "SquareOptions",
    "ValidationError",
    "ValidationReport",
    "ZenohTruth",
    "follow_step",
    "mocap_decoder",
    "prepare_driver",
    "sim_truth_decoder",
    "square_plan",
    "to_start_frame",
    "validate",
]
