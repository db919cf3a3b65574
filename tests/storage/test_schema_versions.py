"""Schema version 2 (each label's minimum covers, their count and support, the task's cover rows) beside
version 1: a version-1 dataset still reads and validates, a version-2 dataset serves what the pipeline
computed, and `storage.validate` names each damage to the new arrays."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from support import storage as fx

from schemas.shard import COVER_ROWS, COVERS, LABEL_COLUMN, MASKS, VIEW_STATE_COLUMN, offsets_array
from storage import StorageError, covers_universe, nearest_cover, open_dataset, validate
from storage.dataset import shard_path


@pytest.fixture
def ds(version_2: Path, tmp_path: Path) -> Path:
    return fx.copy_dataset(version_2, tmp_path / "ds")


FIRST = sorted(fx.task_ids())[0]
SHARD = shard_path(FIRST, fx.ATTEMPT, 2)


def samples_by_id() -> dict[str, object]:
    return {s.sample_id: s for result in fx.task_results() for s in result.samples}


def test_a_version_1_dataset_reads_and_validates(version_1: Path) -> None:
    dataset = open_dataset(str(version_1))
    assert dataset.info.schema_version == 1 and not dataset.has_ambiguity
    assert "label_support" not in dataset.index.column_names
    sample = dataset[3]
    # a version-1 sample: the core keys and the batch-only fields every version has, never covers
    assert set(sample) == {"sample_id", "points", "observed", "view_state", "label", "index", "cloud_size"}
    assert validate(str(version_1), full=True) == []
    with pytest.raises(StorageError, match=r"keeps no minimum covers; add them with `datagen shards relabel"):
        dataset.ambiguity(3)


def test_version_2_serves_the_covers_the_pipeline_computed(version_2: Path) -> None:
    dataset = open_dataset(str(version_2))
    assert dataset.has_ambiguity and dataset.info.schema_version == 2
    computed = samples_by_id()
    for i in range(len(dataset)):
        sample = dataset[i]
        expected = computed[sample["sample_id"]].cover.ambiguity  # type: ignore[attr-defined]
        found = dataset.ambiguity(i)
        assert tuple(int(c) for c in found.covers) == expected.covers
        assert (found.count, found.exact, found.support) == (expected.count, expected.exact, expected.support)
        assert sample["covers"].shape == (len(expected.covers), dataset.num_views)
        assert sample["min_covers"] == expected.count
        assert np.array_equal(sample["support"], [bool(expected.support >> v & 1) for v in range(dataset.num_views)])
        assert np.isclose(sample["marginals"].sum(), sample["label"].sum())  # every minimum cover has |L| views
        label = dataset.masks(i)[1]
        assert found.covers_universe(label)
        for cover in found.covers:
            assert found.covers_universe(int(cover))
        if label:
            lowest = label & -label
            assert not found.covers_universe(label & ~lowest)  # a minimum cover has no spare view


def test_cover_rows_judge_a_view_set_as_the_full_masks_do(version_2: Path) -> None:
    """A view set covers U exactly when it meets every cover row that misses S, as a test over every
    key of P_full says."""
    result = next(r for r in fx.task_results() if r.task_id == FIRST)
    rows = fx.stored_array(version_2 / SHARD, COVER_ROWS)
    from datagen.pipeline.coverage import coverage_table

    full = coverage_table(result.sets.refined, fx.config().alpha).masks
    rng = np.random.default_rng(0)
    for sample in result.samples[:20]:
        for views in [sample.label, *rng.integers(0, 1 << 32, size=30, dtype=np.uint64).tolist()]:
            universe = full[(full & np.uint64(sample.case)) == 0]
            truth = bool(((universe & np.uint64(views)) != 0).all())
            assert covers_universe(rows, sample.case, int(views)) == truth


def test_nearest_cover_shares_most_views() -> None:
    covers = np.array([0b0011, 0b0101, 0b1100], dtype=np.uint64)
    assert nearest_cover(covers, 0b1000) == 0b1100
    assert nearest_cover(covers, 0b0001) == 0b0011  # a tie goes to the first listed
    assert nearest_cover(covers, 0b1101) == 0b0101  # two shared with 0b0101 and 0b1100: the first


def test_an_unknown_schema_version_is_one_line(ds: Path) -> None:
    info = json.loads((ds / "dataset.json").read_text())
    info["schema_version"] = 99
    (ds / "dataset.json").write_text(json.dumps(info))
    with pytest.raises(StorageError, match=r"schema version 99; this reader knows 1, 2, 3, 4, 5: upgrade datagen"):
        open_dataset(str(ds))


def edit(ds: Path, name: str, change) -> None:  # type: ignore[no-untyped-def]
    fx.edit_array(ds / SHARD, name, change)


def first_ambiguous_row() -> int:
    """A row of the first task whose label is one of several minimum covers."""
    result = next(r for r in fx.task_results() if r.task_id == FIRST)
    return next(i for i, s in enumerate(result.samples) if s.cover.ambiguity.count > 2)


def test_a_listed_cover_that_does_not_cover_u(ds: Path) -> None:
    row = first_ambiguous_row()

    def drop_a_view(covers: np.ndarray) -> np.ndarray:
        offsets = fx.stored_array(ds / SHARD, offsets_array(COVERS))
        masks = fx.stored_array(ds / SHARD, MASKS)
        last = offsets[row + 1] - 1
        if covers[last] == masks[row, LABEL_COLUMN]:
            last -= 1
        covers[last] = covers[last] & (covers[last] - np.uint64(1))
        return covers

    edit(ds, COVERS, drop_a_view)
    found = validate(str(ds), full=True)
    assert any(f"{SHARD} row {row}:" in line for line in found), found


def test_the_label_missing_from_its_covers(ds: Path) -> None:
    row = first_ambiguous_row()
    label = int(fx.stored_array(ds / SHARD, MASKS)[row, LABEL_COLUMN])
    case = int(fx.stored_array(ds / SHARD, MASKS)[row, VIEW_STATE_COLUMN])
    offsets = fx.stored_array(ds / SHARD, offsets_array(COVERS))

    def replace_label(covers: np.ndarray) -> np.ndarray:
        listed = covers[offsets[row] : offsets[row + 1]]
        position = offsets[row] + int(np.flatnonzero(listed == np.uint64(label))[0])
        covers[position] = covers[offsets[row] + (1 if position == offsets[row] else 0)]
        return covers

    assert label & case == 0
    edit(ds, COVERS, replace_label)
    found = validate(str(ds), full=True)
    assert f"{SHARD} row {row}: label {tuple(v for v in range(32) if label >> v & 1)} is not among" in "\n".join(found)


def test_cover_rows_that_are_not_p_fulls(ds: Path) -> None:
    edit(ds, COVER_ROWS, lambda rows: rows[1:])
    assert validate(str(ds), full=True) == [
        f"{SHARD}: {COVER_ROWS} are not the undominated masks of P_full recomputed from the stored P_i"
    ]


def test_cover_offsets_that_do_not_end_at_the_covers(ds: Path) -> None:
    edit(ds, offsets_array(COVERS), lambda offsets: offsets[:-1])
    found = validate(str(ds), full=True)
    assert any(line.startswith(f"{SHARD}: {offsets_array(COVERS)} has shape") for line in found), found


def test_a_version_1_shard_in_a_version_2_dataset(tmp_path: Path) -> None:
    """A dataset keeps one layout: a shard of another version is named (writers add tasks in the
    dataset's own version)."""
    root = tmp_path / "mixed"
    v1_first = next(p for p in fx.payloads(1) if p.attributes.task_id == FIRST)
    v2_rest = [p for p in fx.payloads(2) if p.attributes.task_id != FIRST]
    fx.build_dataset(str(root), [v1_first, *v2_rest], schema_version=2)
    found = validate(str(root), full=True)
    assert f"{SHARD}: schema version 1, the dataset is version 2" in found


def test_a_task_whose_every_label_is_empty_reads_back(tmp_path: Path) -> None:
    """Its covers are all zero (the empty cover); zarr would skip such a chunk as fill value, and a
    reader must still find every chunk file (a missing one means damage)."""
    import dataclasses

    from datagen.engine.shard_payload import task_payload

    result = next(r for r in fx.task_results() if r.task_id == FIRST)
    empty = [s for s in result.samples if s.empty_label]
    assert empty, "the capsule has input cases that already see all of P_full"
    payload = task_payload(dataclasses.replace(result, samples=tuple(empty)), fx.config())
    assert not payload.arrays[COVERS].any()
    root = tmp_path / "empty"
    fx.build_dataset(str(root), [payload], finalise_index=True)
    dataset = open_dataset(str(root))
    assert [dataset.ambiguity(i).covers.tolist() for i in range(len(dataset))] == [[0]] * len(empty)
    assert validate(str(root), full=True) == []
