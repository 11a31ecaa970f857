"""Validation results: per run, and the Table-5-like report with its Figure-13-like plot."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from swpc_hw.onboard.square_path import Direction, SquareOptions
from swpc_hw.robot.model import wrap_angle

FloatArray = NDArray[np.float64]


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

    def reduction(self, label: str | None = None) -> dict[str, float] | None:
        """``1 - mean error(label) / mean error(first label)`` for position and heading
        (``label``: the last file by default); None with a single file."""
        if len(self.labels) < 2:
            return None
        s = self.summary()
        ref, new = s[self.labels[0]]["all"], s[label or self.labels[-1]]["all"]
        return {k: 1.0 - new[k] / ref[k] if ref[k] > 0 else math.nan
                for k in ("position", "heading")}

    def reductions(self) -> dict[str, dict[str, float]]:
        """:meth:`reduction` of every file but the reference (the first)."""
        out: dict[str, dict[str, float]] = {}
        for label in self.labels[1:]:
            red = self.reduction(label)
            if red is not None:
                out[label] = red
        return out

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
        reds = self.reductions()
        if reds:
            lines.append("-" * len(head))
        for label, red in reds.items():
            lines.append(
                f"{'reduction':<12}{label + ' vs ' + self.labels[0]:<16}"
                f"{red['position'] * 100:>12.1f} %{red['heading'] * 100:>14.1f} %"
            )
        return "\n".join(lines)

    def to_document(self) -> dict[str, Any]:
        return {
            "labels": self.labels,
            "files": self.files,
            "options": asdict(self.options),
            "summary": self.summary(),
            "reduction": self.reduction(),
            "reductions": self.reductions(),
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
