"""The refusals every layout shares: options out of range, an output folder that is not new or
empty (or whose path holds the word the loader replaces), a dataset of other than the authors' 32
views. Each is one `StorageError` line naming the fix.
"""

from __future__ import annotations

from pathlib import Path

from storage.export.options import AUTHORS_VIEWS, ROTATION_NAMES, Options
from storage.readers.reader import Dataset
from storage.store.location import StorageError


def check_common(options: Options) -> None:
    if options.seed < 0:
        raise StorageError(f"--seed {options.seed}: give a seed >= 0")
    if not 0.0 <= options.val_fraction <= 1.0:
        raise StorageError(f"--val {options.val_fraction}: give the fraction of objects in test_split, from 0 to 1")
    if options.rotation_names not in ROTATION_NAMES:
        known = ", ".join(repr(name) for name in ROTATION_NAMES)
        raise StorageError(f"--rotation-names {options.rotation_names!r}: unknown; give one of {known}")


def check_points(option: str, count: int) -> None:
    if count < 1:
        raise StorageError(f"{option} {count}: give a positive number of points per cloud")
    if count < 2:
        raise StorageError(
            f"{option} 1: give at least 2 points per cloud (a one-line cloud file reads back as a flat array of "
            "3 numbers, not as one point)"
        )


def check_output(out: Path, word: str | None) -> Path:
    """OUT resolved: a new path or an empty folder, without ``word`` anywhere in it."""
    out = out.expanduser().resolve()
    if word is not None and word in str(out):
        raise StorageError(
            f"{out}: the authors' loader finds companion files by replacing '{word}' in the whole path; "
            f"give an output path without '{word}'"
        )
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        what = "is not a folder" if not out.is_dir() else "is not empty"
        raise StorageError(f"{out}: {what}; give an empty or new folder (an export is never merged into another)")
    return out


def check_views(dataset: Dataset) -> None:
    if dataset.num_views != AUTHORS_VIEWS:
        raise StorageError(
            f"{dataset.url}: has {dataset.num_views} candidate views, but the authors' network has "
            f"{AUTHORS_VIEWS} outputs (32-wide state and gt); export a dataset made with the 32 built-in views"
        )
