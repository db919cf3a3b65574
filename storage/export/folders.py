"""Folder names of an export: each object's folder (unique, never a reserved root name) and each
rotation's (the authors' ``rotate_<k>`` or a yaw in degrees).
"""

from __future__ import annotations

import pyarrow as pa

from schemas.dataset import CARD_FILE
from storage.export.options import AUTHORS_ROTATIONS, ROOT_FILES
from storage.readers.reader import Dataset
from storage.store.location import StorageError


def object_folders(dataset: Dataset, word: str | None, reserved: tuple[str, ...]) -> dict[str, str]:
    """One folder name per object id: its name, or name plus id prefix when two objects share a name,
    or a name is one the export writes at its root. A name holding ``word`` is refused (their loader
    replaces it anywhere in the path)."""
    pairs = pa.table(
        {
            "id": dataset.samples.column("object_id", keep=False),
            "name": dataset.samples.column("object_name", keep=False),
        }
    )
    objects = pairs.group_by(["id", "name"], use_threads=False).aggregate([])  # one row per object, not sample
    ids, names = objects.column("id").to_pylist(), objects.column("name").to_pylist()
    by_id = {object_id: name.replace("/", "_").replace("\\", "_") for object_id, name in zip(ids, names, strict=True)}
    counts: dict[str, int] = {}
    for name in by_id.values():
        counts[name] = counts.get(name, 0) + 1
    taken = {*ROOT_FILES, CARD_FILE, *reserved}  # the dataset card is copied beside them when there is one
    folders = {}
    for object_id, name in sorted(by_id.items()):
        if word is not None and word in name:
            raise StorageError(
                f"object {name!r}: the authors' loader replaces '{word}' in the whole path; rename it (name=...)"
            )
        clash = counts[name] > 1 or name in taken or name.startswith(".")
        folders[object_id] = f"{name}-{object_id[:8]}" if clash else name
    return folders


def rotation_folders(dataset: Dataset, rotation_names: str) -> dict[int, str]:
    """Rotation r (a yaw of r x 360/R degrees) -> its folder name."""
    total = dataset.info.config.rotations
    present = sorted(int(r) for r in dataset.counts("rotation"))
    folders = {}
    for r in present:
        if rotation_names == "yaw":
            folders[r] = f"yaw_{degrees(r, total)}"
            continue
        if (r * AUTHORS_ROTATIONS) % total:
            raise StorageError(
                f"{dataset.url}: rotation {r} of {total} (yaw {degrees(r, total)} deg) has no folder of the "
                "authors' (their rotate_<k> means a yaw of 45 deg x k); pass --rotation-names yaw to name "
                "folders yaw_<degrees> instead"
            )
        folders[r] = f"rotate_{r * AUTHORS_ROTATIONS // total}"
    return folders


def degrees(rotation: int, total: int) -> str:
    return f"{rotation * 360 / total:g}"
