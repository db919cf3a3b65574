"""Export to the authors' text layout, so AIR-OSVP's loader and trainer (COSC_Dataset, train.py) run unchanged.

``<out>/<object>/rotate_<k>/cloud_<i>.txt`` ("x y z" per line, exactly N points, seeded),
``state_<i>.txt`` (32 lines 0/1), ``ids_<i>.txt`` (label view ids, one per line, ascending), plus
``train_split`` and ``test_split`` (object folder names, one per line, split by object) and the
provenance of every choice that differs from the authors' (``PROVENANCE.md``, ``provenance.json``).

What their code needs, and what this module therefore guarantees (docs/authors-code.md section 7.2):

- companions are found by replacing "cloud" in the whole path, so neither the output path nor an
  object folder may contain it;
- their network has 32 outputs and ``gt = zeros(32); gt[ids] = 1``: a dataset of other than 32
  views is refused;
- their recall divides by the label size: a sample with an empty label would make it NaN (and no
  best checkpoint is ever saved), so such samples are skipped and counted; so are samples without
  points (an empty cloud file);
- ``rotate_<k>`` means a yaw of 45 deg x k there; rotations are mapped to that meaning, or refused
  (``rotation_names="yaw"`` names folders by their angle instead);
- the export is written into a hidden sibling folder and renamed into place at the end, into an
  output folder that is new or empty: an interrupted export is never mistaken for a complete one,
  and two exports are never merged.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from storage.location import StorageError
from storage.reader import Dataset, open_dataset
from storage.samples import mask_bits

LAYOUTS = ("air",)
"""Layouts `datagen shards export --layout` writes."""
AUTHORS_VIEWS = 32
"""Outputs of the authors' network (``output_dim: 32``) and the width of their state and gt."""
AUTHORS_ROTATIONS = 8
"""Their ``rotate_<k>`` is a yaw of 360/8 = 45 degrees x k."""
ROTATION_NAMES = ("authors", "yaw")
"""``authors``: ``rotate_<k>`` with their meaning (refused where an angle has none); ``yaw``: ``yaw_<degrees>``."""
TRAIN_SPLIT = "train_split"
TEST_SPLIT = "test_split"
PROVENANCE_MD = "PROVENANCE.md"
PROVENANCE_JSON = "provenance.json"
ROOT_FILES = (TRAIN_SPLIT, TEST_SPLIT, PROVENANCE_MD, PROVENANCE_JSON)
EMPTY_LABEL = "empty label"
NO_POINTS = "no points"
AUTHORS_CODE = "psc0628/AIR-OSVP @ c233bbf, poco_pointr/pointrVP/{COSC_Dataset.py,train.py}"

Progress = Callable[[int, int], None]
"""Called with (samples done, samples in the dataset) after each sample."""


@dataclass(frozen=True)
class AirExport:
    """What `export_air` wrote: counts, the split, and the provenance (also written into the export)."""

    out: Path
    samples: int
    """Samples in the dataset."""
    written: int
    """Samples written (cloud, state and ids files)."""
    skipped: dict[str, str]
    """Sample id -> why it was not written (`EMPTY_LABEL` or `NO_POINTS`)."""
    train_objects: tuple[str, ...]
    test_objects: tuple[str, ...]
    lines: tuple[str, ...]
    """The human summary: every choice that differs from the authors', one line each (the lines of
    ``PROVENANCE.md``, the first one naming the output folder)."""
    provenance: dict[str, Any]
    """The content of ``provenance.json``."""

    @property
    def skipped_empty_label(self) -> int:
        return sum(reason == EMPTY_LABEL for reason in self.skipped.values())

    @property
    def skipped_no_points(self) -> int:
        return sum(reason == NO_POINTS for reason in self.skipped.values())


def check_layout(layout: str) -> None:
    if layout not in LAYOUTS:
        known = ", ".join(repr(name) for name in LAYOUTS)
        raise StorageError(f"--layout {layout!r}: unknown layout; the layouts are {known} (AIR-OSVP's text files)")


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
) -> AirExport:
    """Write every exportable sample of the dataset at ``url`` into the new or empty folder ``out``.

    Raises `StorageError` (one line naming the fix) for bad arguments, an output folder that is not
    new or empty or whose path contains "cloud", a dataset that cannot be read or has other than 32
    views, rotations without an authors' folder, and a split that leaves ``train_split`` empty.
    """
    _check_arguments(num_points, seed, val_fraction, rotation_names)
    target = _check_output(Path(out))
    dataset = open_dataset(url, storage_options)
    _check_views(dataset)
    if len(dataset) == 0:
        raise StorageError(f"{url}: holds no samples; there is nothing to export")
    folders = _object_folders(dataset)
    rotation_folders = _rotation_folders(dataset, rotation_names)
    staging = _make_staging(target)
    try:
        rows, skipped, resampled = _write_samples(
            dataset, staging, target, folders, rotation_folders, num_points, seed, progress
        )
        if not rows:
            raise StorageError(
                f"{url}: every sample has an empty label or no points; there is nothing the authors' trainer can read"
            )
        train, test = dataset.select(rows).split(val_fraction, seed)
        train_names, test_names = _folder_names(train, folders), _folder_names(test, folders)
        if not train_names:
            raise StorageError(
                f"--val {val_fraction}: leaves train_split empty ({len(test_names)} objects in all); their "
                "trainer trains on train_split objects only, so lower --val"
            )
        facts = _Facts(dataset, num_points, seed, val_fraction, rotation_names, rotation_folders, len(rows), skipped)
        provenance = facts.provenance(resampled, train_names, test_names)
        lines = (
            f"exported {len(rows)} samples to {target} (of {len(dataset)} in the dataset)",
            *provenance["lines"][1:],
        )
        _write_text(staging / TRAIN_SPLIT, "".join(f"{name}\n" for name in train_names), target)
        _write_text(staging / TEST_SPLIT, "".join(f"{name}\n" for name in test_names), target)
        _write_text(staging / PROVENANCE_JSON, json.dumps(provenance, indent=1) + "\n", target)
        _write_text(staging / PROVENANCE_MD, _markdown(provenance["lines"]), target)
        _publish(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return AirExport(
        out=target,
        samples=len(dataset),
        written=len(rows),
        skipped=skipped,
        train_objects=tuple(train_names),
        test_objects=tuple(test_names),
        lines=lines,
        provenance=provenance,
    )


# -- checks ------------------------------------------------------------------------------------------


def _check_arguments(num_points: int, seed: int, val_fraction: float, rotation_names: str) -> None:
    if num_points < 1:
        raise StorageError(f"--points {num_points}: give a positive number of points per cloud")
    if num_points < 2:
        raise StorageError(
            "--points 1: give at least 2 points per cloud (the authors' loader reads a one-line cloud file as a "
            "flat array of 3 numbers, not as one point)"
        )
    if seed < 0:
        raise StorageError(f"--seed {seed}: give a seed >= 0")
    if not 0.0 <= val_fraction <= 1.0:
        raise StorageError(f"--val {val_fraction}: give the fraction of objects in test_split, from 0 to 1")
    if rotation_names not in ROTATION_NAMES:
        known = ", ".join(repr(name) for name in ROTATION_NAMES)
        raise StorageError(f"--rotation-names {rotation_names!r}: unknown; give one of {known}")


def _check_output(out: Path) -> Path:
    out = out.expanduser().resolve()
    if "cloud" in str(out):
        raise StorageError(
            f"{out}: the authors' loader finds state and ids files by replacing 'cloud' in the whole path; "
            "give an output path without 'cloud'"
        )
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        what = "is not a folder" if not out.is_dir() else "is not empty"
        raise StorageError(f"{out}: {what}; give an empty or new folder (an export is never merged into another)")
    return out


def _check_views(dataset: Dataset) -> None:
    if dataset.num_views != AUTHORS_VIEWS:
        raise StorageError(
            f"{dataset.url}: has {dataset.num_views} candidate views, but the authors' network has "
            f"{AUTHORS_VIEWS} outputs (32-wide state and gt); export a dataset made with the 32 built-in views"
        )


# -- names of folders --------------------------------------------------------------------------------


def _object_folders(dataset: Dataset) -> dict[str, str]:
    """One folder name per object id: its name, or name plus id prefix when two objects share a name
    (or a name is one of the export's own files). The authors' loader finds companions by replacing
    'cloud' anywhere in the path, so a name containing it is refused."""
    ids = dataset.index.column("object_id").to_pylist()
    names = dataset.index.column("object_name").to_pylist()
    by_id = {object_id: name.replace("/", "_").replace("\\", "_") for object_id, name in zip(ids, names, strict=True)}
    counts: dict[str, int] = {}
    for name in by_id.values():
        counts[name] = counts.get(name, 0) + 1
    folders = {}
    for object_id, name in sorted(by_id.items()):
        if "cloud" in name:
            raise StorageError(
                f"object {name!r}: the authors' loader replaces 'cloud' in the whole path; rename it (name=...)"
            )
        clash = counts[name] > 1 or name in ROOT_FILES or name.startswith(".")
        folders[object_id] = f"{name}-{object_id[:8]}" if clash else name
    return folders


def _rotation_folders(dataset: Dataset, rotation_names: str) -> dict[int, str]:
    """Rotation r (a yaw of r x 360/R degrees) -> its folder name."""
    total = dataset.info.config.rotations
    present = sorted({int(r) for r in dataset.index.column("rotation").to_pylist()})
    folders = {}
    for r in present:
        if rotation_names == "yaw":
            folders[r] = f"yaw_{_degrees(r, total)}"
            continue
        if (r * AUTHORS_ROTATIONS) % total:
            raise StorageError(
                f"{dataset.url}: rotation {r} of {total} (yaw {_degrees(r, total)} deg) has no folder of the "
                "authors' (their rotate_<k> means a yaw of 45 deg x k); pass --rotation-names yaw to name "
                "folders yaw_<degrees> instead"
            )
        folders[r] = f"rotate_{r * AUTHORS_ROTATIONS // total}"
    return folders


def _degrees(rotation: int, total: int) -> str:
    return f"{rotation * 360 / total:g}"


# -- writing -----------------------------------------------------------------------------------------


def _make_staging(target: Path) -> Path:
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = target.parent / f".{target.name}.partial-{uuid.uuid4().hex[:12]}"
        staging.mkdir()
    except OSError as exc:
        raise StorageError(
            f"{target}: cannot create the output folder ({exc.strerror or exc}); check the path"
        ) from None
    return staging


def _publish(staging: Path, target: Path) -> None:
    """Rename the finished export into place (onto a new path, or over an empty folder)."""
    try:
        os.rename(staging, target)
    except OSError as exc:
        raise StorageError(
            f"{target}: could not be made the export ({exc.strerror or exc}); something else wrote there "
            "meanwhile: give an empty or new folder"
        ) from None


def _write_text(path: Path, text: str, target: Path) -> None:
    try:
        path.write_text(text)
    except OSError as exc:
        raise StorageError(f"{target}: cannot write the export ({exc.strerror or exc}); check free space") from None


def _write_samples(
    dataset: Dataset,
    staging: Path,
    target: Path,
    folders: dict[str, str],
    rotation_folders: dict[int, str],
    num_points: int,
    seed: int,
    progress: Progress | None,
) -> tuple[list[int], dict[str, str], int]:
    """(rows written, skipped sample id -> reason, clouds drawn with replacement), shard by shard."""
    index = dataset.index
    sample_ids = index.column("sample_id").to_pylist()
    objects = index.column("object_id").to_pylist()
    rotations = index.column("rotation").to_pylist()
    shard_rows = index.column("row").to_pylist()
    written: list[int] = []
    skipped: dict[str, str] = {}
    resampled = 0
    made: set[Path] = set()
    done = 0
    for block in dataset.shard_blocks():
        for i in (int(i) for i in block):
            view_state, label = dataset.masks(i)
            keys = dataset.keys(i, "points") if label else np.empty((0, 3), dtype=np.int16)
            if not label or not keys.shape[0]:
                skipped[sample_ids[i]] = EMPTY_LABEL if not label else NO_POINTS
            else:
                replace = keys.shape[0] < num_points
                resampled += replace
                # The export's own stream, (seed, sample id), part of its documented format: not the
                # (seed, epoch, index) streams of `storage.samples`, which depend on a dataset's order.
                chosen = sample_rng(seed, sample_ids[i]).choice(keys.shape[0], size=num_points, replace=replace)
                folder = staging / folders[objects[i]] / rotation_folders[int(rotations[i])]
                if folder not in made:
                    _make_folder(folder, target)
                    made.add(folder)
                _write_sample(folder, int(shard_rows[i]), dataset.centres(keys[chosen]), view_state, label, target)
                written.append(i)
            done += 1
            if progress is not None:
                progress(done, len(dataset))
    return sorted(written), skipped, resampled


def sample_rng(seed: int, sample_id: str) -> np.random.Generator:
    """The stream that draws one sample's points: fixed by the seed and the sample id alone."""
    digest = int.from_bytes(hashlib.sha256(sample_id.encode()).digest()[:8], "little")
    return np.random.default_rng(np.random.SeedSequence([seed, digest]))


def _make_folder(folder: Path, target: Path) -> None:
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StorageError(f"{target}: cannot write the export ({exc.strerror or exc}); check free space") from None


def _write_sample(
    folder: Path, row: int, points: npt.NDArray[np.float32], view_state: int, label: int, target: Path
) -> None:
    cloud = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in points.tolist())
    state = "".join(f"{bit}\n" for bit in mask_bits(view_state, AUTHORS_VIEWS).astype(int).tolist())
    ids = "".join(f"{v}\n" for v in np.flatnonzero(mask_bits(label, AUTHORS_VIEWS)).tolist())
    _write_text(folder / f"cloud_{row}.txt", cloud, target)
    _write_text(folder / f"state_{row}.txt", state, target)
    _write_text(folder / f"ids_{row}.txt", ids, target)


def _folder_names(dataset: Dataset, folders: dict[str, str]) -> list[str]:
    return sorted({folders[o] for o in dataset.index.column("object_id").to_pylist()})


# -- provenance --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Facts:
    dataset: Dataset
    num_points: int
    seed: int
    val_fraction: float
    rotation_names: str
    rotation_folders: dict[int, str]
    written: int
    skipped: dict[str, str]

    def provenance(self, resampled: int, train: list[str], test: list[str]) -> dict[str, Any]:
        config = self.dataset.info.config
        index = self.dataset.index
        refiners = sorted(set(index.column("refiner").to_pylist()))
        weights = sorted(set(index.column("weights_id").to_pylist()) - {""})
        empty = sum(reason == EMPTY_LABEL for reason in self.skipped.values())
        no_points = len(self.skipped) - empty
        low, high = config.size_range
        voxel_mm = f"{config.voxel_size * 1000:g} mm"
        rotations = self._rotations_line()
        builtin = config.view_space.source == "builtin"
        views = (
            f"views: 32, the authors' view_space_32.txt in its order (bit i of state and ids = their view i), "
            f"radius {config.view_space.radius:g} m"
            if builtin
            else f"views: 32 from {config.view_space.source!r}, not the authors' positions: bit i of state and ids "
            "is this dataset's view i, so a checkpoint trained on their data does not apply"
        )
        weights_text = f", weights {', '.join(w[:16] for w in weights)}" if weights else ""
        lines = [
            f"exported {self.written} samples (of {len(self.dataset)} in the dataset)",
            f"skipped {empty} samples with an empty label (no view needed: their recall divides by the label "
            "size, one such sample makes it NaN and no best checkpoint is saved; their generator writes none)",
            f"skipped {no_points} samples with no points (their loader cannot read an empty cloud file)",
            f"dataset: {self.dataset.url} (config hash {self.dataset.info.config_hash}, alpha {config.alpha}, "
            f"refiner {', '.join(refiners)}{weights_text}); labels are exact minimum covers, the lexicographically "
            f"smallest in the {config.label_tie_break!r} view order, theirs Gurobi's choice",
            f"points: {self.num_points} per cloud (every cloud the same size, as their do_sample: False batching "
            f"needs), drawn from the sample's refined cloud P(O_S) of {voxel_mm} voxel centres without "
            f"replacement, with replacement for the {resampled} samples that have fewer; seeded by "
            f"(seed {self.seed}, sample id)",
            f"frame: this project's task frame, not theirs: metres, origin at the object's bounding-box centre, "
            f"z up, each object scaled so its largest extent lies in [{low:g}, {high:g}] m (or its objects-file "
            "size=), turned by the task's yaw; theirs are raw world metres in the object's own world frame "
            "(not centred, not scaled). The dataset keeps no per-object offset or scale, so the world frame "
            "cannot be restored",
            rotations,
            views,
            f"split: train_split {len(train)} objects, test_split {len(test)} (by object, val {self.val_fraction:g}, "
            f"seed {self.seed}, as storage's Dataset.split); their train.py trains on train_split objects only "
            "(its validation is 20% of their samples, numpy seed 42, also trained on) and reads test_split "
            "without using it",
            f"provenance: {PROVENANCE_MD} and {PROVENANCE_JSON} in the export",
        ]
        return {
            "layout": "air",
            "read_by": AUTHORS_CODE,
            "dataset": {
                "url": self.dataset.url,
                "config_hash": self.dataset.info.config_hash,
                "alpha": config.alpha,
                "refiner": refiners,
                "weights_id": weights,
                "empty_labels": config.empty_labels,
                "rotations": config.rotations,
                "views": self.dataset.num_views,
                "view_space": config.view_space.source,
                "samples": len(self.dataset),
                "versions": self.dataset.info.versions,
            },
            "written": self.written,
            "skipped": {
                "empty_label": empty,
                "no_points": no_points,
                "samples": dict(sorted(self.skipped.items())),
            },
            "points": {
                "per_cloud": self.num_points,
                "source": "points: the refined cloud P(O_S), voxel centres",
                "sampling": "uniform without replacement; with replacement when the cloud has fewer points",
                "rng": "numpy default_rng(SeedSequence([seed, sha256(sample_id) first 8 bytes, little-endian]))",
                "seed": self.seed,
                "drawn_with_replacement": resampled,
                "format": "x y z per line, %.6f",
            },
            "frame": {
                "name": "task frame",
                "units": "m",
                "origin": "the object's bounding-box centre, z up, largest extent scaled into size_range, yawed",
                "size_range_m": [low, high],
                "authors": "raw world metres in the object's own world frame, not centred or scaled",
                "world_frame_recoverable": False,
                "why": "the dataset stores no per-object offset or scale",
            },
            "rotations": {
                "folders": self.rotation_names,
                "dataset_rotations": config.rotations,
                "meaning_here": "rotation r is a yaw of r x 360/rotations degrees about z through the object's centre",
                "meaning_authors": "rotate_<k> is a yaw of 45 x k degrees about the world origin",
                "folder_of_rotation": {str(r): name for r, name in sorted(self.rotation_folders.items())},
            },
            "views": {"count": self.dataset.num_views, "source": config.view_space.source, "authors_order": builtin},
            "split": {
                "val_fraction": self.val_fraction,
                "seed": self.seed,
                "by": "object (storage Dataset.split over the written samples)",
                "train_split": train,
                "test_split": test,
                "authors_use": "train.py trains on train_split objects only; its validation is a 20% sample-level "
                "split of them (numpy seed 42) that is trained on too; test_split is read but not used",
            },
            "lines": lines,
        }

    def _rotations_line(self) -> str:
        total = self.dataset.info.config.rotations
        step = f"{360 / total:g} deg"
        if self.rotation_names == "yaw":
            return (
                f"rotations: folders yaw_<degrees> ({total} rotations, {step} apart), not the authors' rotate_<k> "
                "(a yaw of 45 deg x k); their loader does not read folder names; yaw about the object's centre, "
                "theirs about the world origin"
            )
        if total == AUTHORS_ROTATIONS:
            return (
                "rotations: rotate_<r> is a yaw of 45 deg x r, the authors' meaning (8 rotations, as theirs); "
                "yaw about the object's centre, theirs about the world origin"
            )
        return (
            f"rotations: rotate_<k> is a yaw of 45 deg x k, the authors' meaning; this dataset's {total} rotations "
            f"({step} apart) are mapped r -> k = r x 8/{total}; yaw about the object's centre, theirs about the "
            "world origin"
        )


def _markdown(lines: list[str]) -> str:
    head = [
        "# Provenance of this export",
        "",
        f"Written by `datagen shards export --layout air` for AIR-OSVP's loader and trainer ({AUTHORS_CODE}).",
        f"Every choice that differs from the authors' is listed; `{PROVENANCE_JSON}` holds the same facts as data.",
        "",
    ]
    return "\n".join(head + [f"- {line}" for line in lines]) + "\n"
