"""The text formats the authors' loaders read: numbers as their C++ writes them, a view state and a
label as their files hold them.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from storage.export.options import AUTHORS_VIEWS

Views = npt.NDArray[np.bool_]
"""A view set as a sample gives it: one bool per view (`storage.readers.Dataset.sample`)."""


def cpp_text(values: npt.ArrayLike, columns: int = 1) -> str:
    """Values as C++'s ostream writes a double by default (6 significant digits, like ``%g``), ``columns``
    to a line separated by spaces: what the authors' generator writes. Each distinct value is
    formatted once (an occupancy grid holds a handful), so 32,768 lines cost a few milliseconds."""
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    if not flat.size:
        return ""
    unique, inverse = np.unique(flat, return_inverse=True)
    table = np.array([f"{value:g}" for value in unique.tolist()], dtype=object)
    rows = table[inverse].reshape(-1, columns)
    return "".join(" ".join(row) + "\n" for row in rows.tolist()) if columns > 1 else "\n".join(rows[:, 0]) + "\n"


def state_text(view_state: Views) -> str:
    """The 32 lines 0/1 of a view state (line v: view v is in the case)."""
    return "".join(f"{bit}\n" for bit in _authors_views(view_state).astype(int).tolist())


def ids_text(label: Views) -> str:
    """A label's view ids, one per line, ascending."""
    return "".join(f"{v}\n" for v in np.flatnonzero(_authors_views(label)).tolist())


def bits32(views: Views) -> npt.NDArray[np.float32]:
    """The 32 views of a view set as float32 0/1 (a state or multi-hot label row)."""
    return _authors_views(views).astype(np.float32)


def _authors_views(views: Views) -> Views:
    """One bool for each of the authors' 32 views (`storage.export.checks.check_views` refuses others)."""
    found = np.asarray(views, dtype=bool).reshape(-1)
    if found.size != AUTHORS_VIEWS:
        raise ValueError(f"a view set of {found.size} views; the authors' layouts have {AUTHORS_VIEWS}")
    return found
