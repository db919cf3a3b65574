"""`Dataset[i]`, the sample a person reads (README "Read a dataset in five lines"), pinned.

Every sample of a small dataset, in a layout with minimum covers (the current one) and in layout 1
without them, is compared array by array (dtype, shape and every value) with what the stored files
hold, read here by zarr itself: the whole clouds in metres, the view state and label as
one bool per view, and with covers the support, the listed covers, their marginals and the count.
`Dataset[i]` reads through the field registry (`storage.samples.SAMPLE_FIELDS`) and the one assembler;
these are the values and keys it gave when it still had a read path of its own, so a sample reads as
it always has (a field registered from a test module reaches it too: `test_toy_field.py`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import pytest
from support import storage as fx

from schemas.shard import COVERS, LABEL_COLUMN, MASKS, VIEW_STATE_COLUMN, keys_array, offsets_array
from storage import open_dataset

CORE_KEYS = {"sample_id", "points", "observed", "view_state", "label"}
COVER_KEYS = {"support", "marginals", "covers", "min_covers", "min_covers_exact"}


@pytest.fixture(scope="module")
def current(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return fx.finalised_dataset(tmp_path_factory, fx.SCHEMA_VERSION)


@pytest.fixture(scope="module")
def first(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return fx.finalised_dataset(tmp_path_factory, 1)


def _bools(masks: Any, width: int) -> npt.NDArray[np.bool_]:
    values = np.asarray(masks, dtype=np.uint64)
    return ((values[..., None] >> np.arange(width, dtype=np.uint64)) & np.uint64(1)).astype(bool)


def _centres(keys: npt.NDArray[Any], voxel: float, offset: npt.NDArray[np.float64]) -> npt.NDArray[np.float32]:
    return ((keys.astype(np.float64) + 0.5 - offset) * voxel).astype(np.float32)


def _stored(root: Path) -> list[dict[str, Any]]:
    """Every sample as the stored files give it, in the reader's order (read here, not by `storage`)."""
    ds = open_dataset(str(root))
    config = ds.info.config
    voxel, offset = float(config.voxel_size), np.asarray(config.grid_offset, dtype=np.float64)
    width = ds.num_views
    index = ds.index.to_pylist()
    by_id = {row["sample_id"]: row for row in index}
    arrays: dict[tuple[str, str], npt.NDArray[Any]] = {}

    def array(shard: str, name: str) -> npt.NDArray[Any]:
        if (shard, name) not in arrays:
            arrays[shard, name] = fx.stored_array(root / shard, name)
        return arrays[shard, name]

    samples = []
    for i in range(len(ds)):
        shard, row = ds.shard_of(i), ds.row_of(i)
        facts = by_id[ds.index_row(i)["sample_id"]]
        masks = array(shard, MASKS)[row]
        sample: dict[str, Any] = {"sample_id": facts["sample_id"]}
        for source in ("points", "observed"):
            offsets = array(shard, offsets_array(source))
            keys = array(shard, keys_array(source))[offsets[row] : offsets[row + 1]]
            sample[source] = _centres(keys, voxel, offset)
        sample["view_state"] = _bools(int(masks[VIEW_STATE_COLUMN]), width)
        sample["label"] = _bools(int(masks[LABEL_COLUMN]), width)
        if "label_support" in facts:
            offsets = array(shard, offsets_array(COVERS))
            listed = np.asarray(array(shard, COVERS)[offsets[row] : offsets[row + 1]], dtype=np.uint64)
            bits = _bools(listed, width)
            sample["support"] = _bools(int(facts["label_support"]), width)
            sample["marginals"] = (bits.mean(axis=0) if listed.size else np.zeros(width)).astype(np.float32)
            sample["covers"] = bits
            sample["min_covers"] = int(facts["min_covers"])
            sample["min_covers_exact"] = bool(facts["min_covers_exact"])
        samples.append(sample)
    return samples


def _same(found: Any, expected: Any, where: str) -> None:
    if isinstance(expected, np.ndarray):
        assert isinstance(found, np.ndarray), where
        assert found.dtype == expected.dtype and found.shape == expected.shape, where
        assert np.array_equal(found, expected), where
    else:
        assert type(found) is type(expected) and found == expected, where


@pytest.mark.parametrize("layout", ["current", "first"])
def test_every_sample_reads_as_stored(layout: str, request: pytest.FixtureRequest) -> None:
    root: Path = request.getfixturevalue(layout)
    ds = open_dataset(str(root))
    stored = _stored(root)
    assert len(stored) == len(ds) > 10
    for i, expected in enumerate(stored):
        found = ds[i]
        assert list(found)[: len(expected)] == list(expected)  # today's keys first, in today's order
        assert set(expected) == (CORE_KEYS | COVER_KEYS if layout == "current" else CORE_KEYS)
        for key, value in expected.items():
            _same(found[key], value, f"sample {i} {key}")
    last = ds[-1]
    for key, value in stored[-1].items():
        _same(last[key], value, f"sample -1 {key}")
    with pytest.raises(IndexError):
        ds[len(ds)]


def test_a_selection_reads_its_samples_as_the_whole_dataset(current: Path) -> None:
    ds = open_dataset(str(current))
    rows = [5, 0, 3]
    chosen = ds.select(rows)
    for position, row in enumerate(rows):
        whole, part = ds[row], chosen[position]
        for key in CORE_KEYS | COVER_KEYS:
            _same(part[key], whole[key], f"row {row} {key}")


def test_the_registered_fields_a_sample_carries(current: Path) -> None:
    """Beside its own keys a sample carries every other registered field the dataset has, as the row
    of a one-sample batch (the next-view labels of a version-3 dataset among them)."""
    ds = open_dataset(str(current))
    sample = ds[2]
    batch_only = {"index", "cloud_size", "view_gain", "coverage_gain", "best_view"}
    assert batch_only <= set(sample)
    view = ds.next_view(2)
    assert int(sample["best_view"]) == view.best_view
    assert sample["index"] == 2
    assert int(sample["cloud_size"]) == sample["points"].shape[0]
    expected_gain = (view.view_gains.astype(np.float64) / view.visible_size).astype(np.float32)
    _same(sample["view_gain"], expected_gain, "view_gain")
