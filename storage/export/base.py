"""The export's base types: what an export is given (`Run`), what it wrote (`Export`), where a sample
goes (`Place`), a layout (`Layout`) and its writer (`Writer`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

from storage.export.checks import check_common, check_points, check_views
from storage.export.options import EMPTY_LABEL, NO_POINTS, Options
from storage.readers.reader import Dataset, Sample
from storage.store.location import StorageError

Progress = Callable[[int, int], None]
"""Called with (samples done, samples in the dataset) after each sample."""


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
    def write(self, place: Place, sample: Sample) -> None:
        """Write the sample's files (its folder exists): ``sample`` holds the layout's `Layout.fields`,
        read through storage's field registry (`storage.readers.Dataset.sample`)."""

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
    fields: ClassVar[tuple[str, ...]] = ()
    """What its writer reads of each sample: registered sample fields (`storage.samples.SAMPLE_FIELDS`)
    and ``"observed"``, as `storage.readers.Dataset.sample` gives them (view sets as bools per view,
    clouds whole in metres); none: the sample's id alone."""

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
