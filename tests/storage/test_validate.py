"""`storage.validate` finds each kind of corruption, naming the shard (and row), and passes a clean
dataset. Every case corrupts a fresh copy of one clean local dataset.

The clean dataset has the folder layout (version 4: a file per array and chunk), where each damage is
one file operation; the checks of a shard's content read it through `ShardReader` whatever its layout,
and the damages of the one-file layout (version 5) are at the end."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import zarr
from support import storage as fx

from schemas.index import CommitRecord
from schemas.shard import LABEL_COLUMN, MASKS, VIEW_STATE_COLUMN
from storage.checks import validate
from storage.dataset import commit_path, committed_tasks, finalise, fragment_path, shard_path
from storage.readers import open_dataset
from storage.shards import KEY_CHUNK_ROWS
from storage.store import open_location

LAYOUT = 4
"""The folder layout (see the module's docstring)."""


@pytest.fixture(scope="module")
def clean(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("validate") / "clean"
    fx.build_dataset(str(root), schema_version=LAYOUT)
    return root


@pytest.fixture
def ds(clean: Path, tmp_path: Path) -> Path:
    """A fresh copy of the clean dataset for one corruption."""
    return fx.copy_dataset(clean, tmp_path / "ds")


def first_task() -> str:
    """The task whose rows come first in the merged index (commit records are sorted by task id)."""
    return sorted(fx.task_ids())[0]


def payload_of(task_id: str):  # type: ignore[no-untyped-def]
    return next(p for p in fx.payloads(LAYOUT) if p.attributes.task_id == task_id)


SHARD = shard_path(first_task(), fx.ATTEMPT, LAYOUT)
FRAGMENT = fragment_path(first_task(), fx.ATTEMPT)


def group(root: Path, shard: str = SHARD) -> zarr.Group:
    return zarr.open_group(str(root / shard), mode="r+")


def problems(root: Path) -> list[str]:
    found = validate(str(root), full=True)
    assert found, "validate found nothing"
    return found


def lines_naming(found: list[str], *parts: str) -> list[str]:
    return [line for line in found if all(part in line for part in parts)]


def rewrite_fragment(root: Path, relative: str, column: str, values: list) -> None:  # type: ignore[type-arg]
    path = root / relative
    table = pq.read_table(path)
    table = table.set_column(
        table.schema.get_field_index(column),
        table.schema.field(column),
        pa.array(values, table.schema.field(column).type),
    )
    pq.write_table(table, path)


# -- clean ---------------------------------------------------------------------------------------


def test_clean_dataset_passes(clean: Path) -> None:
    assert validate(str(clean), full=True) == []
    assert validate(str(clean), full=False, seed=3) == []


def test_clean_finalised_dataset_passes(ds: Path) -> None:
    finalise(open_location(str(ds)))
    assert validate(str(ds), full=True) == []


def test_not_a_dataset_is_one_problem_line(tmp_path: Path) -> None:
    found = validate(str(tmp_path))
    assert len(found) == 1 and "not a datagen dataset" in found[0] and str(tmp_path) in found[0]


# -- truncated arrays ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["points_keys", "observed_keys", "refined_keys"])
def test_key_array_rewritten_shorter(ds: Path, name: str) -> None:
    array = group(ds)[name]
    assert isinstance(array, zarr.Array)
    array.resize((array.shape[0] - 100, 3))
    offsets = name.replace("_keys", "_offsets")
    assert lines_naming(problems(ds), SHARD, offsets, "truncated")


def test_gt_keys_with_the_wrong_shape(ds: Path) -> None:
    g = group(ds)
    gt = np.asarray(g["gt_keys"][...])
    del g["gt_keys"]
    g.create_array("gt_keys", data=gt[:, :2].copy())
    assert lines_naming(problems(ds), SHARD, "gt_keys")


# Only the sharded key arrays (more than KEY_CHUNK_ROWS rows; the shard index carries a CRC32C) are
# truncated here. A truncated single-chunk array (masks, offsets, gt_keys) is caught only by chance:
# numcodecs' Blosc decoder trusts the frame header and reads past the end of the short buffer
# (zarr-developers/numcodecs#228), so decoding sometimes "succeeds" with garbage. See the report.
@pytest.mark.parametrize("array", ["points_keys", "observed_keys", "refined_keys", "visible_keys"])
def test_chunk_file_truncated_on_disk(ds: Path, array: str) -> None:
    assert payload_of(first_task()).arrays[array].shape[0] > KEY_CHUNK_ROWS  # stored as a zarr shard
    chunks = sorted(p for p in (ds / SHARD / array / "c").rglob("*") if p.is_file())
    assert chunks, f"no chunk files under {array}"
    size = chunks[0].stat().st_size
    os.truncate(chunks[0], size // 2)
    assert lines_naming(problems(ds), SHARD, "truncated or corrupt")


ZARR_FILLS_MISSING_CHUNKS = (
    "storage/checks/validation.py _check_shard/_check_key_sets: zarr reads a missing or zero-length chunk file as the "
    "fill value (all-zero keys), so validate reports nothing and the reader returns zero points; validate should "
    "compare nchunks_initialized with nchunks and check that every key set is sorted and unique"
)


@pytest.mark.parametrize("damage", ["empty", "deleted"])
def test_chunk_file_emptied_or_deleted_on_disk(ds: Path, damage: str) -> None:
    chunk = ds / SHARD / "points_keys" / "c" / "0" / "0"
    assert chunk.is_file()
    if damage == "empty":
        os.truncate(chunk, 0)
    else:
        chunk.unlink()
    assert lines_naming(validate(str(ds), full=True), SHARD, "points_keys")


def test_shard_group_missing(ds: Path) -> None:
    shutil.rmtree(ds / SHARD)
    assert lines_naming(problems(ds), SHARD, "cannot open shard")


# -- offsets -------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["points_offsets", "observed_offsets", "visible_offsets"])
def test_non_monotone_offsets(ds: Path, name: str) -> None:
    g = group(ds)
    offsets = np.asarray(g[name][...])
    offsets[2], offsets[3] = offsets[3], offsets[2]
    assert offsets[3] < offsets[2]
    g[name][...] = offsets
    assert lines_naming(problems(ds), f"{SHARD} row 2:", name, "not monotone")


def test_offsets_not_ending_at_the_key_count(ds: Path) -> None:
    g = group(ds)
    offsets = np.asarray(g["points_offsets"][...])
    offsets[-1] += 5
    g["points_offsets"][...] = offsets
    assert lines_naming(problems(ds), SHARD, "points_offsets")


# -- index ---------------------------------------------------------------------------------------


def test_index_row_pointing_to_an_uncommitted_shard(ds: Path) -> None:
    orphan = shard_path(first_task(), "orphan", LAYOUT)
    shutil.copytree(ds / SHARD, ds / orphan)  # really on disk, but no commit record names it
    shards = pq.read_table(ds / FRAGMENT).column("shard").to_pylist()
    rewrite_fragment(ds, FRAGMENT, "shard", [orphan, *shards[1:]])
    found = problems(ds)
    assert lines_naming(found, "index row 0:", orphan, "no commit record")


def test_index_row_out_of_range(ds: Path) -> None:
    rows = pq.read_table(ds / FRAGMENT).column("row").to_pylist()
    rows[3] = len(rows) + 7
    rewrite_fragment(ds, FRAGMENT, "row", rows)
    assert lines_naming(problems(ds), "index row 3:", f"row {len(rows) + 7}", SHARD, "outside")


def point_row_5_nowhere(path: Path) -> None:
    table = pq.read_table(path)
    shards = table.column("shard").to_pylist()
    shards[5] = "shards/nowhere/a1.zarr"
    table = table.set_column(table.schema.get_field_index("shard"), table.schema.field("shard"), pa.array(shards))
    pq.write_table(table, path)


def test_dangling_row_in_a_finalised_index(ds: Path) -> None:
    """The index an earlier datagen finalised (`fx.finalise_as_before`)."""
    location = open_location(str(ds))
    fx.finalise_as_before(location)
    point_row_5_nowhere(ds / "index.parquet")
    assert lines_naming(problems(ds), "index row 5:", "shards/nowhere/a1.zarr")


def test_dangling_row_in_the_manifest(ds: Path) -> None:
    finalise(open_location(str(ds)))
    samples = json.loads((ds / "index" / "manifest.json").read_text())["segments"][0]["samples"]
    point_row_5_nowhere(ds / samples)
    assert lines_naming(problems(ds), samples, "row 5 ", "shards/nowhere/a1.zarr")


def test_fragment_missing(ds: Path) -> None:
    os.remove(ds / FRAGMENT)
    found = problems(ds)
    assert lines_naming(found, FRAGMENT, "cannot read index fragment")


def duplicate_task(ds: Path) -> tuple[str, int]:
    """Commit a second task whose shard and fragment copy the first task's; returns its shard and size."""
    task = first_task()
    copy_task = "0000000000000000-r9"  # sorts first, so the originals are the duplicates in the index
    copy_shard, copy_fragment = shard_path(copy_task, fx.ATTEMPT, LAYOUT), fragment_path(copy_task, fx.ATTEMPT)
    shutil.copytree(ds / SHARD, ds / copy_shard)
    shutil.copy(ds / FRAGMENT, ds / copy_fragment)
    count = payload_of(task).attributes.num_samples
    rewrite_fragment(ds, copy_fragment, "shard", [copy_shard] * count)
    record = CommitRecord(
        schema_version=1,
        task_id=copy_task,
        attempt_id=fx.ATTEMPT,
        shard=copy_shard,
        index_fragment=copy_fragment,
        num_samples=count,
    )
    (ds / commit_path(copy_task)).write_text(record.model_dump_json())
    assert len(committed_tasks(open_location(str(ds)))) == 3
    return copy_shard, count


def test_duplicate_sample_is_found(ds: Path) -> None:
    _, count = duplicate_task(ds)
    found = problems(ds)
    sample_ids = payload_of(first_task()).index_rows["sample_id"]
    duplicates = [line for line in found if "duplicate sample id" in line]
    assert len(duplicates) == count
    for sample in sample_ids:
        assert lines_naming(duplicates, sample)


def test_duplicate_sample_line_names_the_shards(ds: Path) -> None:
    copy_shard, count = duplicate_task(ds)
    duplicates = [line for line in problems(ds) if "duplicate sample id" in line]
    assert len(duplicates) == count
    for row, line in enumerate(duplicates):
        assert f"{SHARD} row {row}" in line and f"{copy_shard} row {row}" in line


@pytest.mark.parametrize("record", ["commit", "dataset.json"])
def test_unparsable_record_is_reported(ds: Path, record: str) -> None:
    relative = commit_path(first_task()) if record == "commit" else "dataset.json"
    (ds / relative).write_text('{"task_id": ')
    assert lines_naming(validate(str(ds), full=True), relative)


# -- masks and labels ----------------------------------------------------------------------------


def edit_masks(ds: Path, row: int, view_state: int | None = None, label: int | None = None) -> None:
    g = group(ds)
    masks = np.asarray(g[MASKS][...])
    if view_state is not None:
        masks[row, VIEW_STATE_COLUMN] = view_state
    if label is not None:
        masks[row, LABEL_COLUMN] = label
    g[MASKS][...] = masks


def original_masks(row: int) -> tuple[int, int]:
    view_state, label = payload_of(first_task()).arrays[MASKS][row]
    return int(view_state), int(label)


@pytest.mark.parametrize("column", ["label", "view_state"])
def test_mask_bits_beyond_the_view_count(ds: Path, column: str) -> None:
    n = fx.config().num_views
    row = 4
    view_state, label = original_masks(row)
    if column == "label":
        edit_masks(ds, row, label=label | (1 << (n + 3)))
    else:
        edit_masks(ds, row, view_state=view_state | (1 << 63))
    assert lines_naming(problems(ds), f"{SHARD} row {row}:", f"beyond the {n} views")


def test_label_overlapping_the_input(ds: Path) -> None:
    row = next(r for r in range(10) if original_masks(r)[1])
    view_state, label = original_masks(row)
    edit_masks(ds, row, label=label | (view_state & -view_state))
    found = problems(ds)
    assert lines_naming(found, f"{SHARD} row {row}:", "label shares views with the input")


def test_label_that_is_not_a_cover(ds: Path) -> None:
    masks = payload_of(first_task()).arrays[MASKS]
    row = int(np.flatnonzero(masks[:, LABEL_COLUMN])[-1])  # the last row whose label is non-empty
    view_state, label = original_masks(row)
    edit_masks(ds, row, label=label & (label - 1))  # drop the label's lowest view
    found = problems(ds)
    assert lines_naming(found, f"{SHARD} row {row}:", "uncovered")
    assert len(found) == 1
    # The reader itself does not check: it serves the corrupted label as stored.
    reopened = open_dataset(str(ds))
    i = reopened.index.column("sample_id").to_pylist().index(payload_of(first_task()).index_rows["sample_id"][row])
    assert reopened.masks(i) == (view_state, label & (label - 1))


def test_commit_record_disagreeing_with_the_shard(ds: Path) -> None:
    path = ds / commit_path(first_task())
    record = json.loads(path.read_text())
    record["num_samples"] += 1
    path.write_text(json.dumps(record))
    found = problems(ds)
    assert lines_naming(found, SHARD, "disagree with the commit record")
    assert lines_naming(found, FRAGMENT, "rows for")


# -- the records behind the lines ----------------------------------------------------------------


def test_problems_are_records_and_repair_sorts_them_whatever_their_wording(ds: Path) -> None:
    """A truncated chunk, a deleted commit record under a finalised index, a damaged failure record and a
    stale merged index: each problem names its file, task, array and place, and what mends it; sorting
    them for repair gives the same tasks, index and rest when every message is reworded."""
    import dataclasses

    from storage import Mend, Problem
    from storage.checks import sort_problems, validate_dataset
    from storage.dataset import MANIFEST_FILE

    finalise(open_location(str(ds)))
    first, second = sorted(fx.task_ids())
    chunk = next(p for p in sorted((ds / SHARD).rglob("*")) if p.is_file() and "/c/" in str(p) and "points" in str(p))
    chunk.write_bytes(chunk.read_bytes()[:7])
    (ds / commit_path(second)).unlink()
    (ds / "failures").mkdir(exist_ok=True)
    (ds / "failures" / "deadbeefdeadbeef-r0.json").write_text("{not json")
    found = validate_dataset(str(ds), full=True).problems
    assert all(isinstance(p, Problem) and p.line == str(p) for p in found)
    by_task = {p.task for p in found if p.mend is Mend.TASK}
    assert by_task == {first, second, "deadbeefdeadbeef-r0"}
    shard_problem = next(p for p in found if p.task == first)
    assert shard_problem.file.startswith(SHARD) and shard_problem.kind in ("array", "shard")
    lost = next(p for p in found if p.task == second)
    assert (lost.file, lost.kind, lost.mend) == (MANIFEST_FILE, "index", Mend.TASK)
    sorted_once = sort_problems(found)
    reworded = [dataclasses.replace(p, message=f"reworded {n}") for n, p in enumerate(found)]
    sorted_again = sort_problems(reworded)
    assert {t: len(ps) for t, ps in sorted_again.tasks.items()} == {t: len(ps) for t, ps in sorted_once.tasks.items()}
    assert len(sorted_again.index) == len(sorted_once.index) and len(sorted_again.other) == len(sorted_once.other)
    assert [p.line.split(": ", 1)[1] for p in reworded] == [f"reworded {n}" for n in range(len(found))]


def test_an_unreachable_store_is_its_own_error_not_a_problem(tmp_path: Path) -> None:
    from storage import StorageError, StoreUnreachable
    from storage.store import storage_failure

    error = storage_failure("s3://bucket/data", ConnectionRefusedError("connection refused"))
    assert isinstance(error, StoreUnreachable) and isinstance(error, StorageError)
    local = storage_failure(str(tmp_path / "x"), PermissionError("denied"))
    assert isinstance(local, StoreUnreachable) and "check the path and its permissions" in str(local)


# -- the one-file layout (version 5) ---------------------------------------------------------------


@pytest.fixture(scope="module")
def clean_zip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("validate-zip") / "clean"
    fx.build_dataset(str(root))
    return root


@pytest.fixture
def zds(clean_zip: Path, tmp_path: Path) -> Path:
    return fx.copy_dataset(clean_zip, tmp_path / "zds")


ZIP_SHARD = shard_path(first_task(), fx.ATTEMPT)


def test_clean_one_file_dataset_passes(clean_zip: Path) -> None:
    assert ZIP_SHARD.endswith(".zarr.zip") and (clean_zip / ZIP_SHARD).is_file()
    assert validate(str(clean_zip), full=True) == []


ZIP_DAMAGES = {
    "deleted": (lambda p: p.unlink(), "cannot open shard"),
    "emptied": (lambda p: os.truncate(p, 0), "cannot open shard"),
    "truncated": (lambda p: os.truncate(p, p.stat().st_size // 2), "cannot open shard"),
    "directory overwritten": (lambda p: p.write_bytes(p.read_bytes()[:-22] + bytes(22)), "cannot open shard"),
    "member lost": (lambda p: fx.zip_without(p, "points_keys/c/0/0"), "points_keys"),
    "array metadata lost": (lambda p: fx.zip_without(p, "masks/zarr.json"), "masks"),
    "member corrupt": (lambda p: fx.corrupt_member(p, "masks/c/0/0"), "truncated or corrupt"),
    "key shard corrupt": (lambda p: fx.corrupt_member(p, "points_keys/c/0/0"), "truncated or corrupt"),
}


@pytest.mark.parametrize("damage", sorted(ZIP_DAMAGES))
def test_a_damaged_shard_file_is_named(zds: Path, damage: str) -> None:
    make, says = ZIP_DAMAGES[damage]
    make(zds / ZIP_SHARD)
    assert lines_naming(problems(zds), ZIP_SHARD, says)


def test_a_wrong_label_in_a_shard_file_is_named(zds: Path) -> None:
    masks = payload_of(first_task()).arrays[MASKS]
    row = int(np.flatnonzero(masks[:, LABEL_COLUMN])[-1])
    label = int(masks[row, LABEL_COLUMN])

    def drop_a_view(values: np.ndarray) -> np.ndarray:
        values[row, LABEL_COLUMN] = label & (label - 1)
        return values

    fx.edit_array(zds / ZIP_SHARD, MASKS, drop_a_view)
    assert lines_naming(problems(zds), f"{ZIP_SHARD} row {row}:", "uncovered")
