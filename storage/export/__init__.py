"""Export a dataset in the file layouts the authors' trainers read, unchanged (docs/authors-code.md section 7).

``air`` (AIR-OSVP's text files), ``mascvp`` (MA-SCVP's and SC-Net's), ``nbvnet`` and ``pcnbv``: each a
`Layout` in `LAYOUTS`, each written by `export` with one output protocol (a hidden sibling folder renamed
into place), one split by object, and a provenance file naming every choice that differs from theirs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from storage.export.base import Export, Layout, Progress
from storage.export.options import EMPTY_LABEL, NO_NEXT_VIEW, NO_POINTS, PROVENANCE_JSON, PROVENANCE_MD, ROOT_FILES
from storage.export.registry import LAYOUTS, check_layout, layout_named, register_layout
from storage.export.run import export
from storage.export.streams import sample_rng
from storage.export.text import cpp_text

__all__ = [
    "EMPTY_LABEL",
    "LAYOUTS",
    "NO_NEXT_VIEW",
    "NO_POINTS",
    "PROVENANCE_JSON",
    "PROVENANCE_MD",
    "ROOT_FILES",
    "Export",
    "Layout",
    "check_layout",
    "cpp_text",
    "export",
    "export_air",
    "layout_named",
    "register_layout",
    "sample_rng",
]


def export_air(
    url: str,
    out: str | Path,
    num_points: int = 2048,
    seed: int = 0,
    val_fraction: float = 0.2,
    *,
    rotation_names: str = "authors",
    progress: Progress | None = None,
    storage_options: dict[str, Any] | None = None,
) -> Export:
    """`export` with ``layout="air"``: AIR-OSVP's text files, ``num_points`` per cloud."""
    return export(
        "air",
        url,
        out,
        num_points=num_points,
        seed=seed,
        val_fraction=val_fraction,
        rotation_names=rotation_names,
        progress=progress,
        storage_options=storage_options,
    )
