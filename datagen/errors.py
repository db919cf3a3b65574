"""The project's own exception types: errors a user can cause, each with a message that says the fix.

All derive from `DatagenError`, the one root defined in `schemas.errors` (re-exported here) that
`storage.StorageError` and `jobs.LedgerError` derive from too. The CLI prints any of them in one
line and exits non-zero; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from schemas.errors import DatagenError

__all__ = [
    "ConfigError",
    "DatagenError",
    "InvalidArgument",
    "ObjectError",
    "ObjectsFileError",
    "OutputError",
    "PlannerError",
    "ViewSpaceError",
]


class ConfigError(DatagenError):
    """A config file or value is invalid."""


class ObjectsFileError(DatagenError):
    """An objects file (as a whole, or one of its lines) is invalid."""


class ObjectError(DatagenError):
    """One object cannot be loaded or prepared; the other objects go on."""


class ViewSpaceError(DatagenError):
    """A view-space file is missing or malformed."""


class InvalidArgument(DatagenError, ValueError):
    """A function argument a user chose is out of its allowed range."""


class OutputError(DatagenError):
    """An output location cannot be created or written."""


class PlannerError(DatagenError):
    """A planner for `datagen evaluate` is unknown, or its checkpoint is missing or unusable."""
