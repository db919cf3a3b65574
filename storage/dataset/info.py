"""Create and read ``dataset.json``; refuse to mix two configs in one dataset."""

from __future__ import annotations

from pydantic import ValidationError

from schemas.dataset import DATASET_FILE, DatasetInfo
from schemas.version import unreadable_version
from storage.dataset.manifest import mark_adding
from storage.dataset.writer import COMMITS, FAILURES
from storage.store.location import Location, StorageError, damaged, first_validation_error


def read_info(location: Location) -> DatasetInfo:
    """``dataset.json``; a `StorageError` naming the file and the fix when it is missing or bad."""
    if not location.exists(DATASET_FILE):
        if holds_records(location):
            raise damaged(location.url, DATASET_FILE, "missing although the dataset holds commit or failure records")
        raise StorageError(f"{location.url}: no {DATASET_FILE} here; this is not a datagen dataset (check the URL)")
    try:
        info = DatasetInfo.model_validate_json(location.read_bytes(DATASET_FILE))
    except ValidationError as exc:
        problem = f"unreadable ({first_validation_error(exc)})"
        raise damaged(location.url, DATASET_FILE, problem) from None
    newer = unreadable_version(info.schema_version)
    if newer:
        raise StorageError(f"{location.url}: {DATASET_FILE} says {newer}")
    return info


def holds_records(location: Location) -> bool:
    """True when commit or failure records are there (a dataset, whatever became of its dataset.json)."""
    return any(location.listdir(folder) for folder in (COMMITS, FAILURES))


def existing_info(location: Location, info: DatasetInfo) -> DatasetInfo | None:
    """The ``dataset.json`` already at ``location`` when it has ``info``'s config (None: no dataset
    there yet); a `StorageError` naming the fix when it holds a dataset of another config. Reads only:
    a job is checked with it before it is recorded, so a refused job leaves nothing behind."""
    if not location.exists(DATASET_FILE):
        return None
    existing = read_info(location)
    if existing.config_hash != info.config_hash:
        theirs, ours = existing.config.poco_version, info.config.poco_version
        hint = f" (it was made with poco_version = {theirs}, this job has {ours}: set it to add to it)"
        raise StorageError(
            f"{location.url}: holds a dataset of another config (hash {existing.config_hash[:12]}, "
            f"this job {info.config_hash[:12]}){hint if theirs != ours else ''}; write to a new --out"
        )
    return existing


def init_dataset(location: Location, info: DatasetInfo) -> DatasetInfo:
    """Write ``dataset.json`` for a new dataset, or check that an existing one has the same config; a
    job adds to it next, so readers are told to look past its manifest (`manifest.mark_adding`)."""
    existing = existing_info(location, info)
    if existing is not None:
        mark_adding(location)
        return existing
    location.write_atomic(DATASET_FILE, info.model_dump_json(indent=1).encode())
    mark_adding(location)
    return info
