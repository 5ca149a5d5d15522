"""The errors the VFM raises, in one place.

Hierarchy::

    VFMError                      base class; catch this to handle any VFM failure
    ├── DataError                 an input file or record cannot be used as it is
    │   └── ObservationFormatError  a file breaks the observation format (names file, row, column)
    ├── ConfigError               a setting, name or option is invalid (names the valid choices)
    └── PhysicsError              inputs outside the domain where the choke equations hold

Messages are full sentences that say what was wrong and what to do instead.
"""

from __future__ import annotations

__all__ = ["VFMError", "DataError", "ObservationFormatError", "ConfigError", "PhysicsError"]


class VFMError(Exception):
    """Base class of every error the VFM raises on purpose."""


class DataError(VFMError):
    """An input file or record cannot be used as it is."""


class ObservationFormatError(DataError):
    """A file breaks the observation format.

    The message names the file, and where it applies the (1-based, header = row 1) row,
    the column and what is wrong with the value.
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | None = None,
        row: int | None = None,
        column: str | None = None,
    ) -> None:
        self.path = path
        self.row = row
        self.column = column
        where = []
        if path is not None:
            where.append(f"file {path}")
        if row is not None:
            where.append(f"row {row}")
        if column is not None:
            where.append(f"column '{column}'")
        prefix = (", ".join(where) + ": ") if where else ""
        super().__init__(prefix + message)


class ConfigError(VFMError):
    """A setting, registry name or command option is invalid."""


class PhysicsError(VFMError):
    """Inputs lie outside the domain where the choke equations hold."""
