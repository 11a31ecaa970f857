"""The square-path validation drive's error type."""

from __future__ import annotations

from swpc_hw.errors import SwpcError


class ValidationError(SwpcError, RuntimeError):
    """The validation drive could not run or complete (fault, no truth, timeout)."""
