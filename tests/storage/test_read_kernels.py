"""The cheaper per-shard steps of the streaming read give exactly what the plain per-sample ones give:
`storage.samples.seeding` (numpy's SeedSequence -> PCG64 seeding on arrays), `samples.resample_many_keys`,
`samples.many_cloud_positions` (version 4's windows and whole-cloud draws, seeded together),
`covers.listed_marginals`, `samples.key_centres` into ``out``, the local listing of a shard
(`group_files.local_files`) and its attributes read without zarr (`ShardReader`).
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import fsspec
import numpy as np
import pytest
from support import storage as fx

from storage import ShardReader, StorageError, open_dataset
from storage.dataset import shard_path
from storage.samples import (
    StreamGenerator,
    cloud_positions,
    cover_marginals,
    key_centres,
    listed_marginals,
    many_cloud_positions,
    pcg64_states,
    resample_keys,
    resample_many_keys,
)
from storage.shards import local_files


def test_pcg64_states_are_numpys() -> None:
    rng = np.random.default_rng(11)
    streams = [tuple(int(v) for v in row) for row in rng.integers(0, 2**32, size=(500, 3))]
    streams += [(0, 0, 0), (0, 0, 1), (7, 3, 0), (2**32 - 1, 2**32 - 1, 2**32 - 1), (0, 2**31, 12)]
    states = pcg64_states(streams)
    assert states is not None
    generator = StreamGenerator()
    for stream, state in zip(streams, states, strict=True):
        expected = np.random.default_rng(np.random.SeedSequence(list(stream)))
        assert (state[0], state[1]) == tuple(expected.bit_generator.state["state"].values()), stream
        drawn = generator.at(state).choice(5000, size=64, replace=False, shuffle=False)
        assert np.array_equal(drawn, expected.choice(5000, size=64, replace=False, shuffle=False)), stream


@pytest.mark.parametrize("stream", [(0, 0, 2**32), (-1, 0, 0), (0, 0, np.int64(4)), (1.0, 0, 0)])
def test_pcg64_states_leave_other_streams_to_numpy(stream: tuple[object, ...]) -> None:
    assert pcg64_states([(0, 0, 1), stream]) is None  # type: ignore[list-item]
    assert pcg64_states([]) == []


@pytest.mark.parametrize("num_points", [1, 64, 2048])
def test_resample_many_keys_is_resample_keys(num_points: int) -> None:
    rng = np.random.default_rng(3)
    sizes = [0, 1, 5, 63, 64, 65, 2047, 2048, 2049, 10_001, 20_000]
    clouds = [rng.integers(-900, 900, size=(size, 3)).astype(np.int16) for size in sizes]
    rows = [int(r) for r in rng.integers(0, 2**31, size=len(sizes))]
    for seed, epoch in ((0, 0), (7, 3), (2**32 - 1, 12)):
        found = resample_many_keys(clouds, num_points, seed, epoch, rows)
        for cloud, row, got in zip(clouds, rows, found, strict=True):
            expected = resample_keys(cloud, num_points, seed, epoch, row)
            assert got.dtype == expected.dtype and np.array_equal(got, expected), (cloud.shape, row)
    # a stream numpy hashes as more words: the plain path, the same arrays
    big = resample_many_keys(clouds[:3], 8, 2**40, 0, [1, 2, 3])
    for cloud, row, got in zip(clouds, [1, 2, 3], big, strict=False):
        assert np.array_equal(got, resample_keys(cloud, 8, 2**40, 0, row))


@pytest.mark.parametrize("windowed", [False, True])
def test_many_cloud_positions_are_cloud_positions(windowed: bool) -> None:
    """Window starts (the stream's first PCG64 word) and whole-cloud draws alike, for clouds smaller
    than, as large as and larger than the count; a stream numpy hashes as more words takes the plain
    path with the same positions."""
    rng = np.random.default_rng(5)
    counts = [1, 5, 2047, 2048, 2049, 4096, 17_700, 100_003]
    rows = [int(r) for r in rng.integers(0, 2**31, size=len(counts))]
    for seed, epoch, num_points in ((0, 0, 2048), (7, 3, 64), (2**32 - 1, 12, 2048), (2**40, 1, 2048)):
        found = many_cloud_positions(counts, num_points, seed, epoch, rows, windowed)
        for count, row, got in zip(counts, rows, found, strict=True):
            expected = cloud_positions(count, num_points, seed, epoch, row, windowed)
            assert got.dtype == expected.dtype and np.array_equal(got, expected), (count, row, seed)


@pytest.mark.parametrize("num_views", [1, 7, 32, 33, 64])
def test_listed_marginals_are_cover_marginals(num_views: int) -> None:
    rng = np.random.default_rng(num_views)
    sizes = rng.integers(0, 30, size=120)
    sizes[[0, 5, -1]] = 0
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    covers = rng.integers(0, 2**63, size=int(offsets[-1]), dtype=np.uint64) * np.uint64(2) + np.uint64(1)
    rows = rng.permutation(sizes.size)[:90]

    def plain(where: np.ndarray) -> np.ndarray:
        return np.stack([cover_marginals(covers[where[r] : where[r + 1]], num_views) for r in rows.tolist()])

    found = listed_marginals(covers, offsets, rows, num_views)
    assert found.dtype == np.float64 and np.array_equal(found.view(np.uint64), plain(offsets).view(np.uint64))
    shuffled = offsets.copy()  # not back to back (a damaged offsets array): sample by sample, the same
    shuffled[[10, 11]] = shuffled[[11, 10]]
    assert np.array_equal(listed_marginals(covers, shuffled, rows, num_views), plain(shuffled))
    assert listed_marginals(covers[:0], np.zeros(4, dtype=np.int64), np.arange(3), num_views).shape == (3, num_views)


def test_key_centres_in_place_are_the_plain_formula() -> None:
    rng = np.random.default_rng(5)
    for shape in ((4, 300, 3), (2, 3, 50, 3), (300, 3), (3,), (0, 5, 3)):
        keys = rng.integers(-32768, 32767, size=shape).astype(np.int16)
        for voxel, offset in ((0.002, (0.2718, 0.3141, 0.1618)), (0.0037, (1e-3, -5.2, 3.3))):
            plain = ((keys.astype(np.float64) + 0.5 - np.asarray(offset)) * voxel).astype(np.float32)
            out = np.empty(keys.shape, dtype=np.float32)
            assert key_centres(keys, voxel, offset, out=out) is out
            assert np.array_equal(out.view(np.uint32), plain.view(np.uint32)), shape
            assert np.array_equal(key_centres(keys, voxel, offset).view(np.uint32), plain.view(np.uint32)), shape


def test_local_files_are_fsspecs_listing(tmp_path: Path) -> None:
    root = tmp_path / "group"
    for relative, size in (("a/zarr.json", 3), ("a/c/0/0", 5), ("a/c/0/1", 0), ("zarr.json", 1), ("b/c/0", 2)):
        (root / relative).parent.mkdir(parents=True, exist_ok=True)
        (root / relative).write_bytes(b"x" * size)
    (root / "empty").mkdir()
    found = fsspec.filesystem("file").find(str(root), detail=True)
    listed = sorted(path.removeprefix(str(root)).strip("/") for path, info in found.items() if info.get("size"))
    assert local_files(str(root)) == listed == ["a/c/0/0", "a/zarr.json", "b/c/0", "zarr.json"]
    assert local_files(str(tmp_path / "missing")) == []


@pytest.mark.parametrize("layout", [4, 5])
def test_shard_attributes_without_zarr_are_zarrs(tmp_path: Path, layout: int) -> None:
    """Both layouts: a folder of files (4) and one ZIP (5)."""
    root = tmp_path / "ds"
    fx.build_dataset(str(root), finalise_index=True, schema_version=layout)
    dataset = open_dataset(str(root))
    relative = shard_path(sorted(fx.task_ids())[0], fx.ATTEMPT, layout)
    reader = ShardReader(dataset.location, relative)
    assert reader._zarr_group is None  # read and verified without opening the group through zarr
    through_zarr = type(reader.attributes).model_validate(dict(reader._group.attrs))
    assert reader.attributes.model_dump() == through_zarr.model_dump()
    if layout == 4:
        (root / relative / "zarr.json").write_text("{not json")
    else:
        fx.corrupt_member(root / relative, "zarr.json")
    with pytest.raises(StorageError, match=r"unreadable group metadata zarr\.json"):
        ShardReader(dataset.location, relative)
    if layout == 4:
        (root / relative / "zarr.json").unlink()
    else:
        (root / relative).unlink()
    with pytest.raises(StorageError, match="the shard group is missing"):
        ShardReader(dataset.location, relative, verify=False)


def test_a_numpy_seeding_otherwise_falls_back_to_numpys_own(monkeypatch: pytest.MonkeyPatch) -> None:
    import storage.samples.seeding as seeding  # the fallback's own switch (an internal)

    assert seeding.agrees_with_numpy()
    monkeypatch.setattr(seeding, "agrees_with_numpy", lambda: False)
    assert seeding.pcg64_states([(1, 2, 3)]) is None
    clouds = [np.arange(300, dtype=np.int16).reshape(100, 3), np.zeros((0, 3), dtype=np.int16)]
    got = resample_many_keys(clouds, 64, 5, 1, [10, 11])
    for cloud, index, drawn in zip(clouds, [10, 11], got, strict=True):
        np.testing.assert_array_equal(drawn, resample_keys(cloud, 64, 5, 1, index))
