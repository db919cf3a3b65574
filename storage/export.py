"""Export to the authors' text layout, so AIR-OSVP's trainer (COSC_Dataset) runs unchanged.

``<out>/<object>/rotate_<r>/cloud_<i>.txt`` ("x y z" per line, exactly N points, seeded),
``state_<i>.txt`` (n lines 0/1), ``ids_<i>.txt`` (label view ids, one per line, ascending), plus
``train_split`` and ``test_split`` (object names, one per line; split by object). The loader finds
companions by replacing "cloud" in the whole path, so the output path must not contain "cloud".
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.location import StorageError
from storage.reader import Dataset, open_dataset


def export_air(url: str, out: str | Path, num_points: int = 2048, seed: int = 0, val_fraction: float = 0.2) -> int:
    """Write every sample in the authors' layout; returns the number of samples written."""
    out = Path(out).resolve()
    if "cloud" in str(out):
        raise StorageError(f"{out}: the authors' loader replaces 'cloud' in the whole path; choose a path without it")
    if num_points < 1:
        raise StorageError(f"--points {num_points}: give a positive number of points per cloud")
    dataset = open_dataset(url)
    folders = _object_folders(dataset)
    names = [folders[o] for o in dataset.index.column("object_id").to_pylist()]
    rotations = dataset.index.column("rotation").to_pylist()
    rows = dataset.index.column("row").to_pylist()
    for i in range(len(dataset)):
        folder = out / names[i] / f"rotate_{rotations[i]}"
        folder.mkdir(parents=True, exist_ok=True)
        _write_sample(dataset, i, folder, rows[i], num_points, seed)
    train, val = dataset.split(val_fraction, seed)
    _write_names(out / "train_split", train, folders)
    _write_names(out / "test_split", val, folders)
    return len(dataset)


def _write_sample(dataset: Dataset, i: int, folder: Path, row: int, num_points: int, seed: int) -> None:
    keys = dataset.keys(i, "points")
    rng = np.random.default_rng(np.random.SeedSequence([seed, i]))
    if keys.shape[0]:
        keys = keys[rng.choice(keys.shape[0], size=num_points, replace=keys.shape[0] < num_points)]
    points = dataset.centres(keys)
    np.savetxt(folder / f"cloud_{row}.txt", points, fmt="%.6f")
    view_state, label = dataset.masks(i)
    state = [(view_state >> v) & 1 for v in range(dataset.num_views)]
    (folder / f"state_{row}.txt").write_text("".join(f"{s}\n" for s in state))
    (folder / f"ids_{row}.txt").write_text("".join(f"{v}\n" for v in range(dataset.num_views) if label >> v & 1))


def _object_folders(dataset: Dataset) -> dict[str, str]:
    """One folder name per object: its name, or name plus id prefix when two objects share a name.
    The authors' loader finds companions by replacing 'cloud' anywhere in the path, so a name
    containing it is refused."""
    ids = dataset.index.column("object_id").to_pylist()
    names = dataset.index.column("object_name").to_pylist()
    by_id = dict(zip(ids, names, strict=True))
    counts: dict[str, int] = {}
    for name in by_id.values():
        counts[name] = counts.get(name, 0) + 1
    folders = {}
    for object_id, name in sorted(by_id.items()):
        if "cloud" in name:
            raise StorageError(
                f"object {name!r}: the authors' loader replaces 'cloud' in the whole path; rename it (name=...)"
            )
        folders[object_id] = name if counts[name] == 1 else f"{name}-{object_id[:8]}"
    return folders


def _write_names(path: Path, dataset: Dataset, folders: dict[str, str]) -> None:
    names = sorted({folders[o] for o in dataset.index.column("object_id").to_pylist()})
    path.write_text("".join(f"{name}\n" for name in names))
