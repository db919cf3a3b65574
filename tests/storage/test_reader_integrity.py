"""Readers never serve a damaged dataset: `open_dataset`, ``Dataset[i]``, iteration and
`OSVPDataset` raise one `StorageError` line naming the file (relative to the dataset), the dataset
URL and the fix (`datagen shards validate URL`), for every kind of damage `storage.validate` sees.

Every case damages a fresh copy of one small finalised dataset (two built-ins, `support.storage`).
Before these checks, a deleted chunk file read back as zeros, a deleted commit record silently
dropped a task, and a truncated file raised a bare ``ValueError``/``KeyError``/``ArrowInvalid``.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from support import storage as fx

from schemas.index import FailureRecord
from schemas.version import SCHEMA_VERSION
from storage import StorageError
from storage.checks import validate
from storage.dataset import (
    ADDING_FILE,
    commit_path,
    failure_path,
    finalise,
    fragment_path,
    mark_adding,
    read_failures,
    shard_path,
    write_failure,
)
from storage.readers import Dataset, open_dataset
from storage.store import open_location

FIRST, SECOND = sorted(fx.task_ids())
FOLDER_LAYOUT = 4
"""A layout storing each array and chunk as a file of its own: the damages of one file of a shard."""
SHARD = shard_path(FIRST, fx.ATTEMPT, FOLDER_LAYOUT)
ZIP_SHARD = shard_path(FIRST, fx.ATTEMPT)
FRAGMENT = fragment_path(FIRST, fx.ATTEMPT)
FIX = "datagen shards validate"


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("integrity") / "clean"
    fx.build_dataset(str(root), finalise_index=True)
    return root


@pytest.fixture
def ds(clean: Path, tmp_path: Path) -> Path:
    return fx.copy_dataset(clean, tmp_path / "ds")


@pytest.fixture(scope="module")
def clean_folders(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("integrity") / "folders"
    fx.build_dataset(str(root), finalise_index=True, schema_version=FOLDER_LAYOUT)
    return root


@pytest.fixture
def fds(clean_folders: Path, tmp_path: Path) -> Path:
    """A copy of the dataset in the folder layout."""
    return fx.copy_dataset(clean_folders, tmp_path / "fds")


def assert_one_line(error: BaseException, root: Path, *parts: str) -> str:
    """The error is a StorageError, one line, naming the dataset, ``parts`` and the fix."""
    assert isinstance(error, StorageError), repr(error)
    message = str(error)
    assert "\n" not in message, message
    for part in (str(root), *parts, f"{FIX} {root}"):
        assert part in message, (part, message)
    return message


def assert_validate_names(root: Path, *parts: str) -> None:
    """`validate` reports the damage as a problem line (it never raises on a damaged file)."""
    found = validate(str(root), full=True)
    assert [line for line in found if all(part in line for part in parts)], found


def rows_of(dataset: Dataset, task_id: str) -> list[int]:
    return np.flatnonzero(pc.equal(dataset.index.column("task_id"), task_id).to_numpy(zero_copy_only=False)).tolist()


def chunk(root: Path, array: str, shard: str = SHARD) -> Path:
    found = sorted(p for p in (root / shard / array / "c").rglob("*") if p.is_file())
    assert len(found) == 1, found
    return found[0]


# -- point 2: a shard with a missing, emptied or truncated file ----------------------------------------


def delete_chunk(root: Path, array: str) -> None:
    chunk(root, array).unlink()


def empty_chunk(root: Path, array: str) -> None:
    os.truncate(chunk(root, array), 0)


def truncate_chunk(root: Path, array: str) -> None:
    path = chunk(root, array)
    os.truncate(path, path.stat().st_size // 2)


def unreadable_metadata(root: Path, metadata: str) -> None:
    (root / SHARD / metadata).write_text('{"zarr_format": ')


PARTIAL = f"{SHARD}/points_keys/c/0/0.0123456789abcdef0123456789abcdef.partial"
"""The temporary of an interrupted chunk write (one of `LEFTOVERS`)."""


def partial_beside_a_deleted_chunk(root: Path) -> None:
    """The chunk file gone, its whole content left in a ``.partial`` temporary beside it."""
    stored = chunk(root, "points_keys")
    (root / PARTIAL).write_bytes(stored.read_bytes())
    stored.unlink()


@dataclass(frozen=True)
class ShardDamage:
    """One way to damage the first task's shard, and what reading a row of it must then say."""

    damage: Callable[[Path], None]
    names: tuple[str, ...]
    """Parts of the `StorageError` line, beside the dataset and the fix (`assert_one_line`)."""
    validate_names: tuple[str, ...]
    """Parts of one `validate` problem line (`validate` never raises on a damaged file)."""
    lost_chunk: bool = False
    """A chunk file lost (not fill values): the line also names the repair, and the other task still reads."""


SHARD_DAMAGES: dict[str, ShardDamage] = {
    **{
        f"{how}-{array}": ShardDamage(partial(damage, array=array), (SHARD, array), (SHARD, array), lost_chunk=True)
        for how, damage in (("deleted", delete_chunk), ("emptied", empty_chunk))
        for array in ("points_keys", "masks", "observed_offsets")
    },
    **{
        f"truncated-{array}": ShardDamage(
            partial(truncate_chunk, array=array),
            (f"{SHARD}/{array}", "truncated or corrupt"),
            (SHARD, "truncated or corrupt"),
        )
        for array in ("points_keys", "masks")
    },
    "missing array": ShardDamage(
        lambda root: shutil.rmtree(root / SHARD / "points_keys"), (SHARD, "points_keys"), (SHARD, "points_keys")
    ),
    **{
        f"unreadable {metadata}": ShardDamage(
            partial(unreadable_metadata, metadata=metadata), (SHARD, metadata), (SHARD, "metadata")
        )
        for metadata in ("zarr.json", "points_keys/zarr.json")
    },
    "missing shard group": ShardDamage(
        lambda root: shutil.rmtree(root / SHARD), (SHARD, "missing"), (SHARD, "cannot open shard")
    ),
    "partial file does not stand in for a deleted chunk": ShardDamage(
        partial_beside_a_deleted_chunk, (SHARD, "points_keys"), (SHARD, "points_keys")
    ),
}


@pytest.mark.parametrize("case", list(SHARD_DAMAGES))
def test_damaged_shard_is_one_line_naming_it(fds: Path, case: str) -> None:
    ds = fds
    damage = SHARD_DAMAGES[case]
    damage.damage(ds)
    dataset = open_dataset(str(ds))  # the index is intact: opening works
    with pytest.raises(StorageError) as caught:
        dataset[rows_of(dataset, FIRST)[0]]
    repair = (f"datagen shards repair {ds}",) if damage.lost_chunk else ()
    assert_one_line(caught.value, ds, *damage.names, *repair)
    if damage.lost_chunk:  # the intact task still reads
        assert len(dataset[rows_of(dataset, SECOND)[0]]["points"]) > 0
    assert_validate_names(ds, *damage.validate_names)


ZIP_DAMAGES: dict[str, tuple[Callable[[Path], None], tuple[str, ...]]] = {
    "deleted": (lambda p: p.unlink(), ("missing",)),
    "emptied": (lambda p: os.truncate(p, 0), ("not a readable ZIP",)),
    "truncated": (lambda p: os.truncate(p, p.stat().st_size // 2), ("not a readable ZIP",)),
    "member lost": (lambda p: fx.zip_without(p, "points_keys/c/0/0"), ("points_keys", "truncated")),
    "member corrupt": (lambda p: fx.corrupt_member(p, "masks/c/0/0"), ("masks", "truncated or corrupt")),
    "group metadata corrupt": (lambda p: fx.corrupt_member(p, "zarr.json"), ("zarr.json",)),
}
"""Damages of a one-file shard (layout 5) and what the reader's line says beside the shard's path."""


@pytest.mark.parametrize("case", sorted(ZIP_DAMAGES))
def test_damaged_shard_file_is_one_line_naming_it(ds: Path, case: str) -> None:
    damage, names = ZIP_DAMAGES[case]
    damage(ds / ZIP_SHARD)
    dataset = open_dataset(str(ds))
    with pytest.raises(StorageError) as caught:
        dataset[rows_of(dataset, FIRST)[0]]
    assert_one_line(caught.value, ds, ZIP_SHARD, *names, f"datagen shards repair {ds}")
    assert len(dataset[rows_of(dataset, SECOND)[0]]["points"]) > 0  # the intact task still reads
    assert_validate_names(ds, ZIP_SHARD)


def test_missing_chunk_file_stops_iteration_and_the_torch_dataset(fds: Path) -> None:
    from torch.utils.data import DataLoader

    from storage.torch import OSVPDataset

    ds = fds
    delete_chunk(ds, "points_keys")
    dataset = open_dataset(str(ds))
    with pytest.raises(StorageError) as caught:
        for _ in dataset.iter_shuffled(seed=0):
            pass
    assert_one_line(caught.value, ds, SHARD, "points_keys")
    torch_dataset = OSVPDataset(str(ds), num_points=64)
    row = rows_of(torch_dataset.dataset, FIRST)[0]
    with pytest.raises(StorageError) as caught:
        torch_dataset[row]
    assert_one_line(caught.value, ds, SHARD, "points_keys")
    with pytest.raises(StorageError):  # re-raised in the parent from a worker process
        for _ in DataLoader(torch_dataset, batch_size=16, num_workers=1, multiprocessing_context="fork"):
            pass


def test_each_shard_is_listed_once_per_reader(ds: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The whole-shard check costs one listing per shard per reader, however often the shard
    drops out of the cache (and selections share what their parent verified)."""
    import storage.readers.reader as reader_module  # the reader's own cache size (an internal)
    from storage.shards import ShardReader

    verified: list[str] = []
    original = ShardReader.verify

    def counting(self: ShardReader) -> None:
        verified.append(self.relative)
        original(self)

    monkeypatch.setattr(ShardReader, "verify", counting)
    monkeypatch.setattr(reader_module, "SHARD_CACHE", 1)
    dataset = open_dataset(str(ds))
    order = [rows_of(dataset, FIRST)[0], rows_of(dataset, SECOND)[0]] * 3
    for i in order:
        dataset[i]
    dataset.select(order)[0]
    assert sorted(verified) == sorted({ZIP_SHARD, shard_path(SECOND, fx.ATTEMPT)})


# -- point 3: the finalised index agrees with the commit records -----------------------------------------
#
# Two finalised indexes: the manifest `finalise` writes (``index/manifest.json`` and its segments), and
# the one earlier code wrote (``index.json`` and ``index.parquet``; `fx.finalise_as_before`), which
# datasets made then still hold and readers still follow.

MANIFEST = "index/manifest.json"


@pytest.fixture
def lds(ds: Path) -> Path:
    """The dataset as an earlier datagen finalised it."""
    fx.finalise_as_before(open_location(str(ds)))
    return ds


def segment(root: Path) -> tuple[Path, Path]:
    """The (tasks, samples) tables of the dataset's one segment."""
    (only,) = json.loads((root / MANIFEST).read_text())["segments"]
    return root / only["tasks"], root / only["samples"]


@pytest.mark.parametrize("index", ["manifest while a job adds", "before the manifest"])
def test_deleted_commit_record_refuses_the_finalised_index(ds: Path, index: str) -> None:
    """Where readers list the commit records (a job adds to the dataset, or an earlier datagen's index),
    a finalised task without one is refused; validate names it."""
    from storage.torch import OSVPDataset

    named = MANIFEST
    if index != "manifest while a job adds":
        fx.finalise_as_before(open_location(str(ds)))
        named = "index.json"
    else:
        mark_adding(open_location(str(ds)))
    os.remove(ds / commit_path(FIRST))
    for open_it in (open_dataset, OSVPDataset):
        with pytest.raises(StorageError) as caught:
            open_it(str(ds))
        assert_one_line(caught.value, ds, named, FIRST, commit_path(FIRST))
    found = validate(str(ds), full=True)
    assert [line for line in found if FIRST in line and named in line and "no commit record" in line]


def test_a_finished_manifest_is_the_dataset_read_without_listing_the_commit_records(
    ds: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No job adds to it (a finished job's finalise took its marker away): opening reads the manifest and
    never lists ``commits/`` (100 requests at 100,000 tasks on S3). A commit record lost since then does
    not stop reading the samples, which are intact; validate names it and repair's fix stands."""
    from storage.store import Location

    assert not (ds / ADDING_FILE).exists()
    listed: list[str] = []
    listdir = Location.listdir

    def spy(self: Location, relative: str) -> list[str]:
        listed.append(relative)
        return listdir(self, relative)

    monkeypatch.setattr(Location, "listdir", spy)
    assert len(open_dataset(str(ds))) == fx.total_samples() and "commits" not in listed
    os.remove(ds / commit_path(FIRST))
    dataset = open_dataset(str(ds))
    assert len(dataset) == fx.total_samples() and dataset[0]["points"].size
    found = validate(str(ds), full=True)
    assert [line for line in found if FIRST in line and MANIFEST in line and "no commit record" in line]
    mark_adding(open_location(str(ds)))  # a job starts adding: now the lost record is seen on opening
    with pytest.raises(StorageError):
        open_dataset(str(ds))


def test_deleted_commit_record_of_a_dataset_never_finalised_still_reads(ds: Path) -> None:
    """No finalised index (a job still running): the commit records are all there is to follow."""
    shutil.rmtree(ds / "index")
    os.remove(ds / commit_path(FIRST))
    dataset = open_dataset(str(ds))
    assert set(dataset.index.column("task_id").to_pylist()) == {SECOND}
    assert validate(str(ds), full=True) == []


@pytest.mark.parametrize("index", ["manifest", "before the manifest"])
def test_task_committed_after_finalise_reads_and_validate_says_the_index_is_stale(tmp_path: Path, index: str) -> None:
    first, second = (next(p for p in fx.payloads() if p.attributes.task_id == t) for t in (FIRST, SECOND))
    root = tmp_path / "grown"
    location = fx.build_dataset(str(root), task_payloads=[first], finalise_index=True)
    if index != "manifest":
        fx.finalise_as_before(location)
    fx.build_dataset(str(root), task_payloads=[second])  # a resumed job, not finalised yet
    assert len(open_dataset(str(root))) == fx.total_samples()
    found = validate(str(root), full=True)
    assert len(found) == 1 and commit_path(SECOND) in found[0] and "not in the finalised index" in found[0]
    finalise(location)
    assert validate(str(root), full=True) == []
    assert sorted(open_dataset(str(root)).index.column("task_id").to_pylist()) == sorted(
        open_dataset(str(root)).select(range(fx.total_samples())).index.column("task_id").to_pylist()
    )


def drop_index_rows(path: Path, task_id: str, keep: int) -> None:
    table = pq.read_table(path)
    mask = pc.equal(table.column("task_id"), task_id).to_numpy(zero_copy_only=False)
    rows = np.flatnonzero(~mask).tolist() + np.flatnonzero(mask)[:keep].tolist()
    pq.write_table(table.take(sorted(rows)), path)


def test_index_rows_differing_from_the_commit_record_are_refused(lds: Path) -> None:
    ds = lds
    drop_index_rows(ds / "index.parquet", FIRST, keep=3)
    with pytest.raises(StorageError) as caught:
        open_dataset(str(ds))
    message = assert_one_line(caught.value, ds, "index.parquet", FIRST)
    assert "has 3 rows" in message
    found = validate(str(ds), full=True)
    assert [line for line in found if line.startswith("index.parquet:") and FIRST in line and "has 3 rows" in line]


def test_a_samples_table_missing_rows_is_refused(ds: Path) -> None:
    """A reader checks each samples table's row count (its footer) against the manifest; validate names
    the task whose rows are missing."""
    _, samples = segment(ds)
    drop_index_rows(samples, FIRST, keep=3)
    relative = str(samples.relative_to(ds))
    with pytest.raises(StorageError) as caught:
        open_dataset(str(ds))
    assert_one_line(caught.value, ds, relative, MANIFEST, "rows")
    found = validate(str(ds), full=True)
    assert [line for line in found if line.startswith(f"{relative}:") and FIRST in line and "has 3 rows" in line]


def test_index_naming_another_attempt_is_refused(lds: Path) -> None:
    ds = lds
    coverage = json.loads((ds / "index.json").read_text())
    coverage[FIRST] = "someone-else"
    (ds / "index.json").write_text(json.dumps(coverage))
    with pytest.raises(StorageError) as caught:
        open_dataset(str(ds))
    assert_one_line(caught.value, ds, "index.json", FIRST, "someone-else")
    assert [line for line in validate(str(ds), full=True) if "index.json" in line and FIRST in line]


def test_a_manifest_naming_another_attempt_is_a_validate_problem(ds: Path) -> None:
    """A reader trusts the manifest's attempts (checking them would read every commit record: a request
    per task); validate compares each with its record."""
    tasks, _ = segment(ds)
    table = pq.read_table(tasks)
    attempts = [
        "someone-else" if t == FIRST else a
        for t, a in zip(*(table.column(c).to_pylist() for c in ("task_id", "attempt_id")), strict=True)
    ]
    pq.write_table(
        table.set_column(table.schema.get_field_index("attempt_id"), "attempt_id", pa.array(attempts)), tasks
    )
    assert len(open_dataset(str(ds))) == fx.total_samples()
    assert [
        line for line in validate(str(ds), full=True) if MANIFEST in line and FIRST in line and "someone-else" in line
    ]


def test_stale_failure_beside_a_commit_is_a_warning(ds: Path) -> None:
    from storage.checks import validate_dataset

    record = FailureRecord(
        schema_version=SCHEMA_VERSION, task_id=FIRST, object_name="capsule", origin="o.txt:1", message="boom"
    )
    location = open_location(str(ds))
    write_failure(location, record)  # committed already: not written
    assert read_failures(location) == []
    (ds / failure_path(FIRST)).parent.mkdir(exist_ok=True)
    (ds / failure_path(FIRST)).write_text(record.model_dump_json())  # a writer killed before removing it
    found = validate_dataset(str(ds), full=True)
    assert found.problems == []
    assert len(found.warnings) == 1 and failure_path(FIRST) in found.warnings[0] and "stale" in found.warnings[0]
    assert len(open_dataset(str(ds))) == fx.total_samples()


# -- point 4: a damaged dataset-level file is named ------------------------------------------------------


def truncate(path: Path) -> None:
    os.truncate(path, path.stat().st_size // 2)


def unfinalised(root: Path) -> None:
    shutil.rmtree(root / "index")


FILE_DAMAGES: dict[str, tuple[str, Callable[[Path], None]]] = {
    "truncated manifest": (MANIFEST, lambda root: truncate(root / MANIFEST)),
    "truncated tasks table": ("index/tasks-", lambda root: truncate(segment(root)[0])),
    "truncated samples table": ("index/samples-", lambda root: truncate(segment(root)[1])),
    "truncated index.parquet": (
        "index.parquet",
        lambda root: (fx.finalise_as_before(open_location(str(root))), truncate(root / "index.parquet")),
    ),
    "truncated index.json": (
        "index.json",
        lambda root: (fx.finalise_as_before(open_location(str(root))), truncate(root / "index.json")),
    ),
    "truncated commit record (not finalised)": (
        commit_path(FIRST),
        lambda root: (unfinalised(root), truncate(root / commit_path(FIRST))),
    ),
    "empty commit record (not finalised)": (
        commit_path(FIRST),
        lambda root: (unfinalised(root), os.truncate(root / commit_path(FIRST), 0)),
    ),
    "truncated dataset.json": ("dataset.json", lambda root: truncate(root / "dataset.json")),
    "missing dataset.json": ("dataset.json", lambda root: os.remove(root / "dataset.json")),
    "truncated fragment (not finalised)": (FRAGMENT, lambda root: (unfinalised(root), truncate(root / FRAGMENT))),
    "missing fragment (not finalised)": (FRAGMENT, lambda root: (unfinalised(root), os.remove(root / FRAGMENT))),
}


@pytest.mark.parametrize("damage", sorted(FILE_DAMAGES))
def test_damaged_file_is_one_line_naming_it(ds: Path, damage: str) -> None:
    from storage.torch import OSVPDataset

    relative, make = FILE_DAMAGES[damage]
    make(ds)
    for open_it in (open_dataset, OSVPDataset):
        with pytest.raises(StorageError) as caught:
            open_it(str(ds))
        assert_one_line(caught.value, ds, f": {relative}")
    found = validate(str(ds), full=True)  # never raises
    assert [line for line in found if relative in line], found


def test_a_damaged_commit_record_under_the_manifest_is_a_validate_problem(ds: Path, clean: Path) -> None:
    """Opening a finalised dataset lists the commit records but reads none (a request per task): the
    manifest holds what they say, and the samples read as before; validate reads every record."""
    truncate(ds / commit_path(FIRST))
    dataset, reference = open_dataset(str(ds)), open_dataset(str(clean))
    assert dataset.index.equals(reference.index)
    np.testing.assert_array_equal(dataset[0]["points"], reference[0]["points"])
    assert [line for line in validate(str(ds), full=True) if commit_path(FIRST) in line]


def test_unparsable_failure_record_is_named(ds: Path) -> None:
    (ds / "failures").mkdir()
    (ds / failure_path("0000000000000000-r0")).write_text('{"task_id": ')
    with pytest.raises(StorageError) as caught:
        open_dataset(str(ds)).failures()
    assert_one_line(caught.value, ds, failure_path("0000000000000000-r0"))
    assert [line for line in validate(str(ds), full=True) if failure_path("0000000000000000-r0") in line]


# -- point 5: leftovers of interrupted writes ------------------------------------------------------------

LEFTOVERS = (
    "dataset.json.tmp-0123456789abcdef0123456789abcdef",
    "index.parquet.tmp-0123456789abcdef0123456789abcdef",
    f"{commit_path(FIRST)}.tmp-0123456789abcdef0123456789abcdef",
    f"{FRAGMENT}.tmp-0123456789abcdef0123456789abcdef",
)
LAYOUT_LEFTOVERS = {
    "folders": PARTIAL,
    "one file": f"{ZIP_SHARD}.tmp-0123456789abcdef0123456789abcdef",
}
"""What an interrupted shard write leaves: zarr's temporary of a chunk file (folder layout), the atomic
write's temporary of the whole shard file (one-file layout)."""


@pytest.mark.parametrize("layout", sorted(LAYOUT_LEFTOVERS))
def test_temporary_leftovers_are_warnings_and_never_read(
    ds: Path, clean: Path, fds: Path, clean_folders: Path, layout: str
) -> None:
    from storage.checks import validate_dataset

    if layout == "folders":
        ds, clean = fds, clean_folders
    leftovers = (*LEFTOVERS, LAYOUT_LEFTOVERS[layout])
    for relative in leftovers:
        (ds / relative).write_bytes(b"partial")
    found = validate_dataset(str(ds), full=True)
    assert found.problems == []
    assert len(found.warnings) == len(leftovers)
    for relative in leftovers:
        assert [line for line in found.warnings if line.startswith(f"{relative}: ") and "safe to delete" in line]
    dataset, reference = open_dataset(str(ds)), open_dataset(str(clean))
    assert dataset.index.equals(reference.index)
    for i in range(len(dataset)):
        np.testing.assert_array_equal(dataset[i]["points"], reference[i]["points"])


def test_a_failed_atomic_write_leaves_no_temporary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A full disk fails the write; the partial temporary file is removed, not left in the dataset."""

    def full_disk(_: int) -> None:
        raise OSError(28, "No space left on device")

    location = open_location(str(tmp_path / "ds"))
    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError, match="No space left"):
        location.write_atomic("index.json", b"{}")
    with pytest.raises(OSError, match="No space left"):
        location.create_exclusive("commits/x.json", b"{}")
    assert [p for p in (tmp_path / "ds").rglob("*") if p.is_file()] == []
