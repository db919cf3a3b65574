"""The export layouts by name: `datagen shards export --layout NAME` dispatches through `LAYOUTS`."""

from __future__ import annotations

from storage.export.air import AIR
from storage.export.base import Layout
from storage.export.mascvp import MASCVP
from storage.export.nbvnet import NBVNET
from storage.export.pcnbv import PCNBV
from storage.location import StorageError

LAYOUTS: dict[str, Layout] = {layout.name: layout for layout in (AIR, MASCVP, NBVNET, PCNBV)}
"""Layout name -> layout, in the order ``--help`` lists them."""


def layout_named(name: str) -> Layout:
    """The layout called ``name``; an unknown name is a `StorageError` listing the known ones."""
    found = LAYOUTS.get(name)
    if found is None:
        known = ", ".join(f"{layout.name!r} ({layout.summary})" for layout in LAYOUTS.values())
        raise StorageError(f"--layout {name!r}: unknown layout; the layouts are {known}")
    return found


def check_layout(name: str) -> None:
    """Refuse an unknown layout name (before any file is touched)."""
    layout_named(name)
