"""storage.torch: OSVPDataset tensors, seeded resampling, splits, lazy per-worker stores, and the
shard-aware sampler, on a small real dataset (3 built-ins x 2 rotations, `support.torch_data`).

Expected values come from the pipeline's own output (`support.torch_data.Built.samples`), not from the
reader under test.
"""

from __future__ import annotations

import itertools
import os
import pickle

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pytest
import torch
from support.torch_data import Built, bits, cached_dataset
from torch.utils.data import DataLoader, Subset

from datagen.pipeline.keys import key_centres, unpack_keys
from storage.readers import load_memory
from storage.torch import OSVPDataset, ShardShuffleSampler

NUM_POINTS = 256


@pytest.fixture(scope="session")
def small(tmp_path_factory: pytest.TempPathFactory) -> Built:
    return cached_dataset("small", tmp_path_factory.mktemp("torch_small"))


def sample_ids(dataset: OSVPDataset) -> list[str]:
    return dataset.dataset.index.column("sample_id").to_pylist()


def assert_centres_of(points: np.ndarray, packed: np.ndarray, built: Built) -> np.ndarray:
    """Every point is exactly (float32) the centre of one of the packed keys; returns the keys hit."""
    config = built.config
    keys = np.floor(points.astype(np.float64) / config.voxel_size + np.asarray(config.grid_offset)).astype(np.int64)
    centres = key_centres(keys, config.voxel_size, config.grid_offset).astype(np.float32)
    np.testing.assert_array_equal(points, centres)
    expected = unpack_keys(packed)
    expected_rows = {tuple(k) for k in expected.tolist()}
    hit = {tuple(k) for k in keys.tolist()}
    assert hit <= expected_rows
    return keys


def items_by_index(loader: DataLoader) -> dict[int, dict[str, torch.Tensor]]:
    out: dict[int, dict[str, torch.Tensor]] = {}
    for batch in loader:
        for j, index in enumerate(batch["index"].tolist()):
            assert index not in out
            out[index] = {k: v[j] for k, v in batch.items()}
    return out


def assert_same_items(a: dict[int, dict[str, torch.Tensor]], b: dict[int, dict[str, torch.Tensor]]) -> None:
    assert a.keys() == b.keys()
    for index in a:
        for name in ("points", "view_state", "label", "index"):
            assert torch.equal(a[index][name], b[index][name]), (index, name)


# ---------------------------------------------------------------------------------------------------------
# tensors
# ---------------------------------------------------------------------------------------------------------


def test_every_item_has_shapes_dtypes_and_the_stored_values(small: Built) -> None:
    dataset = OSVPDataset(small.url, num_points=NUM_POINTS)
    assert len(dataset) == len(small.samples)
    ids = sample_ids(dataset)
    assert set(ids) == set(small.samples)
    n = dataset.dataset.num_views
    # the fields every reader gives for this dataset (the registry's), as the in-memory batch has them
    fields = set(load_memory(small.url).batch([0], NUM_POINTS, 0, 0).as_dict())
    assert {"points", "view_state", "label", "index", "cloud_size", "marginals", "support"} <= fields
    for i in range(len(dataset)):
        item = dataset[i]
        expected = small.samples[ids[i]]
        assert set(item) == fields
        assert item["points"].shape == (NUM_POINTS, 3) and item["points"].dtype == torch.float32
        assert item["view_state"].shape == (n,) and item["view_state"].dtype == torch.float32
        assert item["label"].shape == (n,) and item["label"].dtype == torch.float32
        assert int(item["index"]) == i
        np.testing.assert_array_equal(item["view_state"].numpy(), bits(expected.case, n))
        np.testing.assert_array_equal(item["label"].numpy(), bits(expected.label, n))
        keys = assert_centres_of(item["points"].numpy(), expected.points, small)
        if len(expected.points) >= NUM_POINTS:  # drawn without replacement: distinct points
            assert len({tuple(k) for k in keys.tolist()}) == NUM_POINTS


def test_fewer_keys_than_points_draws_with_replacement(small: Built) -> None:
    sizes = {sid: len(s.points) for sid, s in small.samples.items()}
    num_points = int(np.median(list(sizes.values())))
    dataset = OSVPDataset(small.url, num_points=num_points)
    ids = sample_ids(dataset)
    short = [i for i, sid in enumerate(ids) if sizes[sid] < num_points][:5]
    assert short
    for i in short:
        expected = small.samples[ids[i]]
        points = dataset[i]["points"].numpy()
        assert points.shape == (num_points, 3)
        keys = assert_centres_of(points, expected.points, small)
        assert len({tuple(k) for k in keys.tolist()}) <= len(expected.points)


def test_observed_source_uses_observed_keys(small: Built) -> None:
    dataset = OSVPDataset(small.url, num_points=NUM_POINTS, source="observed")
    refined = OSVPDataset(small.url, num_points=NUM_POINTS, source="points")
    ids = sample_ids(dataset)
    differ = 0
    for i in range(0, len(dataset), 7):
        expected = small.samples[ids[i]]
        # the fixture's ShiftRefiner makes P(O_S) a strict superset of keys(O_S)
        assert len(expected.points) > len(expected.observed)
        assert_centres_of(dataset[i]["points"].numpy(), expected.observed, small)
        points = refined[i]["points"].numpy()
        assert_centres_of(points, expected.points, small)
        keys = np.floor(points.astype(np.float64) / small.config.voxel_size + np.asarray(small.config.grid_offset))
        observed = {tuple(k) for k in unpack_keys(expected.observed).tolist()}
        differ += any(tuple(k) not in observed for k in keys.astype(np.int64).tolist())
    assert differ > 0  # source='points' does read the refined set


def test_bad_arguments_are_refused(small: Built) -> None:
    with pytest.raises(ValueError, match="source"):
        OSVPDataset(small.url, source="gt")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="num_points"):
        OSVPDataset(small.url, num_points=0)


# ---------------------------------------------------------------------------------------------------------
# resampling depends only on (seed, epoch, index)
# ---------------------------------------------------------------------------------------------------------


def test_resampling_is_a_function_of_seed_epoch_and_index(small: Built) -> None:
    a = OSVPDataset(small.url, num_points=NUM_POINTS, seed=5)
    b = OSVPDataset(small.url, num_points=NUM_POINTS, seed=5)
    other_seed = OSVPDataset(small.url, num_points=NUM_POINTS, seed=6)
    indices = [0, 3, len(a) // 2, len(a) - 1]
    for i in reversed(indices):  # a different access order changes nothing
        b[i]
    for i in indices:
        assert torch.equal(a[i]["points"], b[i]["points"])
        assert torch.equal(a[i]["points"], a[i]["points"])  # repeated access: same draw
        assert not torch.equal(a[i]["points"], other_seed[i]["points"])
    epoch0 = {i: a[i]["points"] for i in indices}
    a.set_epoch(1)
    b.set_epoch(1)
    for i in indices:
        assert not torch.equal(a[i]["points"], epoch0[i])
        assert torch.equal(a[i]["points"], b[i]["points"])
        assert torch.equal(a[i]["label"], b[i]["label"])
    a.set_epoch(0)
    for i in indices:
        assert torch.equal(a[i]["points"], epoch0[i])


def test_dataloader_workers_see_the_same_tensors_as_the_main_process(small: Built) -> None:
    dataset = OSVPDataset(small.url, num_points=NUM_POINTS, seed=2)
    dataset.set_epoch(3)  # before the iterators are made: workers get this epoch
    sampler = ShardShuffleSampler(dataset, seed=1)
    serial = items_by_index(DataLoader(dataset, batch_size=16, sampler=sampler, num_workers=0))
    parallel = items_by_index(DataLoader(dataset, batch_size=16, sampler=sampler, num_workers=2))
    assert set(serial) == set(range(len(dataset)))
    assert_same_items(serial, parallel)
    # and the epoch really reached the workers
    for index in (0, len(dataset) - 1):
        assert torch.equal(parallel[index]["points"], dataset[index]["points"])
        dataset.set_epoch(0)
        assert not torch.equal(parallel[index]["points"], dataset[index]["points"])
        dataset.set_epoch(3)


# ---------------------------------------------------------------------------------------------------------
# object-level splits
# ---------------------------------------------------------------------------------------------------------


def test_train_and_val_partition_the_samples_by_object(small: Built) -> None:
    whole = OSVPDataset(small.url, num_points=16)
    train = OSVPDataset(small.url, num_points=16, split="train", val_fraction=0.34, split_seed=4)
    val = OSVPDataset(small.url, num_points=16, split="val", val_fraction=0.34, split_seed=4)
    train_ids, val_ids = sample_ids(train), sample_ids(val)
    assert len(train) + len(val) == len(whole)
    assert set(train_ids) | set(val_ids) == set(small.samples)
    assert not set(train_ids) & set(val_ids)
    train_objects = {small.samples[s].object_id for s in train_ids}
    val_objects = {small.samples[s].object_id for s in val_ids}
    assert not train_objects & val_objects
    assert train_objects | val_objects == small.objects
    assert len(val_objects) == round(0.34 * len(small.objects)) == 1
    # items of a split dataset are the samples its index names
    for i in (0, len(val) - 1):
        expected = small.samples[val_ids[i]]
        np.testing.assert_array_equal(val[i]["label"].numpy(), bits(expected.label, 32))
        assert_centres_of(val[i]["points"].numpy(), expected.points, small)
    # deterministic in split_seed; other seeds pick other objects
    again = OSVPDataset(small.url, num_points=16, split="val", val_fraction=0.34, split_seed=4)
    assert sample_ids(again) == val_ids
    chosen = {
        frozenset(
            small.samples[s].object_id
            for s in sample_ids(OSVPDataset(small.url, num_points=16, split="val", val_fraction=0.34, split_seed=k))
        )
        for k in range(8)
    }
    assert len(chosen) > 1


# ---------------------------------------------------------------------------------------------------------
# stores are opened lazily, per process
# ---------------------------------------------------------------------------------------------------------


def test_dataset_pickles_without_open_stores_after_use(small: Built) -> None:
    dataset = OSVPDataset(small.url, num_points=NUM_POINTS, seed=9)
    first = dataset[0]
    last = dataset[len(dataset) - 1]
    assert dataset.dataset._shards  # handles are open (and cached) in this process
    data = pickle.dumps(dataset)
    assert dataset.dataset._shards  # pickling does not close this process's handles
    copy = pickle.loads(data)
    assert not copy.dataset._shards  # no handles travelled
    assert torch.equal(copy[0]["points"], first["points"])
    assert torch.equal(copy[len(copy) - 1]["label"], last["label"])
    # the cached arrays (all keys of the shards read so far, or the chunks a window of them decoded)
    # did not travel either
    readers = dataset.dataset._shards.values()
    cached = sum(a.nbytes for r in readers for a in r._cache.values())
    cached += sum(
        a.nbytes for r in readers for t in r._takers.values() if t._chunked for a in t._chunked._chunks.values()
    )
    assert len(data) < cached


@pytest.mark.parametrize("context", ["fork", "spawn"])
def test_dataloader_works_with_fork_and_spawn(small: Built, context: str) -> None:
    dataset = OSVPDataset(small.url, num_points=64, seed=4)
    dataset[0]  # open a store in the parent first: the workers must not inherit a broken handle
    subset = Subset(dataset, list(range(0, len(dataset), 5)))
    loader = DataLoader(subset, batch_size=8, num_workers=2, multiprocessing_context=context)
    got = items_by_index(loader)
    assert set(got) == set(subset.indices)
    for index, item in got.items():
        expected = dataset[index]
        for name in ("points", "view_state", "label"):
            assert torch.equal(item[name], expected[name])


# ---------------------------------------------------------------------------------------------------------
# ShardShuffleSampler
# ---------------------------------------------------------------------------------------------------------


def test_shard_shuffle_sampler_is_a_seeded_permutation_per_epoch(small: Built) -> None:
    dataset = OSVPDataset(small.url, num_points=16)
    sampler = ShardShuffleSampler(dataset, seed=3, shards_mixed=1)
    first = list(sampler)
    assert len(sampler) == len(dataset)
    assert sorted(first) == list(range(len(dataset)))
    assert first != list(range(len(dataset)))
    assert list(ShardShuffleSampler(dataset, seed=3, shards_mixed=1)) == first
    assert list(ShardShuffleSampler(dataset, seed=4, shards_mixed=1)) != first
    sampler.set_epoch(1)
    second = list(sampler)
    assert sorted(second) == sorted(first) and second != first
    sampler.set_epoch(0)
    assert list(sampler) == first


def test_shard_shuffle_sampler_keeps_to_few_shards_at_a_time(small: Built) -> None:
    dataset = OSVPDataset(small.url, num_points=16)
    shard_of = dataset.dataset.index.column("shard").to_pylist()
    shards = len(set(shard_of))
    assert shards >= 6

    def same_shard_rate(order: list[int]) -> float:
        return float(np.mean([shard_of[a] == shard_of[b] for a, b in itertools.pairwise(order)]))

    local = same_shard_rate(list(ShardShuffleSampler(dataset, seed=0, shards_mixed=1)))
    # mixing every shard at once is a plain shuffle: consecutive samples share a shard ~1/shards
    mixed = same_shard_rate(list(ShardShuffleSampler(dataset, seed=0, shards_mixed=shards)))
    assert local > 0.6
    assert mixed < 2.0 / shards
