"""Case-insensitive string enums for configuration choices (pyproj ``BaseEnum`` style)."""

from __future__ import annotations

import enum

from .errors import ConfigError

__all__ = ["StrChoice"]


class StrChoice(str, enum.Enum):
    """String enum that accepts case-insensitive names or values.

    ``Unit("c")``, ``Unit("C")`` and ``Unit.C`` are the same member; an unknown
    choice raises :class:`~thermogrammetry.errors.ConfigError` listing the valid ones.
    """

    @classmethod
    def _missing_(cls, value):  # called by Enum when the exact lookup fails
        if isinstance(value, str):
            key = value.strip().lower()
            for member in cls:
                if member.value.lower() == key or member.name.lower() == key:
                    return member
        valid = ", ".join(repr(m.value) for m in cls)
        raise ConfigError(f"{value!r} is not a valid {cls.__name__}; expected one of {valid}")

    def __str__(self) -> str:
        return self.value
