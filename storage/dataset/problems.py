"""What `storage.validate` finds, as records: where a problem is, what mends it, and its line.

A problem names the file it is in (relative to the dataset), the task that owns that file where one
does, the array and the row or view within it, a `kind` (stable, for code) and a message (for people);
the printed line is made from them. `datagen shards repair` decides what to re-run from the records,
never from the message, so rewording a message changes no repair.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum


class Mend(StrEnum):
    """What makes a problem go away."""

    TASK = "task"
    """Re-running the task that owns the file (its shard, fragment or records are damaged)."""
    INDEX = "index"
    """Finalising the index again (the merged index alone is stale or damaged)."""
    NONE = "none"
    """Neither (``dataset.json`` is damaged): the dataset cannot be repaired from its own files."""


@dataclass(frozen=True)
class Problem:
    """One problem of a dataset."""

    kind: str
    """What is wrong, as a stable word: ``shard`` (the group or its attributes), ``array`` (missing,
    truncated, misshapen, unsorted), ``sample`` (a mask), ``uncovered`` (a label leaves keys of its U),
    ``label`` (a label breaks its objective's promise), ``covers`` (the listed covers or ties),
    ``fragment``, ``record``, ``index``, ``index-row``, ``dataset``."""
    file: str
    """The file or folder it is in, relative to the dataset root."""
    message: str
    """What is wrong, for people (the line without its place)."""
    mend: Mend
    task: str | None = None
    """The task whose re-run mends it (`Mend.TASK`), or that it concerns."""
    array: str | None = None
    """The shard array it is in, where one is."""
    place: str = ""
    """Where inside the file: ``row 3`` (a sample) or ``view 5`` (a per-view set); empty for the file."""

    @property
    def line(self) -> str:
        """The printed line: ``FILE[ PLACE]: MESSAGE``, or the message alone where no file is named
        (a folder with no dataset at all: the message names the URL itself)."""
        where = " ".join(part for part in (self.file, self.place) if part)
        return f"{where}: {self.message}" if where else self.message

    def __str__(self) -> str:
        return self.line


def lines(problems: list[Problem]) -> list[str]:
    """The printed lines of ``problems``, in order."""
    return [problem.line for problem in problems]
