"""The export layouts by name: `datagen shards export --layout NAME` dispatches through `LAYOUTS`.

A package adds a layout with no file of ours touched: an entry point of the group
``datagen.export_layouts`` naming an instance of its `Layout` (or a module calling `register_layout`).
"""

from __future__ import annotations

from schemas.registry import Registry
from storage.export.air import AIR
from storage.export.base import Layout
from storage.export.mascvp import MASCVP
from storage.export.nbvnet import NBVNET
from storage.export.pcnbv import PCNBV
from storage.store.location import StorageError

LAYOUTS: Registry[Layout] = Registry(
    "export layout", "datagen.export_layouts", error=StorageError, check=lambda entry: isinstance(entry, Layout)
)
"""Layout name -> layout, in the order ``--help`` lists them (`register_layout`)."""


def register_layout(layout: Layout) -> Layout:
    """Register ``layout`` under its name (once)."""
    return LAYOUTS.register(layout.name, layout)


for _layout in (AIR, MASCVP, NBVNET, PCNBV):
    register_layout(_layout)


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
