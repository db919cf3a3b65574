"""``datagen shards validate`` and ``datagen shards relabel`` through the CLI, on a dataset the engine
wrote (local, and a copy in fsspec's memory filesystem), plus the label checker's own solver against
the brute-force oracle of tests/support/setcover_oracle.py.

Every corruption is made on a fresh copy of the shared dataset, never on the dataset itself.
"""

from __future__ import annotations

import itertools
import json
import os
import shutil
import uuid
from contextlib import AbstractContextManager
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import zarr
from click.testing import Result
from support import storage as fx
from support.engine import assert_same_samples
from support.setcover_oracle import oracle_cover, oracle_minimal
from support.shards import (
    EngineDataset,
    copy_to_memory,
    engine_dataset,  # noqa: F401
)
from typer.testing import CliRunner

from datagen.cli.main import app
from datagen.inspection import label_check
from datagen.inspection.cover_check import TaskRows, expected_label, lexicographic_rank
from datagen.inspection.label_check import views_text
from datagen.pipeline.coverage import coverage_table
from datagen.pipeline.keys import pack_keys
from datagen.pipeline.task import sample_id
from schemas.dataset import DatasetInfo
from schemas.index import CommitRecord
from schemas.shard import LABEL_COLUMN, MASKS, VIEW_STATE_COLUMN
from schemas.version import SCHEMA_VERSION
from storage import StorageError, committed_tasks, open_dataset, open_location, read_failures, undominated
from storage.checks import SAMPLED_ROWS_PER_SHARD
from storage.dataset import commit_path, fragment_path, mark_adding, shard_path
from storage.samples import mask_views, visibility_judge
from storage.shards import KEY_CHUNK_ROWS, ShardReader

runner = CliRunner()
WHERE = ["local", "memory"]


def shards(*args: str) -> Result:
    return runner.invoke(app, ["shards", *args])


def url_of(dataset: EngineDataset, where: str) -> str:
    return dataset.url if where == "local" else dataset.memory_url


def problem_lines(result: Result) -> list[str]:
    """Every output line but the closing two: the count of problems and the fix."""
    closing = result.output.splitlines()[-2:]
    assert closing[-1].startswith("fix: "), result.output  # a damaged dataset names its fix (issue 52)
    return result.output.splitlines()[:-2]


def lines_with(result: Result, *parts: str) -> list[str]:
    return [line for line in result.output.splitlines() if all(part in line for part in parts)]


def info_of(url: str) -> DatasetInfo:
    location = open_location(url)
    return DatasetInfo.model_validate_json(location.read_bytes("dataset.json"))


# -- corrupting a copy -----------------------------------------------------------------------------------


@pytest.fixture
def ds(engine_dataset: EngineDataset, tmp_path: Path) -> Path:  # noqa: F811
    """A fresh local copy of the engine's dataset for one corruption."""
    return Path(shutil.copytree(engine_dataset.url, tmp_path / "ds"))


def first(root: Path) -> CommitRecord:
    """The first committed task: its rows come first in the finalised index."""
    return committed_tasks(open_location(str(root)))[0]


def group(root: Path, record: CommitRecord) -> AbstractContextManager[zarr.Group]:
    """The task's shard group through zarr, written back when the block ends (`fx.shard_group`)."""
    return fx.shard_group(root / record.shard, mode="r+")


def validate_all(root: Path | str) -> Result:
    result = shards("validate", str(root), "--all")
    assert result.exit_code == 1, result.output
    return result


def rewrite_parquet(path: Path, column: str, values: list) -> None:  # type: ignore[type-arg]
    table = pq.read_table(path)
    field = table.schema.field(column)
    table = table.set_column(table.schema.get_field_index(column), field, pa.array(values, field.type))
    pq.write_table(table, path)


def stored_masks(root: Path, record: CommitRecord) -> np.ndarray:
    return fx.stored_array(root / record.shard, MASKS)


def write_label(root: Path, record: CommitRecord, row: int, label: int, index: bool = True) -> None:
    """Replace one stored label in the shard and, unless told otherwise, in the index (label and size)."""
    with group(root, record) as g:
        masks = np.asarray(g[MASKS][...])
        masks[row, LABEL_COLUMN] = label
        g[MASKS][...] = masks
    if index:
        table = pq.read_table(fx.samples_table(root))
        labels, sizes = table.column("label").to_pylist(), table.column("label_size").to_pylist()
        labels[row], sizes[row] = label, label.bit_count()
        rewrite_parquet(fx.samples_table(root), "label", labels)
        rewrite_parquet(fx.samples_table(root), "label_size", sizes)


def per_view_keys(root: Path | str, record: CommitRecord, name: str) -> list[np.ndarray]:
    """A shard's stored per-view key sets (``visible`` or ``refined``), int16 triples per view."""
    shard = ShardReader(open_location(str(root)), record.shard)
    keys, offsets = shard.array(f"{name}_keys"), shard.array(f"{name}_offsets")
    return [keys[offsets[v] : offsets[v + 1]] for v in range(offsets.size - 1)]


def task_rows(root: Path | str, record: CommitRecord, alpha: int) -> TaskRows:
    """The P_full masks rebuilt from the shard's stored P_i (the pipeline's coverage table)."""
    shard = ShardReader(open_location(str(root)), record.shard)
    keys, offsets = shard.array("refined_keys"), shard.array("refined_offsets")
    per_view = [pack_keys(keys[offsets[v] : offsets[v + 1]]) for v in range(offsets.size - 1)]
    return TaskRows.from_masks(coverage_table(per_view, alpha).masks)


def maybe_in_memory(root: Path, where: str) -> str:
    return str(root) if where == "local" else copy_to_memory(root)


# -- a clean dataset -------------------------------------------------------------------------------------


@pytest.mark.parametrize("where", WHERE)
def test_validate_all_passes_on_the_clean_dataset(engine_dataset: EngineDataset, where: str) -> None:  # noqa: F811
    url = url_of(engine_dataset, where)
    result = shards("validate", url, "--all")
    assert result.exit_code == 0, result.output
    samples = len(open_dataset(url))
    assert result.output.splitlines() == [
        f"ok: {engine_dataset.committed_tasks} tasks sound, {samples} labels checked with the solver (every label)"
    ]


@pytest.mark.parametrize("where", WHERE)
def test_validate_samples_labels_per_shard(engine_dataset: EngineDataset, where: str) -> None:  # noqa: F811
    url = url_of(engine_dataset, where)
    result = shards("validate", url)
    assert result.exit_code == 0, result.output
    sizes = [r.num_samples for r in committed_tasks(open_location(url))]
    checked = sum(min(size, SAMPLED_ROWS_PER_SHARD) for size in sizes)
    assert f" {checked} labels checked with the solver (a sample of labels)" in result.output


def test_validate_of_a_folder_that_is_no_dataset(tmp_path: Path) -> None:
    result = shards("validate", str(tmp_path))
    assert result.exit_code == 1
    assert problem_lines(result) == [f"{tmp_path}: no dataset.json here; this is not a datagen dataset (check the URL)"]
    assert result.output.splitlines()[-2].startswith("1 problem ")
    assert result.output.splitlines()[-1] == f"fix: check the URL: {tmp_path} holds no datagen dataset"


# -- storage's corruptions (tests/storage/test_validate.py's list), each seen through the CLI --------------------


@pytest.mark.parametrize("name", ["points_keys", "observed_keys", "refined_keys"])
def test_key_array_rewritten_shorter(ds: Path, name: str) -> None:
    record = first(ds)
    with group(ds, record) as g:
        array = g[name]
        assert isinstance(array, zarr.Array)
        array.resize((array.shape[0] - 100, 3))
    result = validate_all(ds)
    assert lines_with(result, record.shard, name.replace("_keys", "_offsets"), "truncated")


def test_gt_keys_with_the_wrong_shape(ds: Path) -> None:
    record = first(ds)
    with group(ds, record) as g:
        gt = np.asarray(g["gt_keys"][...])
        del g["gt_keys"]
        g.create_array("gt_keys", data=gt[:, :2].copy())
    assert lines_with(validate_all(ds), record.shard, "gt_keys", "expected (G, 3) int16")


@pytest.mark.parametrize("name", ["points_keys", "observed_keys", "refined_keys", "visible_keys"])
def test_chunk_file_truncated_on_disk(ds: Path, name: str) -> None:
    record = first(ds)
    assert fx.stored_array(ds / record.shard, name).shape[0] > KEY_CHUNK_ROWS  # a zarr shard, its index checksummed
    fx.truncate_member(ds / record.shard, f"{name}/c/0/0")
    result = validate_all(ds)
    assert lines_with(result, record.shard, "truncated or corrupt")
    assert not lines_with(result, "cannot check labels")  # storage's line says it; the label check stays quiet


@pytest.mark.parametrize("damage", ["empty", "deleted"])
def test_chunk_file_emptied_or_deleted(ds: Path, damage: str) -> None:
    record = first(ds)
    if damage == "empty":
        fx.truncate_member(ds / record.shard, "points_keys/c/0/0", keep=0)
    else:
        fx.zip_without(ds / record.shard, "points_keys/c/0/0")
    assert lines_with(validate_all(ds), record.shard, "points_keys")


def test_shard_group_missing(ds: Path) -> None:
    record = first(ds)
    (ds / record.shard).unlink()
    result = validate_all(ds)
    assert lines_with(result, record.shard, "cannot open shard")
    assert not lines_with(result, "cannot check labels")


@pytest.mark.parametrize("name", ["points_offsets", "observed_offsets", "visible_offsets"])
def test_non_monotone_offsets(ds: Path, name: str) -> None:
    record = first(ds)
    with group(ds, record) as g:
        offsets = np.asarray(g[name][...])
        offsets[2], offsets[3] = offsets[3], offsets[2]
        assert offsets[3] < offsets[2]
        g[name][...] = offsets
    assert lines_with(validate_all(ds), f"{record.shard} row 2:", name, "not monotone")


def test_offsets_not_ending_at_the_key_count(ds: Path) -> None:
    record = first(ds)
    with group(ds, record) as g:
        offsets = np.asarray(g["points_offsets"][...])
        offsets[-1] += 5
        g["points_offsets"][...] = offsets
    assert lines_with(validate_all(ds), record.shard, "points_offsets", "not monotone")


def test_index_row_pointing_to_an_uncommitted_shard(ds: Path) -> None:
    record = first(ds)
    orphan = shard_path(record.task_id, "orphan")
    (ds / orphan).write_bytes((ds / record.shard).read_bytes())  # on disk, but no commit record names it
    values = pq.read_table(fx.samples_table(ds)).column("shard").to_pylist()
    rewrite_parquet(fx.samples_table(ds), "shard", [orphan, *values[1:]])
    assert lines_with(validate_all(ds), "index row 0:", orphan, "no commit record")


def test_dangling_index_row(ds: Path) -> None:
    values = pq.read_table(fx.samples_table(ds)).column("shard").to_pylist()
    values[5] = "shards/nowhere/a1.zarr"
    rewrite_parquet(fx.samples_table(ds), "shard", values)
    assert lines_with(validate_all(ds), "index row 5:", "shards/nowhere/a1.zarr")


def test_index_row_out_of_range(ds: Path) -> None:
    record = first(ds)
    rows = pq.read_table(fx.samples_table(ds)).column("row").to_pylist()
    rows[3] = record.num_samples + 7
    rewrite_parquet(fx.samples_table(ds), "row", rows)
    assert lines_with(validate_all(ds), "index row 3:", f"row {record.num_samples + 7}", record.shard, "outside")


def test_fragment_missing(ds: Path) -> None:
    record = first(ds)
    os.remove(ds / record.index_fragment)
    assert lines_with(validate_all(ds), record.index_fragment, "cannot read index fragment")


def test_duplicate_samples(ds: Path) -> None:
    """A second commit whose shard and fragment copy the first task's: every sample id twice."""
    record = first(ds)
    copy_task = "0000000000000000-r9"
    copy_shard, copy_fragment = shard_path(copy_task, "a1"), fragment_path(copy_task, "a1")
    (ds / copy_shard).parent.mkdir(parents=True)
    shutil.copy(ds / record.shard, ds / copy_shard)
    shutil.copy(ds / record.index_fragment, ds / copy_fragment)
    rewrite_parquet(ds / copy_fragment, "shard", [copy_shard] * record.num_samples)
    copied = record.model_copy(update={"task_id": copy_task, "shard": copy_shard, "index_fragment": copy_fragment})
    (ds / commit_path(copy_task)).write_text(copied.model_dump_json())
    duplicates = lines_with(validate_all(ds), "duplicate sample id")
    assert len(duplicates) == record.num_samples
    assert all(record.shard in line and copy_shard in line for line in duplicates)


@pytest.mark.parametrize("relative", ["commit", "dataset.json"])
def test_unparsable_record(ds: Path, relative: str) -> None:
    path = commit_path(first(ds).task_id) if relative == "commit" else "dataset.json"
    (ds / path).write_text('{"task_id": ')
    result = shards("validate", str(ds), "--all")
    assert result.exit_code == 1
    assert lines_with(result, path)
    if relative == "dataset.json":
        assert len(problem_lines(result)) == 1  # said once, though both checkers need the file


@pytest.mark.parametrize("column", ["label", "view_state"])
def test_mask_bits_beyond_the_view_count(ds: Path, column: str) -> None:
    record, row = first(ds), 4
    masks = stored_masks(ds, record)
    n = info_of(str(ds)).num_views
    if column == "label":
        masks[row, LABEL_COLUMN] |= np.uint64(1 << (n + 3))
    else:
        masks[row, VIEW_STATE_COLUMN] |= np.uint64(1 << 63)
    with group(ds, record) as g:
        g[MASKS][...] = masks
    assert lines_with(validate_all(ds), f"{record.shard} row {row}:", f"beyond the {n} views")


def test_label_overlapping_the_input(ds: Path) -> None:
    record = first(ds)
    masks = stored_masks(ds, record)
    row = int(np.flatnonzero(masks[:, LABEL_COLUMN])[0])
    case, label = int(masks[row, VIEW_STATE_COLUMN]), int(masks[row, LABEL_COLUMN])
    write_label(ds, record, row, label | (case & -case))
    result = validate_all(ds)
    assert lines_with(result, f"{record.shard} row {row}:", "label shares views with the input")
    # The input view covers nothing of U, so the solver check also sees a label one view too large.
    assert lines_with(result, sample_id(record.task_id, case), "is not minimum")


def test_label_that_is_not_a_cover(ds: Path) -> None:
    record = first(ds)
    masks = stored_masks(ds, record)
    row = int(np.flatnonzero(masks[:, LABEL_COLUMN])[-1])
    label = int(masks[row, LABEL_COLUMN])
    write_label(ds, record, row, label & (label - 1))  # without its lowest view
    result = validate_all(ds)
    assert len(problem_lines(result)) == 1, result.output  # storage's line; the label check's twin is dropped
    assert lines_with(result, f"{record.shard} row {row}:", "keys of U uncovered")


def test_commit_record_disagreeing_with_the_shard(ds: Path) -> None:
    record = first(ds)
    path = ds / commit_path(record.task_id)
    data = json.loads(path.read_text())
    data["num_samples"] += 1
    path.write_text(json.dumps(data))
    result = validate_all(ds)
    assert lines_with(result, record.shard, "disagree with the commit record")
    assert lines_with(result, record.index_fragment, "rows for")


def test_deleted_commit_record_of_a_finalised_dataset(ds: Path) -> None:
    """Before: "ok: 5 tasks sound" while the finalised index still listed the task."""
    record = first(ds)
    os.remove(ds / commit_path(record.task_id))
    result = validate_all(ds)
    assert lines_with(result, "index/manifest.json", record.task_id, "no commit record")
    assert len(open_dataset(str(ds))) > 0  # a finished dataset is its manifest; its samples are intact
    mark_adding(open_location(str(ds)))  # a job adding to it: opening lists the records and refuses
    with pytest.raises(StorageError, match=record.task_id):
        open_dataset(str(ds))


def test_leftover_temporary_file_is_a_warning_and_passes(ds: Path) -> None:
    leftover = f"{commit_path(first(ds).task_id)}.tmp-0123456789abcdef0123456789abcdef"
    (ds / leftover).write_bytes(b"{")
    result = shards("validate", str(ds))
    assert result.exit_code == 0, result.output
    assert lines_with(result, "warning:", leftover, "safe to delete")
    assert result.output.splitlines()[-1].startswith("ok: ") and "1 warning" in result.output.splitlines()[-1]


# -- labels that cover but break the rules (the solver's part) -------------------------------------------


@pytest.mark.parametrize("where", WHERE)
def test_label_that_covers_but_is_not_minimum(ds: Path, where: str) -> None:
    record = first(ds)
    masks = stored_masks(ds, record)
    row = int(np.flatnonzero(masks[:, LABEL_COLUMN])[0])
    case, label = int(masks[row, VIEW_STATE_COLUMN]), int(masks[row, LABEL_COLUMN])
    extra = next(v for v in range(info_of(str(ds)).num_views) if not (case | label) >> v & 1)
    larger = label | 1 << extra
    write_label(ds, record, row, larger)
    result = validate_all(maybe_in_memory(ds, where))
    k = label.bit_count()
    listed, recomputed = problem_lines(result)
    # Version 2 lists every minimum cover beside the label: the structural pass already sees that the
    # larger label is not one of them; the solver's pass says why.
    assert f" row {row}: label {mask_views(larger)} is not among its " in listed
    assert listed.endswith(" listed minimum covers")
    assert recomputed == (
        f"{sample_id(record.task_id, case)}: label {views_text(larger)} covers U but is not minimum "
        f"(k={k + 1} > k*={k})"
    )


def other_minimum_cover(root: Path, record: CommitRecord, alpha: int) -> tuple[int, int, int]:
    """(row, stored label, another cover of the same size) for the first row whose U has several
    minimum covers, found by enumerating every combination of views outside the case."""
    rows = task_rows(root, record, alpha)
    masks = stored_masks(root, record)
    for row, (case, label) in enumerate(masks.tolist()):
        universe = rows.distinct[(rows.distinct & np.uint64(case)) == 0]
        k = int(label).bit_count()
        if k == 0:
            continue
        outside = [v for v in range(info_of(str(root)).num_views) if not case >> v & 1]
        for combination in itertools.combinations(outside, k):
            other = sum(1 << v for v in combination)
            if other != label and bool(((universe & np.uint64(other)) != 0).all()):
                return row, int(label), other
    raise AssertionError("no sample with two minimum covers in the dataset")


@pytest.mark.parametrize("where", WHERE)
def test_minimum_cover_that_is_not_the_lexicographic_choice(ds: Path, where: str) -> None:
    record = first(ds)
    alpha = info_of(str(ds)).config.alpha
    row, label, other = other_minimum_cover(ds, record, alpha)
    assert other > 0 and other.bit_count() == label.bit_count()
    write_label(ds, record, row, other)
    result = validate_all(maybe_in_memory(ds, where))
    case = int(stored_masks(ds, record)[row, VIEW_STATE_COLUMN])
    assert problem_lines(result) == [
        f"{sample_id(record.task_id, case)}: label {views_text(other)} is minimum but not the lexicographic "
        f"choice {views_text(label)}"
    ]
    # The HiGHS path of the checker (used when enumeration would be too long) reaches the same verdict.
    highs = task_rows(ds, record, alpha)
    highs.search_limit = 0
    assert [kind for kind, _ in highs.judge(case, other)] == ["not-lexicographic"]
    assert list(highs.judge(case, label)) == []


def test_index_label_disagreeing_with_the_shard(ds: Path) -> None:
    record = first(ds)
    alpha = info_of(str(ds)).config.alpha
    row, label, other = other_minimum_cover(ds, record, alpha)
    table = pq.read_table(fx.samples_table(ds))
    labels = table.column("label").to_pylist()
    labels[row] = other
    rewrite_parquet(fx.samples_table(ds), "label", labels)
    result = validate_all(ds)
    case = int(stored_masks(ds, record)[row, VIEW_STATE_COLUMN])
    assert problem_lines(result) == [
        f"{sample_id(record.task_id, case)}: the index says label {views_text(other)}, "
        f"the shard holds {views_text(label)}"
    ]


# -- relabel ---------------------------------------------------------------------------------------------


def new_url(where: str, tmp_path: Path, name: str) -> str:
    return str(tmp_path / name) if where == "local" else f"memory://{name}-{uuid.uuid4().hex[:8]}"


@pytest.mark.parametrize("where", WHERE)
def test_relabel_to_the_same_alpha_reproduces_the_labels(
    engine_dataset: EngineDataset,  # noqa: F811
    tmp_path: Path,
    where: str,
) -> None:
    source = url_of(engine_dataset, where)
    out = new_url(where, tmp_path, "same")
    alpha = info_of(source).config.alpha
    result = shards("relabel", source, "--alpha", str(alpha), "--out", out)
    assert result.exit_code == 0, result.output
    # Every array of every shard (masks included) and every index column but the volatile ones.
    assert assert_same_samples(source, out) == len(open_dataset(source))
    assert info_of(out).config_hash == info_of(source).config_hash
    assert f"config hash: {info_of(source).config_hash}" in result.output.splitlines()
    assert sorted(f.task_id for f in read_failures(open_location(out))) == sorted(
        f.task_id for f in read_failures(open_location(source))
    )


@pytest.mark.parametrize("where", WHERE)
def test_relabel_to_another_alpha_validates(engine_dataset: EngineDataset, tmp_path: Path, where: str) -> None:  # noqa: F811
    source = url_of(engine_dataset, where)
    out = new_url(where, tmp_path, "alpha5")
    result = shards("relabel", source, "--alpha", "5", "--out", out)
    assert result.exit_code == 0, result.output
    old, new = info_of(source), info_of(out)
    assert new.config.alpha == 5 and new.config == old.config.model_copy(update={"alpha": 5})
    assert new.config_hash != old.config_hash and new.config_hash == new.config.config_hash()
    lines = result.output.splitlines()
    assert f"config hash: {new.config_hash}" in lines and f"dataset: {out}" in lines
    assert any("labels/s" in line for line in lines)
    checked = shards("validate", out, "--all")
    assert checked.exit_code == 0, checked.output
    a, b = open_dataset(source), open_dataset(out)
    assert sorted(a.index.column("sample_id").to_pylist()) == sorted(b.index.column("sample_id").to_pylist())
    assert set(b.index.column("config_hash").to_pylist()) == {new.config_hash}
    old_labels = dict(zip(a.index.column("sample_id").to_pylist(), a.index.column("label").to_pylist(), strict=True))
    changed = [
        s
        for s, label in zip(b.index.column("sample_id").to_pylist(), b.index.column("label").to_pylist(), strict=True)
        if old_labels[s] != label
    ]
    assert changed, "a lower alpha grows P_full, so some labels must change"
    assert len(read_failures(open_location(out))) == engine_dataset.failed_tasks


@pytest.mark.parametrize("version", [1, 2, 3])
def test_relabel_brings_an_older_dataset_to_a_fresh_generation(tmp_path: Path, version: int) -> None:
    """Relabelling a version-1, 2 or 3 dataset at its own alpha gives exactly a fresh generation of
    the same tasks in the newest layout: same samples and labels, every minimum cover, count, support
    and cover row (version 2), every view's gains, best next view and occupancy grid (version 3), each
    refined cloud in the stored point order (version 4)."""
    from support import storage as fx

    old, fresh, out = tmp_path / "old", tmp_path / "fresh", tmp_path / "relabelled"
    fx.build_dataset(str(old), finalise_index=True, schema_version=version)
    fx.build_dataset(str(fresh), finalise_index=True)
    result = shards("relabel", str(old), "--out", str(out))
    assert result.exit_code == 0, result.output
    assert info_of(str(out)).schema_version == SCHEMA_VERSION
    assert info_of(str(out)).config_hash == info_of(str(old)).config_hash
    assert assert_same_samples(str(out), str(fresh)) == len(open_dataset(str(fresh)))
    checked = shards("validate", str(out), "--all")
    assert checked.exit_code == 0, checked.output
    # The old clouds are sorted sets; the new ones hold the same keys, shuffled.
    before, after = open_dataset(str(old)), open_dataset(str(out))
    where = {sample: i for i, sample in enumerate(after.index.column("sample_id").to_pylist())}
    for i, sample in enumerate(before.index.column("sample_id").to_pylist()):
        stored, sorted_set = after.keys(where[sample], "points"), before.keys(i, "points")
        np.testing.assert_array_equal(np.unique(stored, axis=0), sorted_set, err_msg=sample)
        assert len(stored) < 3 or not np.array_equal(stored, sorted_set), sample


def test_validate_all_recounts_the_minimum_covers(tmp_path: Path) -> None:
    """`--all` enumerates every view set of the label's size itself: a wrong count or support in the
    index, or a listed cover dropped from an exact list, is a line naming the sample."""
    from schemas.index import INDEX_SCHEMA

    root = tmp_path / "v2"
    fx.build_dataset(str(root), finalise_index=True)
    table = pq.read_table(fx.samples_table(root))
    counts = table.column("min_covers").to_numpy().copy()
    support = table.column("label_support").to_numpy().copy()
    row = int(np.flatnonzero(counts > 2)[0])
    counts[row] += 1
    other = int(np.flatnonzero(counts > 2)[1])
    missing = next(
        v
        for v in range(32)
        if not int(support[other]) >> v & 1 and not int(table["view_state"][other].as_py()) >> v & 1
    )
    support[other] |= np.uint64(1 << missing)
    for name, values in (("min_covers", counts), ("label_support", support)):
        table = table.set_column(table.schema.get_field_index(name), name, pa.array(values))
    pq.write_table(table.cast(INDEX_SCHEMA), fx.samples_table(root))
    report = label_check.check_labels(str(root), full=True)
    lines = [p.line for p in report.problems]
    names = table.column("sample_id").to_pylist()
    assert f"{names[row]}: the index counts {counts[row]} minimum covers, there are {counts[row] - 1}" in lines
    assert any(line.startswith(f"{names[other]}: support ") for line in lines)
    assert {p.kind for p in report.problems} == {label_check.COVERS_WRONG}
    assert len(lines) == 2


def test_relabel_into_another_dataset_is_refused(engine_dataset: EngineDataset, tmp_path: Path) -> None:  # noqa: F811
    target = Path(shutil.copytree(engine_dataset.url, tmp_path / "existing"))
    before = (target / "dataset.json").read_bytes()
    result = shards("relabel", engine_dataset.url, "--alpha", "5", "--out", str(target))
    assert result.exit_code == 2
    (line,) = result.output.splitlines()
    there = info_of(str(target)).config_hash[:12]
    assert line.startswith(f"error: {target}: already holds another dataset (config {there}, this relabel makes ")
    assert line.endswith("give an empty --out, or the same one to finish a stopped relabel")
    assert (target / "dataset.json").read_bytes() == before


def test_a_stopped_relabel_is_finished_by_running_it_again(engine_dataset: EngineDataset, tmp_path: Path) -> None:  # noqa: F811
    """Stopped after its first task, the same relabel into the same --out keeps what was committed and
    relabels the rest: the same samples as a relabel never stopped."""
    from datagen.engine.relabel import RelabelProgress, relabel_dataset

    class Stop(Exception):
        pass

    def stop_after_one(done: RelabelProgress) -> None:
        raise Stop

    stopped, whole = str(tmp_path / "stopped"), str(tmp_path / "whole")
    with pytest.raises(Stop):
        relabel_dataset(engine_dataset.url, 5, stopped, progress=stop_after_one)
    assert len(committed_tasks(open_location(stopped))) == 1
    result = shards("relabel", engine_dataset.url, "--alpha", "5", "--out", stopped)
    assert result.exit_code == 0, result.output
    assert f"kept 1 task a stopped relabel into {stopped} had committed" in result.output.splitlines()
    assert shards("relabel", engine_dataset.url, "--alpha", "5", "--out", whole).exit_code == 0
    assert assert_same_samples(whole, stopped) == len(open_dataset(whole)) > 0
    assert shards("validate", stopped, "--all").exit_code == 0


def test_relabel_with_an_alpha_beyond_the_views(engine_dataset: EngineDataset, tmp_path: Path) -> None:  # noqa: F811
    result = shards("relabel", engine_dataset.url, "--alpha", "33", "--out", str(tmp_path / "out"))
    assert result.exit_code == 2
    assert result.output.splitlines() == ["error: --alpha 33 is outside 1..32 (the dataset has 32 views)"]
    assert not (tmp_path / "out").exists()


# -- the checker's solver against the oracle -------------------------------------------------------------


def random_instances(count: int, seed: int) -> list[tuple[int, list[int]]]:
    """(views, rows) with a few rows of a few views each: ties are common, covers of 1 to 6 views."""
    rng = np.random.default_rng(seed)
    instances = []
    for _ in range(count):
        n = int(rng.integers(4, 16))
        rows = []
        for _ in range(int(rng.integers(1, 25))):
            width = int(rng.integers(1, 5))
            rows.append(sum(1 << int(v) for v in rng.choice(n, size=width, replace=False)))
        instances.append((n, rows))
    return instances


@pytest.mark.parametrize("search_limit", [2_000_000, 0], ids=["enumeration", "highs"])
def test_expected_label_matches_the_oracle(search_limit: int) -> None:
    for n, rows in random_instances(60 if search_limit else 25, seed=11):
        truth = oracle_cover(rows)
        reduced = undominated(np.array(rows, dtype=np.uint64))
        # Any cover bounds the search; the union of all views is the loosest.
        for bound in (truth.label, (1 << n) - 1):
            expected = expected_label(reduced, bound, search_limit)
            assert (expected.size, expected.label) == (truth.size, truth.label), (rows, bound)


@pytest.mark.parametrize("dense", [True, False], ids=["dense-grid", "sorted"])
def test_full_masks_match_the_pipelines_coverage_table(
    engine_dataset: EngineDataset,  # noqa: F811
    dense: bool,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    if not dense:
        monkeypatch.setattr(label_check, "DENSE_CELLS", 0)
    location = open_location(engine_dataset.url)
    for record in committed_tasks(location):
        shard = ShardReader(location, record.shard)
        keys, offsets = shard.array("refined_keys"), shard.array("refined_offsets")
        per_view = [pack_keys(keys[offsets[v] : offsets[v + 1]]) for v in range(offsets.size - 1)]
        for alpha in (1, 5, 10, 32):
            ours = np.sort(label_check.full_masks(keys, offsets, alpha))
            assert ours.size > 0 or alpha == 32
            np.testing.assert_array_equal(ours, np.sort(coverage_table(per_view, alpha).masks))


def test_undominated_matches_the_oracle() -> None:
    for _, rows in random_instances(40, seed=5):
        assert undominated(np.array(rows, dtype=np.uint64)).tolist() == oracle_minimal(rows)


def test_lexicographic_rank_is_the_position_in_combinations_order() -> None:
    for m, k in ((6, 3), (9, 2), (7, 7), (5, 1)):
        for position, combination in enumerate(itertools.combinations(range(m), k)):
            assert lexicographic_rank(combination, m) == position


def test_judge_names_each_broken_rule() -> None:
    # Keys seen by views {0,1}, {1,2}, {2,3} (two keys) and {0,3}; nothing is in the case.
    rows = TaskRows.from_masks([0b0011, 0b0110, 0b1100, 0b1100, 0b1001])
    assert list(rows.judge(0, 0b0101)) == []  # {0, 2}: the smallest of the size-2 covers {0,2} and {1,3}
    assert list(rows.judge(0, 0b1010)) == [
        ("not-lexicographic", "label {1, 3} is minimum but not the lexicographic choice {0, 2}")
    ]
    assert list(rows.judge(0, 0b0111)) == [("not-minimum", "label {0, 1, 2} covers U but is not minimum (k=3 > k*=2)")]
    assert list(rows.judge(0, 0b0001)) == [("uncovered", "label {0} does not cover U (3 of 5 keys uncovered)")]
    # With view 0 as the input, U is the three keys without it: {2} covers them alone.
    assert list(rows.judge(0b0001, 0b0100)) == []
    assert list(rows.judge(0b1111, 0)) == []  # U empty: the empty label is right
    assert list(rows.judge(0b1111, 0b10000)) == [("not-minimum", "label {4} covers U but is not minimum (k=1 > k*=0)")]


def test_judge_follows_the_datasets_tie_break() -> None:
    # Keys seen by {0,2}, {1,2} (two keys), {0,2} and {0,1}: {0,1}, {0,2} and {1,2} all cover U; view 2 sees
    # four keys, view 0 and view 1 three each, so the coverage order is 2, 0, 1.
    masks = [0b101, 0b110, 0b110, 0b101, 0b011]
    by_index = TaskRows.from_masks(masks, tie_break="index", num_views=3)
    by_coverage = TaskRows.from_masks(masks, tie_break="coverage", num_views=3)
    assert by_coverage.view_order(0) == [2, 0, 1] and by_index.view_order(0) is None
    assert list(by_index.judge(0, 0b011)) == [] and list(by_coverage.judge(0, 0b101)) == []
    assert list(by_coverage.judge(0, 0b011)) == [
        ("not-lexicographic", "label {0, 1} is minimum but not the coverage tie-break's choice {0, 2}")
    ]
    # With view 2 as the input, U is the one key {0, 1}: views 0 and 1 cover one key each, 0 goes first.
    assert by_coverage.view_order(0b100) == [0, 1, 2]
    assert list(by_coverage.judge(0b100, 0b001)) == []


@pytest.mark.parametrize("search_limit", [2_000_000, 0], ids=["enumeration", "highs"])
def test_expected_label_in_a_view_order_matches_the_renamed_oracle(search_limit: int) -> None:
    rng = np.random.default_rng(3)
    for n, rows in random_instances(40 if search_limit else 20, seed=13):
        order = [int(v) for v in rng.permutation(n)]
        rename = {view: i for i, view in enumerate(order)}
        truth = oracle_cover([sum(1 << rename[v] for v in range(n) if r >> v & 1) for r in rows])
        label = sum(1 << order[i] for i in range(n) if truth.label >> i & 1)
        reduced = undominated(np.array(rows, dtype=np.uint64))
        expected = expected_label(reduced, (1 << n) - 1, search_limit, order)
        assert (expected.size, expected.label) == (truth.size, label), (rows, order)


def test_relabel_with_the_coverage_tie_break_validates(engine_dataset: EngineDataset, tmp_path: Path) -> None:  # noqa: F811
    out = str(tmp_path / "coverage")
    result = shards("relabel", engine_dataset.url, "--tie-break", "coverage", "--out", out)
    assert result.exit_code == 0, result.output
    old, new = info_of(engine_dataset.url), info_of(out)
    assert new.config == old.config.model_copy(update={"label_tie_break": "coverage"})
    assert new.config_hash != old.config_hash and new.config_hash == new.config.config_hash()
    source_line = f"(source: cover, alpha {old.config.alpha}, tie-break index)"
    assert any(line.endswith(source_line) for line in result.output.splitlines()), result.output
    checked = shards("validate", out, "--all")
    assert checked.exit_code == 0, checked.output
    a, b = open_dataset(engine_dataset.url), open_dataset(out)
    before = dict(zip(a.index.column("sample_id").to_pylist(), a.index.column("label").to_pylist(), strict=True))
    after = dict(zip(b.index.column("sample_id").to_pylist(), b.index.column("label").to_pylist(), strict=True))
    assert sorted(before) == sorted(after)
    assert all(int(before[s]).bit_count() == int(after[s]).bit_count() for s in before), "both are minimum covers"
    assert any(before[s] != after[s] for s in before), "equally small covers exist, so some labels move"
    # Claiming the other rule in dataset.json makes the same labels wrong for the checker.
    info_path = Path(out) / "dataset.json"
    info = json.loads(info_path.read_text())
    info["config"]["label_tie_break"] = "index"
    info_path.write_text(json.dumps(info))
    rechecked = shards("validate", out, "--all")
    assert rechecked.exit_code == 1 and "not the lexicographic choice" in rechecked.output


def test_relabel_with_an_unknown_tie_break(engine_dataset: EngineDataset, tmp_path: Path) -> None:  # noqa: F811
    result = shards("relabel", engine_dataset.url, "--tie-break", "fewest", "--out", str(tmp_path / "out"))
    assert result.exit_code == 2
    assert result.output.splitlines() == ["error: --tie-break 'fewest' is not one of index, coverage"]
    assert not (tmp_path / "out").exists()


# -- the visibility objectives (docs/pipeline.md section 7.5) ------------------------------------------------

VISIBILITY = [
    ({"label_objective": "max_coverage", "label_budget": 2}, ["--objective", "max_coverage", "--budget", "2"]),
    ({"label_objective": "partial_cover", "label_tau": 0.85}, ["--objective", "partial_cover", "--tau", "0.85"]),
]


@pytest.mark.parametrize(("changes", "options"), VISIBILITY, ids=["max_coverage", "partial_cover"])
def test_relabel_to_a_visibility_objective_equals_a_fresh_generation(
    tmp_path: Path, changes: dict[str, object], options: list[str]
) -> None:
    """Same samples, labels, ties, counts, support and cover rows as generating with the objective; the new
    dataset validates with the solver's independent check (every view subset tried)."""
    from support import storage as fx

    source, fresh, out = tmp_path / "paper", tmp_path / "fresh", tmp_path / "relabelled"
    fx.build_dataset(str(source), finalise_index=True)
    fx.build_dataset(str(fresh), finalise_index=True, cfg=fx.config(**changes))
    result = shards("relabel", str(source), *options, "--out", str(out))
    assert result.exit_code == 0, result.output
    assert f"for {changes['label_objective']} (" in result.output and "(source: cover, alpha 10" in result.output
    assert info_of(str(out)).config == fx.config(**changes)
    assert info_of(str(out)).config_hash == info_of(str(fresh)).config_hash != info_of(str(source)).config_hash
    assert assert_same_samples(str(out), str(fresh)) == len(open_dataset(str(fresh)))
    checked = shards("validate", str(out), "--all")
    assert checked.exit_code == 0, checked.output
    back = shards("relabel", str(out), "--objective", "cover", "--out", str(tmp_path / "back"))
    assert back.exit_code == 0, back.output
    assert assert_same_samples(str(tmp_path / "back"), str(source)) == len(open_dataset(str(source)))


def test_validate_all_finds_a_visibility_label_that_is_not_the_best(tmp_path: Path) -> None:
    from support import storage as fx

    root = tmp_path / "mc"
    fx.build_dataset(str(root), finalise_index=True, cfg=fx.config(label_objective="max_coverage", label_budget=1))
    record = first(root)
    masks = stored_masks(root, record)
    row = 0
    case, label = (int(m) for m in masks[row])
    worse = next(1 << v for v in range(32) if not (case | label) >> v & 1)
    write_label(root, record, row, worse)
    result = validate_all(root)
    name = sample_id(record.task_id, case)
    judge = visibility_judge([pack_keys(k) for k in per_view_keys(root, record, "visible")], fx.config())
    seen_worse, seen_label = judge.seen(case | worse), judge.seen(case | label)
    assert seen_worse < seen_label
    assert problem_lines(result) == [
        f"{record.shard} row {row}: label {mask_views(worse)} is not among its 1 listed ties",
        f"{name}: label {views_text(worse)} sees {seen_worse} keys, {views_text(label)} sees {seen_label}",
    ]
    fix = result.output.splitlines()[-1]
    assert fix.startswith(f"fix: datagen shards repair {root} (re-runs the 1 damaged task from the ledger")
    assert f"then datagen shards relabel {root} --out NEW_URL" in fix


def test_validate_names_the_repair_that_mends_a_damaged_shard(tmp_path: Path) -> None:
    from support import storage as fx

    root = tmp_path / "damaged"
    fx.build_dataset(str(root), finalise_index=True)
    records = committed_tasks(open_location(str(root)))
    for record in records:  # every task's shard loses its masks: two tasks to re-run
        with group(root, record) as g:
            del g[MASKS]
    result = validate_all(root)
    assert result.output.splitlines()[-1] == (
        f"fix: datagen shards repair {root} (re-runs the 2 damaged tasks from the ledger that made them; where the "
        "job was submitted, or give --home)"
    )


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (
            ["--objective", "best_guess"],
            "error: --objective 'best_guess' is not one of cover, max_coverage, partial_cover",
        ),
        (["--objective", "partial_cover", "--tau", "1.5"], "error: --tau 1.5: Input should be less than or equal to 1"),
        (["--objective", "max_coverage", "--tie-break", "coverage"], "error: label_tie_break = 'coverage' ranks views"),
    ],
)
def test_relabel_with_a_bad_objective_is_one_line(tmp_path: Path, options: list[str], message: str) -> None:
    from support import storage as fx

    fx.build_dataset(str(tmp_path / "source"))
    result = shards("relabel", str(tmp_path / "source"), *options, "--out", str(tmp_path / "out"))
    assert result.exit_code == 2 and len(result.output.splitlines()) == 1
    assert result.output.startswith(message), result.output
    assert not (tmp_path / "out").exists()


def test_relabel_on_ray_gives_what_it_gives_here_and_reads_a_packed_dataset(tmp_path: Path) -> None:
    """``--workers 2`` relabels the tasks side by side on a local Ray: the same samples as one by one
    here; a packed dataset relabels to the same too (its shards read from their byte ranges)."""
    from support.engine import start_local_ray, stop_local_ray

    from storage.dataset import pack_dataset

    source, packed = tmp_path / "source", tmp_path / "packed"
    fx.build_dataset(str(source), finalise_index=True)
    pack_dataset(str(source), str(packed), target_bytes=100_000)
    here, on_ray, from_packed = tmp_path / "here", tmp_path / "ray", tmp_path / "from-packed"
    assert shards("relabel", str(source), "--out", str(here), "--alpha", "9").exit_code == 0
    start_local_ray(2)
    try:
        result = shards("relabel", str(source), "--out", str(on_ray), "--alpha", "9", "--workers", "2")
    finally:
        stop_local_ray()
    assert result.exit_code == 0, result.output
    assert shards("relabel", str(packed), "--out", str(from_packed), "--alpha", "9").exit_code == 0
    samples = assert_same_samples(str(on_ray), str(here))
    assert samples == assert_same_samples(str(from_packed), str(here)) == fx.total_samples()
    assert shards("validate", str(on_ray)).exit_code == 0


def test_validate_on_ray_finds_what_it_finds_here(ds: Path) -> None:
    """``--workers 2`` checks chunks of tasks side by side on a local Ray: the same lines, in the same
    order, as checking them here; ``--sample`` says which share it read."""
    from support.engine import start_local_ray, stop_local_ray

    record = first(ds)
    masks = stored_masks(ds, record)
    row = int(np.flatnonzero(masks[:, LABEL_COLUMN])[-1])
    write_label(ds, record, row, int(masks[row, LABEL_COLUMN]) & (int(masks[row, LABEL_COLUMN]) - 1))
    here = shards("validate", str(ds), "--all")
    start_local_ray(2)
    try:
        on_ray = shards("validate", str(ds), "--all", "--workers", "2")
    finally:
        stop_local_ray()
    assert here.exit_code == on_ray.exit_code == 1
    assert here.output == on_ray.output and f"{record.shard} row {row}" in here.output
    sampled = shards("validate", str(ds), "--sample", "0.2")
    assert "tasks checked (" in sampled.output
