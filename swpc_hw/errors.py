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


class ImplausibleDataError(CalibrationError):
    """The data cannot be what they claim to be (units, clocks, magnitudes against the
    nominal robot): refused before a result exists.  The message names the likely cause.
    """


class ImplausibleResultError(CalibrationError):
    """A solution that fails the plausibility gates after solving (unphysical values,
    magnitudes far from the nominal robot): refused, never installed.
    """
