"""Schema version 4: each refined cloud stored in a seeded random order, read by windows.

The truths here are written out in the test, not taken from the library: the permutation is numpy's
``permutation`` from ``SeedSequence([seed, object id prefix, rotation, 4, case])``; a window of N
points is the stored rows ``(start + 0..N-1) mod K`` from ``start`` = the first 64-bit word of
stream ``SeedSequence([seed, epoch, row])`` mod K; an older dataset's cloud is ``choice(K, N, replace=K < N,
shuffle=False)`` from that same stream, as before version 4. Datasets: the storage tests' two
built-ins (`support.storage`), in version 4 and in version 3.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import numpy.typing as npt
import pytest
import torch
import zarr
from support import storage as fx

from datagen.pipeline.random_streams import Purpose, stream
from schemas.shard import keys_array, offsets_array, point_order
from storage import ShardReader, StorageError, open_dataset, validate
from storage.dataset import shard_path
from storage.readers import load_memory
from storage.samples import gather_clouds
from storage.shards import COMPRESSORS, POINT_CHUNK_ROWS, RowTaker
from storage.stream import ShardStream
from storage.torch import OSVPDataset

SEED = 5
FIRST = sorted(fx.task_ids())[0]
SHARD = shard_path(FIRST, fx.ATTEMPT, 4)


def window_truth(cloud: npt.NDArray[np.int16], num_points: int, seed: int, epoch: int, row: int) -> npt.NDArray:
    """A version-4 cloud's N points, as the contract states them."""
    stream = np.random.SeedSequence([seed, epoch, row])
    if cloud.shape[0] <= num_points:  # whole, with repeats: the older rule
        rng = np.random.default_rng(stream)
        return cloud[rng.choice(cloud.shape[0], size=num_points, replace=cloud.shape[0] < num_points, shuffle=False)]
    start = int(np.random.default_rng(stream).bit_generator.random_raw()) % cloud.shape[0]
    return cloud[(start + np.arange(num_points)) % cloud.shape[0]]


def older_truth(cloud: npt.NDArray[np.int16], num_points: int, seed: int, epoch: int, row: int) -> npt.NDArray:
    """An older dataset's N points, as before version 4."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, epoch, row]))
    return cloud[rng.choice(cloud.shape[0], size=num_points, replace=cloud.shape[0] < num_points, shuffle=False)]


def streamed(root: Path, num_points: int, epoch: int, workers: int = 0) -> dict[int, npt.NDArray[np.int16]]:
    """Every sample's keys through `ShardStream`, by dataset row (back from metres to keys)."""
    source = ShardStream(
        str(root), num_points=num_points, batch_size=16, seed=SEED, epoch=epoch, shuffle_buffer=32, num_workers=workers
    )
    found: dict[int, npt.NDArray[np.int16]] = {}
    dataset = open_dataset(str(root))
    for batch in source.loader(multiprocessing_context="fork" if workers else None):
        for row, points in zip(batch.index.tolist(), batch.points.numpy(), strict=True):
            found[row] = to_keys(dataset, points)
    return found


def to_keys(dataset, points: npt.NDArray[np.float32]) -> npt.NDArray[np.int16]:  # type: ignore[no-untyped-def]
    """Float32 centres back to their integer keys (the centre lies half a voxel inside its key)."""
    config = dataset.info.config
    return np.floor(points.astype(np.float64) / config.voxel_size + np.asarray(config.grid_offset)).astype(np.int16)


def assert_every_reader_gives(root: Path, num_points: int, epoch: int, truths: list[npt.NDArray[np.int16]]) -> None:
    """`ShardStream`, `load_memory` and `OSVPDataset` give ``truths[row]`` for every dataset row in
    ``epoch``: the same keys, and the map-style path the very float32 centres of those keys."""
    dataset = open_dataset(str(root))
    memory = load_memory(str(root))
    mapped = OSVPDataset(str(root), num_points=num_points, seed=SEED)
    mapped.set_epoch(epoch)
    from_stream = streamed(root, num_points, epoch=epoch)
    from_memory = memory.resampled_keys(np.arange(len(memory)), num_points, SEED, epoch)
    assert len(truths) == len(dataset) == len(from_stream)
    for row, truth in enumerate(truths):
        assert np.array_equal(from_stream[row], truth), row
        assert np.array_equal(from_memory[row], truth), row
        assert torch.equal(mapped[row]["points"], torch.from_numpy(dataset.centres(truth))), row


def test_the_generator_stores_each_cloud_in_the_seeded_order(version_4: Path) -> None:
    """Stored row j of a cloud is key order[j] of the case's sorted cloud, order the permutation of the
    sample's own stream; the points array is chunked so that a window meets one or two chunks."""
    computed = {s.sample_id: s for r in fx.task_results() for s in r.samples}
    dataset = open_dataset(str(version_4))
    config, task = dataset.info.config, fx.task_results()[0]
    ids = dataset.index.column("sample_id").to_pylist()
    for i in range(len(dataset)):
        sample = computed[ids[i]]
        stored = dataset.keys(i, "points")
        truth_order = np.random.default_rng(
            np.random.SeedSequence([config.seed, int(task.object_id[:16], 16), 0, 4, sample.case])
        ).permutation(sample.points.size)
        object_id = dataset.index.column("object_id")[i].as_py()
        order = point_order(config.seed, object_id, 0, sample.case, sample.points.size)
        assert np.array_equal(stored, fx.int16_keys(sample.points)[order]), ids[i]
        if object_id == task.object_id:
            assert np.array_equal(order, truth_order)
    rule = stream(config.seed, task.object_id, 0, Purpose.POINT_ORDER, 5).permutation(100)
    assert np.array_equal(point_order(config.seed, task.object_id, 0, 5, 100), rule)
    meta = json.loads((version_4 / SHARD / keys_array("points") / "zarr.json").read_text())
    assert meta["codecs"][0]["configuration"]["chunk_shape"] == [POINT_CHUNK_ROWS, 3]
    observed = zarr.open_group(str(version_4 / SHARD), mode="r")
    first = observed[offsets_array("observed")][1]
    assert (np.diff(observed[keys_array("observed")][:first].astype(np.int64), axis=0)[:, 0] >= 0).all()


@pytest.mark.parametrize("num_points", [2048, 5000])
def test_every_reader_gives_the_window_of_the_stored_order(version_4: Path, num_points: int) -> None:
    """`ShardStream`, `load_memory` and `OSVPDataset` give each sample's window of its stored order (or,
    for a cloud of at most N points, the whole cloud as before); 5,000 points meet both kinds of cloud."""
    dataset = open_dataset(str(version_4))
    sizes = dataset.index.column("num_points").to_numpy()
    assert (sizes > num_points).any() and (num_points < 5000 or (sizes <= num_points).any())
    truths = [window_truth(dataset.keys(row, "points"), num_points, SEED, 2, row) for row in range(len(dataset))]
    assert_every_reader_gives(version_4, num_points, 2, truths)


def test_another_epoch_reads_another_window(version_4: Path) -> None:
    first, second = streamed(version_4, 2048, epoch=0), streamed(version_4, 2048, epoch=1)
    assert sum(not np.array_equal(first[row], second[row]) for row in first) == len(first)


def test_a_window_decodes_only_its_chunks(version_4: Path, tmp_path: Path) -> None:
    """A chunk far from the window is corrupted: the window still reads; a read that needs that chunk
    is the reader's `StorageError` naming the shard."""
    root = fx.copy_dataset(version_4, tmp_path / "ds")
    data_file = root / SHARD / keys_array("points") / "c" / "0" / "0"
    blob = bytearray(data_file.read_bytes())
    rows = int(json.loads((root / SHARD / keys_array("points") / "zarr.json").read_text())["shape"][0])
    chunks = -(-rows // POINT_CHUNK_ROWS)
    entries = np.frombuffer(bytes(blob[-(16 * chunks + 4) : -4]), dtype="<u8").reshape(-1, 2)
    start, size = (int(v) for v in entries[chunks - 2])
    blob[start + size // 2 : start + size // 2 + 8] = b"\xff" * 8
    data_file.write_bytes(bytes(blob))
    dataset = open_dataset(str(root))
    reader = ShardReader(dataset.location, SHARD)
    offsets = reader.array(offsets_array("points"))
    taker = RowTaker(reader, keys_array("points"))
    window = np.arange(100, 100 + 2048, dtype=np.int64)
    expected = zarr.open_group(str(version_4 / SHARD), mode="r")[keys_array("points")][100 : 100 + 2048]
    assert np.array_equal(taker.take(window), expected)
    clouds = gather_clouds(taker.take, offsets[:1], np.diff(offsets[:2]), np.zeros(1, np.int64), 2048, SEED, 0, True)
    intact = ShardReader(open_dataset(str(version_4)).location, SHARD).key_set("points", 0)
    assert np.array_equal(clouds[0], window_truth(intact, 2048, SEED, 0, 0))
    with pytest.raises(StorageError, match=rf"{SHARD}/{keys_array('points')}.*datagen shards validate"):
        taker.take(np.array([(chunks - 2) * POINT_CHUNK_ROWS + 5], dtype=np.int64))


def test_a_take_gives_zarrs_rows_for_any_rows(version_4: Path) -> None:
    """Rows near each other (within a few chunks: no marks), spread over the array, repeated,
    unordered, wrapped and none: each take equals zarr's own read of those rows."""
    reader = ShardReader(open_dataset(str(version_4)).location, SHARD)
    stored = zarr.open_group(str(version_4 / SHARD), mode="r")[keys_array("points")][...]
    total = stored.shape[0]
    assert total > 4 * POINT_CHUNK_ROWS
    rng = np.random.default_rng(7)
    near = rng.integers(POINT_CHUNK_ROWS - 3, 3 * POINT_CHUNK_ROWS + 5, size=900)
    wrapped = np.concatenate([np.arange(total - 700, total), np.arange(0, 1348)])
    cases = [near, rng.integers(0, total, size=3000), np.array([5, 5, 2, 5]), wrapped, np.zeros(0, np.int64)]
    for rows in cases:
        taker = RowTaker(reader, keys_array("points"))  # fresh: no chunk decoded by an earlier case
        assert np.array_equal(taker.take(rows.astype(np.int64)), stored[rows])
    with pytest.raises(IndexError):
        RowTaker(reader, keys_array("points")).take(np.array([total], dtype=np.int64))


def test_the_window_path_is_the_same_with_two_workers(version_4: Path) -> None:
    assert_same(streamed(version_4, 2048, epoch=3), streamed(version_4, 2048, epoch=3, workers=2))


def assert_same(a: dict[int, npt.NDArray[np.int16]], b: dict[int, npt.NDArray[np.int16]]) -> None:
    assert a.keys() == b.keys()
    for row in a:
        assert np.array_equal(a[row], b[row]), row


def test_a_window_is_a_uniform_subsample_of_an_analytic_cloud() -> None:
    """A solid 30 x 30 x 30 block of keys, stored in the seeded order: every window of 2,048 has each
    axis' mean within 5 standard errors of the block's centre (14.5). The sorted order would put a
    window's x mean up to 14 away, 70 standard errors; a window of the stored order never lands there
    unless the order is not random."""
    side, num_points = 30, 2048
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), axis=-1).reshape(-1, 3).astype(np.int16)
    stored = grid[point_order(11, "ab" * 8, 3, 0b1011, grid.shape[0])]
    count = grid.shape[0]
    error = np.sqrt((side**2 - 1) / 12 / num_points * (count - num_points) / (count - 1))
    windows = gather_clouds(
        lambda rows: np.take(stored, rows, axis=0),
        np.zeros(40, dtype=np.int64),
        np.full(40, count, dtype=np.int64),
        np.arange(40, dtype=np.int64),
        num_points,
        SEED,
        0,
        True,
    )
    means = windows.astype(np.float64).mean(axis=1)
    assert np.abs(means - 14.5).max() < 5 * error, (np.abs(means - 14.5).max(), error)
    assert all(np.unique(window, axis=0).shape[0] == num_points for window in windows)  # no key twice
    sorted_window = grid[:num_points].astype(np.float64).mean(axis=0)
    assert abs(sorted_window[0] - 14.5) > 60 * error  # what the test would see without the order


@pytest.mark.parametrize("num_points", [700, 5000])
def test_an_older_dataset_reads_exactly_as_before(version_3: Path, num_points: int) -> None:
    """Version 3 keeps the older rule in every reader: bit-identical clouds."""
    dataset = open_dataset(str(version_3))
    truths = [older_truth(dataset.keys(row, "points"), num_points, SEED, 1, row) for row in range(len(dataset))]
    assert_every_reader_gives(version_3, num_points, 1, truths)


def test_validate_finds_a_cloud_out_of_its_order(version_4: Path, tmp_path: Path) -> None:
    assert validate(str(version_4), full=True) == []
    root = fx.copy_dataset(version_4, tmp_path / "ds")
    group = zarr.open_group(str(root / SHARD), mode="r+")
    offsets = group[offsets_array("points")][...]
    keys = group[keys_array("points")][...]
    row = 3
    start = int(offsets[row])
    keys[[start, start + 1]] = keys[[start + 1, start]]  # the same set, two points swapped
    stored = group[keys_array("points")]
    chunks, shards = stored.chunks, stored.shards
    del group[keys_array("points")]
    group.create_array(keys_array("points"), data=keys, chunks=chunks, shards=shards, compressors=COMPRESSORS)
    found = validate(str(root), full=True)
    assert f"{SHARD} row {row}: {keys_array('points')} is not a sorted, unique set in the stored point order " in (
        "\n".join(found)
    ), found
