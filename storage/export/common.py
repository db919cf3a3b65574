"""What every export layout shares: the output folder's protocol, the refusals, folder names, the seeded
streams, the text formats and the provenance that does not depend on the layout.

The protocol: an export is written into a hidden sibling of OUT and renamed into place at the end,
onto a path that is new or an empty folder, so an interrupted export is never mistaken for a complete
one and two exports are never merged.
"""

from __future__ import annotations

import hashlib
import os
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import numpy.typing as npt
import pyarrow as pa

from storage.location import StorageError
from storage.reader import Dataset
from storage.samples import mask_bits

AUTHORS_VIEWS = 32
"""Outputs of every authors' network (AIR-OSVP, MA-SCVP, SC-Net, NBVNet, PC-NBV): the width of their
state, label and score vectors."""
AUTHORS_ROTATIONS = 8
"""Their ``rotate_<k>`` is a yaw of 360/8 = 45 degrees x k."""
ROTATION_NAMES = ("authors", "yaw")
"""``authors``: ``rotate_<k>`` with their meaning (refused where an angle has none); ``yaw``: ``yaw_<degrees>``."""
TRAIN = "train"
TEST = "test"
SPLITS = (TRAIN, TEST)
TRAIN_SPLIT = "train_split"
TEST_SPLIT = "test_split"
PROVENANCE_MD = "PROVENANCE.md"
PROVENANCE_JSON = "provenance.json"
ROOT_FILES = (TRAIN_SPLIT, TEST_SPLIT, PROVENANCE_MD, PROVENANCE_JSON)
"""What every export writes at its root."""

EMPTY_LABEL = "empty label"
NO_POINTS = "no points"
NO_NEXT_VIEW = "no next view"
PHRASES = {EMPTY_LABEL: "an empty label", NO_POINTS: "no points", NO_NEXT_VIEW: "no next view"}
"""How a provenance line names the samples skipped for each reason."""

Progress = Callable[[int, int], None]
"""Called with (samples done, samples in the dataset) after each sample."""


@dataclass(frozen=True)
class Options:
    """The user's choices; a layout fills its defaults and refuses what it cannot use (`Layout.resolve`)."""

    num_points: int | None = None
    gt_points: int | None = None
    seed: int = 0
    val_fraction: float = 0.2
    rotation_names: str = "authors"


@dataclass(frozen=True)
class Export:
    """What an export wrote: counts, the split, and the provenance (also written into the export)."""

    out: Path
    layout: str
    samples: int
    """Samples in the dataset."""
    written: int
    """Samples written."""
    skipped: dict[str, str]
    """Sample id -> why it was not written (`EMPTY_LABEL`, `NO_POINTS`, `NO_NEXT_VIEW`)."""
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


@dataclass(frozen=True)
class Place:
    """Where one sample goes: its folder of text files, its case number there, and its row in its
    split's arrays."""

    index: int
    """Row of the dataset's index."""
    sample_id: str
    folder: Path
    """``<staging>/<object>/<rotation folder>``, created before the writer is called."""
    case: int
    """``<c>`` of its file names: the sample's row in its task's shard (cases sorted by size, then mask)."""
    split: str
    """`TRAIN` or `TEST`."""
    position: int
    """Its row in its split's arrays (samples in the order the export reads them)."""


@dataclass(frozen=True)
class Run:
    """What a layout's writer is given: the dataset, where to write, the resolved options, and how many
    samples each split's arrays hold."""

    dataset: Dataset
    staging: Path
    target: Path
    options: Options
    split_sizes: Mapping[str, int]


class Writer(ABC):
    """Writes one layout's files for one export, sample by sample, then its per-split files."""

    @abstractmethod
    def write(self, place: Place) -> None:
        """Write the sample's files (its folder exists)."""

    @abstractmethod
    def finish(self) -> None:
        """Write what is whole only once every sample is in (arrays, root files)."""

    @abstractmethod
    def lines(self) -> list[str]:
        """Provenance lines of what this layout writes, placed after the dataset line."""

    @abstractmethod
    def facts(self) -> dict[str, Any]:
        """The same as data: keys added to ``provenance.json``."""


class Layout(ABC):
    """One export format: its checks and defaults, which samples it skips and why, and its writer.
    Instances are registered by name in `storage.export.LAYOUTS`."""

    name: ClassVar[str]
    reader: ClassVar[str]
    """Whose code reads it, in words (``PROVENANCE.md``'s heading)."""
    read_by: ClassVar[str]
    """The authors' files that read it, with the repository and commit."""
    summary: ClassVar[str]
    """One line for ``--help``."""
    path_word: ClassVar[str | None] = None
    """A word their loader replaces in the whole path of what it reads, so OUT may not hold it."""
    name_word: ClassVar[str | None] = None
    """A word no object folder may hold (their loader replaces it in the paths of the text files)."""
    reserved: ClassVar[tuple[str, ...]] = ()
    """Names it writes at OUT's root besides `ROOT_FILES` (an object of such a name gets its id appended)."""
    skip_reasons: ClassVar[Mapping[str, str]]
    """Reason a sample is skipped -> why their code cannot take it."""
    points: ClassVar[int | None] = None
    """Default points per cloud; None: the layout writes no cloud (or needs ``--points``, see `needs_points`)."""
    needs_points: ClassVar[bool] = False
    gt_points: ClassVar[int | None] = None
    """Default points per ground-truth cloud; None: it writes none."""
    needs_next_view: ClassVar[bool] = True
    """Whether it reads the schema-version-3 next-view labels and grids."""
    split_use: ClassVar[str]
    """How their trainer uses train_split and test_split (the provenance's split line ends with it)."""

    def resolve(self, options: Options) -> Options:
        """The options with this layout's defaults; refuses a value it cannot use."""
        check_common(options)
        num_points = options.num_points
        if num_points is None and self.needs_points:
            raise StorageError(
                f"--layout {self.name}: give --points N, the points of every cloud (their trainer batches "
                "clouds of one size)"
            )
        if num_points is not None and self.points is None and not self.needs_points:
            raise StorageError(f"--points {num_points}: layout {self.name} writes no point clouds; leave it out")
        num_points = self.points if num_points is None else num_points
        if num_points is not None:
            check_points("--points", num_points)
        gt_points = options.gt_points
        if gt_points is not None and self.gt_points is None:
            raise StorageError(
                f"--gt-points {gt_points}: layout {self.name} writes no ground-truth clouds; leave it out"
            )
        gt_points = self.gt_points if gt_points is None else gt_points
        if gt_points is not None:
            check_points("--gt-points", gt_points)
        return replace(options, num_points=num_points, gt_points=gt_points)

    def check_dataset(self, dataset: Dataset) -> None:
        """Refuse a dataset whose samples this layout cannot write."""
        check_views(dataset)
        if self.needs_next_view and not dataset.has_next_view:
            raise StorageError(
                f"{dataset.url}: a version-{dataset.info.schema_version} dataset keeps no next-view labels or "
                f"occupancy grids, which --layout {self.name} writes; add them with `datagen shards relabel "
                f"{dataset.url} --out NEW_URL` (no re-imaging) and export NEW_URL"
            )

    @abstractmethod
    def skipped(self, dataset: Dataset) -> list[str]:
        """Per index row, why it is skipped (a key of `skip_reasons`), or "" when it is written."""

    @abstractmethod
    def start(self, run: Run) -> Writer:
        """A writer for one export."""

    def dataset_note(self, dataset: Dataset) -> str:
        """What the provenance's dataset line says of the labels this layout writes."""
        return ""


# -- checks ------------------------------------------------------------------------------------------


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


# -- names of folders --------------------------------------------------------------------------------


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
    taken = set(ROOT_FILES) | set(reserved)
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


# -- the output folder -------------------------------------------------------------------------------


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


# -- seeded streams ----------------------------------------------------------------------------------


def _digest(name: str) -> int:
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "little")


def sample_rng(seed: int, sample_id: str) -> np.random.Generator:
    """The stream that draws one sample's cloud: fixed by the seed and the sample id alone (the export's
    own, part of its documented format: not the (seed, epoch, index) streams of `storage.samples`,
    which depend on a dataset's order)."""
    return np.random.default_rng(np.random.SeedSequence([seed, _digest(sample_id)]))


GROUND_TRUTH_STREAM = 1
"""Appended to a task's stream so that its ground-truth draw never shares a sample's."""


def task_rng(seed: int, task_id: str) -> np.random.Generator:
    """The stream that draws a task's ground-truth cloud (one draw per task, shared by its samples)."""
    return np.random.default_rng(np.random.SeedSequence([seed, _digest(task_id), GROUND_TRUTH_STREAM]))


def draw(rng: np.random.Generator, count: int, size: int) -> tuple[npt.NDArray[np.int64], bool]:
    """``size`` of ``count`` indices, without replacement unless there are fewer; (indices, drawn with
    replacement)."""
    replace_ = count < size
    return rng.choice(count, size=size, replace=replace_), replace_


# -- text formats ------------------------------------------------------------------------------------


def cpp_text(values: npt.ArrayLike, columns: int = 1) -> str:
    """Values as C++'s ostream writes a double by default (6 significant digits, like ``%g``), ``columns``
    to a line separated by spaces: what the authors' generator writes. Each distinct value is
    formatted once (an occupancy grid holds a handful), so 32,768 lines cost a few milliseconds."""
    flat = np.asarray(values, dtype=np.float64).reshape(-1)
    if not flat.size:
        return ""
    unique, inverse = np.unique(flat, return_inverse=True)
    table = np.array([f"{value:g}" for value in unique.tolist()], dtype=object)
    rows = table[inverse].reshape(-1, columns)
    return "".join(" ".join(row) + "\n" for row in rows.tolist()) if columns > 1 else "\n".join(rows[:, 0]) + "\n"


def state_text(view_state: int) -> str:
    """The 32 lines 0/1 of a view state (line v: view v is in the case)."""
    return "".join(f"{bit}\n" for bit in mask_bits(view_state, AUTHORS_VIEWS).astype(int).tolist())


def ids_text(label: int) -> str:
    """A label's view ids, one per line, ascending."""
    return "".join(f"{v}\n" for v in np.flatnonzero(mask_bits(label, AUTHORS_VIEWS)).tolist())


def bits32(mask: int) -> npt.NDArray[np.float32]:
    """The 32 bits of a mask as float32 0/1 (a state or multi-hot label row)."""
    return mask_bits(mask, AUTHORS_VIEWS).astype(np.float32)


# -- provenance shared by every layout ---------------------------------------------------------------


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
