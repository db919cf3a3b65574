"""The output folder's protocol: an export is written into a hidden sibling of OUT and renamed into
place at the end, onto a path that is new or an empty folder, so an interrupted export is never
mistaken for a complete one and two exports are never merged.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path

from storage.store.location import StorageError


def make_staging(target: Path) -> Path:
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = target.parent / f".{target.name}.partial-{uuid.uuid4().hex[:12]}"
        staging.mkdir()
    except OSError as exc:
        raise StorageError(
            f"{target}: cannot create the output folder ({exc.strerror or exc}); check the path"
        ) from None
    return staging


def publish(staging: Path, target: Path) -> None:
    """Rename the finished export into place (onto a new path, or over an empty folder)."""
    try:
        os.rename(staging, target)
    except OSError as exc:
        raise StorageError(
            f"{target}: could not be made the export ({exc.strerror or exc}); something else wrote there "
            "meanwhile: give an empty or new folder"
        ) from None


def write_text(path: Path, text: str, target: Path) -> None:
    try:
        path.write_text(text)
    except OSError as exc:
        raise StorageError(f"{target}: cannot write the export ({exc.strerror or exc}); check free space") from None


def make_folder(folder: Path, target: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StorageError(f"{target}: cannot write the export ({exc.strerror or exc}); check free space") from None
