"""Exception hierarchy: every error the library raises derives from :class:`SwpcError`."""

from __future__ import annotations


class SwpcError(Exception):
    """Root of all swpc errors."""


class KinematicFileError(SwpcError, ValueError):
    """A kinematic file is missing, malformed or fails validation.

    The message names the file and the offending key (``modules[2].r``).
    """


class DatasetError(SwpcError, ValueError):
    """An offline dataset directory is missing a file/column or its data cannot be solved.

    The message names the file and the problem in one line.
    """


class CalibrationError(SwpcError):
    """The solver cannot produce a result from the data it was given."""
