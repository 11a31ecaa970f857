"""Supervision: which nodes are lost, which commands to re-send (a pure core).

:func:`check` is a function of the tracked nodes and a time ``now``: no clock, no lock,
no I/O.  The driver calls it right after it has drained its receive queue, with a
``now`` taken *before* the queue was found empty, so every heartbeat that arrived by
``now`` has been applied and loss is judged on the heartbeats' bus times, not on when a
thread got round to the check::

    lost(n)    <=>  now >= (t_heartbeat(n) or t_configured) + loss_after
    refresh(n) <=>  active and host refresh and commanded(n) and now - last_tx(n) >= T_refresh

``loss_after = heartbeat_loss_periods * heartbeat_period``.  A node is reported lost once
(until its heartbeat is back).  The returned deadline is when the next check is due.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from firmware_protocol import codec
from firmware_protocol.codec import Axis, ControlMode
from swpc_hw.can.node_tracking import NodeTrack


@dataclass
class CheckResult:
    lost: list[NodeTrack] = field(default_factory=list)
    refresh: list[codec.Frame] = field(default_factory=list)
    next_deadline: float = math.inf


def refresh_frames(
    nd: NodeTrack, commanded: Mapping[Axis, tuple[ControlMode, float]] | None = None
) -> list[codec.Frame]:
    """The node's last SetControl per commanded axis (what feeds its watchdog); of
    ``commanded`` instead of the node's own, if given."""
    cmds = nd.commanded if commanded is None else commanded
    return [codec.make_set_control(nd.node, axis, mode, sp) for axis, (mode, sp) in cmds.items()]


def check(
    nodes: Iterable[NodeTrack],
    now: float,
    *,
    t_configured: float,
    loss_after: float,
    refresh_period: float,
    refresh: bool,
) -> CheckResult:
    """Heartbeat loss and host-side watchdog refresh at ``now`` (module docstring).

    ``refresh``: the driver is ACTIVE and refreshes from the host (not through the
    kernel's broadcast manager).  Lost nodes are marked (``alive = False``).
    """
    out = CheckResult()
    for nd in nodes:
        due = (nd.t_heartbeat if nd.t_heartbeat is not None else t_configured) + loss_after
        if now >= due:
            if nd.alive or not nd.lost_reported:
                nd.alive = False
                nd.lost_reported = True
                out.lost.append(nd)
        else:
            out.next_deadline = min(out.next_deadline, due)
        if refresh and nd.commanded:
            if now - nd.last_tx >= refresh_period:
                out.refresh += refresh_frames(nd)
                out.next_deadline = min(out.next_deadline, now + refresh_period)
            else:
                out.next_deadline = min(out.next_deadline, nd.last_tx + refresh_period)
    if out.lost:
        out.refresh = []  # a fault: the motors stop, nothing is refreshed
    return out
