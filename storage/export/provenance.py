"""The provenance every layout writes beside its files: what the dataset is, its frame, its rotations
and views, as lines of ``PROVENANCE.md`` and facts of ``provenance.json``.
"""

from __future__ import annotations

from typing import Any

from storage.export.base import Layout
from storage.export.options import AUTHORS_ROTATIONS, PROVENANCE_JSON
from storage.readers.reader import Dataset


def dataset_facts(dataset: Dataset) -> tuple[str, dict[str, Any]]:
    """The provenance's dataset line (without a layout's note) and its data."""
    config = dataset.info.config
    refiners = sorted(dataset.counts("refiner"))
    weights = sorted(set(dataset.counts("weights_id")) - {""})
    weights_text = f", weights {', '.join(w[:16] for w in weights)}" if weights else ""
    line = (
        f"dataset: {dataset.url} (config hash {dataset.info.config_hash}, alpha {config.alpha}, "
        f"refiner {', '.join(refiners)}{weights_text})"
    )
    facts = {
        "url": dataset.url,
        "config_hash": dataset.info.config_hash,
        "schema_version": dataset.info.schema_version,
        "alpha": config.alpha,
        "refiner": refiners,
        "weights_id": weights,
        "empty_labels": config.empty_labels,
        "rotations": config.rotations,
        "views": dataset.num_views,
        "view_space": config.view_space.source,
        "samples": len(dataset),
        "versions": dataset.info.versions,
    }
    return line, facts


def frame_facts(dataset: Dataset) -> tuple[str, dict[str, Any]]:
    low, high = dataset.info.config.size_range
    line = (
        f"frame: this project's task frame, not theirs: metres, origin at the object's bounding-box centre, "
        f"z up, each object scaled so its largest extent lies in [{low:g}, {high:g}] m (or its objects-file "
        "size=), turned by the task's yaw; theirs are raw world metres in the object's own world frame "
        "(not centred, not scaled). The dataset keeps no per-object offset or scale, so the world frame "
        "cannot be restored"
    )
    facts = {
        "name": "task frame",
        "units": "m",
        "origin": "the object's bounding-box centre, z up, largest extent scaled into size_range, yawed",
        "size_range_m": [low, high],
        "authors": "raw world metres in the object's own world frame, not centred or scaled",
        "world_frame_recoverable": False,
        "why": "the dataset stores no per-object offset or scale",
    }
    return line, facts


def rotation_facts(dataset: Dataset, rotation_names: str, folders: dict[int, str]) -> tuple[str, dict[str, Any]]:
    total = dataset.info.config.rotations
    step = f"{360 / total:g} deg"
    if rotation_names == "yaw":
        line = (
            f"rotations: folders yaw_<degrees> ({total} rotations, {step} apart), not the authors' rotate_<k> "
            "(a yaw of 45 deg x k); their loader does not read folder names; yaw about the object's centre, "
            "theirs about the world origin"
        )
    elif total == AUTHORS_ROTATIONS:
        line = (
            "rotations: rotate_<r> is a yaw of 45 deg x r, the authors' meaning (8 rotations, as theirs); "
            "yaw about the object's centre, theirs about the world origin"
        )
    else:
        line = (
            f"rotations: rotate_<k> is a yaw of 45 deg x k, the authors' meaning; this dataset's {total} rotations "
            f"({step} apart) are mapped r -> k = r x 8/{total}; yaw about the object's centre, theirs about the "
            "world origin"
        )
    facts = {
        "folders": rotation_names,
        "dataset_rotations": total,
        "meaning_here": "rotation r is a yaw of r x 360/rotations degrees about z through the object's centre",
        "meaning_authors": "rotate_<k> is a yaw of 45 x k degrees about the world origin",
        "folder_of_rotation": {str(r): name for r, name in sorted(folders.items())},
    }
    return line, facts


def view_facts(dataset: Dataset) -> tuple[str, dict[str, Any]]:
    config = dataset.info.config
    builtin = config.view_space.source == "builtin"
    line = (
        f"views: 32, the authors' view_space_32.txt in its order (bit i of state and ids = their view i), "
        f"radius {config.view_space.radius:g} m"
        if builtin
        else f"views: 32 from {config.view_space.source!r}, not the authors' positions: bit i of state and ids "
        "is this dataset's view i, so a checkpoint trained on their data does not apply"
    )
    return line, {"count": dataset.num_views, "source": config.view_space.source, "authors_order": builtin}


def markdown(layout: Layout, lines: list[str]) -> str:
    head = [
        "# Provenance of this export",
        "",
        f"Written by `datagen shards export --layout {layout.name}` for {layout.reader} ({layout.read_by}).",
        f"Every choice that differs from the authors' is listed; `{PROVENANCE_JSON}` holds the same facts as data.",
        "",
    ]
    return "\n".join(head + [f"- {line}" for line in lines]) + "\n"
