"""Command-line options shared by ``swpc simulate`` and ``swpc sim`` (human units)."""

from __future__ import annotations

from typing import Any


def add_noise_arguments(p: Any) -> None:
    """Mocap noise, dropouts, outliers and wheel slip (mm and degrees on the command line)."""
    p.add_argument("--pose-sigma-xy", type=float, default=0.0, help="pose noise, mm (0)")
    p.add_argument("--pose-sigma-yaw", type=float, default=0.0, help="yaw noise, deg (0)")
    p.add_argument("--dropout", type=float, default=0.0, help="fraction of poses dropped")
    p.add_argument("--outliers", type=float, default=0.0, help="fraction of outlier poses")
    p.add_argument("--outlier-magnitude", type=float, default=50.0, help="outlier jump, mm")
    p.add_argument("--slip-rate", type=float, default=0.0, help="slip bursts /s per wheel")
