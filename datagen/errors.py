"""The project's own exception types: errors a user can cause, each with a message that says the fix.

The CLI prints these in one line and exits non-zero; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class DatagenError(Exception):
    """Base of every error a user can cause and fix."""


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
