"""The one root of every error a user can cause: `DatagenError`.

A typed base class, as zarr-python's ``zarr/errors.py`` has one, so that a caller can tell "the
user must change something" from "the program is wrong" with a single ``except``. It lives here,
in the bottom package, because every layer raises such errors: ``storage`` (an unreachable store,
a path that holds no dataset), ``jobs`` (a ledger that cannot be opened, an unknown job id) and
``datagen`` (a bad config or objects file, a corrupt mesh, a missing checkpoint); each derives its
own types from this one (`storage.StorageError`, `jobs.LedgerError`, `datagen.errors.*`).

The CLI catches `DatagenError` alone and prints it as one ``error: <message>`` line with a non-zero
exit code. Any other exception is a bug and keeps its traceback.
"""

from __future__ import annotations

__all__ = ["DatagenError"]


class DatagenError(Exception):
    """An error a user caused and can fix; its message names the fix.

    Raise a subclass (or this) only for what a user can change: a path, a URL, a config value, a
    job id, credentials. Write the message as one line that says what is wrong and what to do.
    """
