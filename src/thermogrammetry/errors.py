"""The project's exception tree.

One root, :class:`ThermogrammetryError`; every subclass also derives from the
built-in exception a caller would expect (``ValueError`` for bad values,
``OSError`` for unreadable files), so ``except ValueError`` keeps working.

Bad *input* raises. A *numerical* failure found while solving (non-convergence,
degenerate geometry discovered during a solve) is returned as a result value
with a reason, never raised -- see :mod:`thermogrammetry.results`.

Messages name the offending value (and the file and row where there is one)
and the expected form.
"""

from __future__ import annotations

__all__ = [
    "ThermogrammetryError",
    "InvalidInputError",
    "ShapeError",
    "NonFiniteError",
    "DegenerateInputError",
    "TooFewPointsError",
    "UnknownModelError",
    "ConfigError",
    "DataFileError",
    "UnsupportedFormatError",
    "CorruptFileError",
    "ImageTooLargeError",
]


class ThermogrammetryError(Exception):
    """Root of every exception raised by thermogrammetry."""


class InvalidInputError(ThermogrammetryError, ValueError):
    """A value given to a public function is not what it expects."""


class ShapeError(InvalidInputError):
    """An array has the wrong shape or dimensionality."""


class NonFiniteError(InvalidInputError):
    """An array contains NaN or infinity where finite numbers are required."""


class DegenerateInputError(InvalidInputError):
    """The input geometry cannot determine the requested quantity
    (coplanar control points for a DLT, collinear plane points, ...)."""


class TooFewPointsError(DegenerateInputError):
    """Fewer observations than the estimate needs."""


class UnknownModelError(InvalidInputError):
    """A camera model, format or method name that is not known."""


class ConfigError(InvalidInputError):
    """Invalid configuration: unknown key, wrong type, wrong unit or bad choice."""


class DataFileError(ThermogrammetryError, OSError):
    """A file cannot be read or written as expected."""


class UnsupportedFormatError(DataFileError):
    """A file is readable but not in a format we can interpret."""


class CorruptFileError(DataFileError):
    """A file claims a known format but its content is truncated or inconsistent."""


class ImageTooLargeError(DataFileError):
    """A file declares an image larger than the configured size cap
    (:func:`thermogrammetry.io.limits.max_pixels`); refused before any pixel memory is allocated."""
