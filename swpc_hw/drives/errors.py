"""Exceptions of the drives (every kind), rooted in :class:`CanError` (itself a ``SwpcError``).

Messages name the module, the node and the axis they concern, e.g.
``module 2 (node 2) axis 1 (wheel): ...``.
"""

from __future__ import annotations

from swpc_hw.errors import SwpcError


class CanError(SwpcError):
    """Root of every error the drives raise."""


class CanConfigError(CanError, ValueError):
    """The CAN configuration is invalid (names the key)."""


class CanBusError(CanError):
    """The bus cannot be opened, or a frame cannot be sent."""


class LifecycleError(CanError):
    """The operation is not allowed in the driver's current lifecycle state."""


class CanCommandError(CanError, ValueError):
    """A command cannot be encoded (unknown module, value outside the DBC range, ...)."""


class NodeError(CanError):
    """A controller node is missing, faulted or did not reach a requested state."""

    def __init__(self, message: str, node: int | None = None, axis: int | None = None) -> None:
        super().__init__(message)
        self.node = node
        self.axis = axis


class NodeTimeoutError(NodeError, TimeoutError):
    """A node did not answer or reach a state within the timeout."""
