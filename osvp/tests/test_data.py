"""The in-memory sample bank against storage's own reader (samples and minimum covers), the two
splits, the nested training subsets, and a version-1 dataset."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from osvp.data import DataError, SampleBank, require_covers, split_rows, training_subset
from osvp.train import TrainOptions, run_rows

import storage
from storage.readers import mask_to_bools


@pytest.fixture(scope="module")
def bank(dataset_url: str) -> SampleBank:
    return SampleBank.load(dataset_url)


def test_every_sample_matches_the_storage_reader(bank: SampleBank, dataset_url: str) -> None:
    dataset = storage.open_dataset(dataset_url)
    assert len(bank) == len(dataset) > 100 and bank.num_views == dataset.num_views == 32
    for i in range(0, len(dataset), 7):
        sample = dataset[i]
        start, stop = bank.offsets[i], bank.offsets[i + 1]
        np.testing.assert_array_equal(bank.keys[start:stop], dataset.keys(i))
        np.testing.assert_array_equal(bank.view_state[i].astype(bool), sample["view_state"])
        np.testing.assert_array_equal(bank.labels[i].astype(bool), sample["label"])


def test_batches_are_key_centres_resampled_per_sample_stream(bank: SampleBank, dataset_url: str) -> None:
    dataset = storage.open_dataset(dataset_url)
    rows = [0, 5, 9]
    batch = bank.batch(rows, 256, seed=3, epoch=1)
    assert batch.points.shape == (3, 256, 3) and batch.points.dtype == torch.float32
    for slot, row in enumerate(rows):
        centres = dataset.centres(dataset.keys(row))
        member = (np.abs(batch.points[slot].numpy()[:, None, :] - centres[None]) < 1e-6).all(axis=2).any(axis=1)
        assert member.all()
    again = bank.batch([9, 0], 256, seed=3, epoch=1)  # another order and batch: same cloud per sample
    assert torch.equal(again.points[0], batch.points[2]) and torch.equal(again.points[1], batch.points[0])
    assert not torch.equal(bank.batch([0], 256, seed=3, epoch=2).points[0], batch.points[0])


def test_sample_split_is_a_seeded_80_20_partition(bank: SampleBank) -> None:
    train, val = split_rows(bank, "samples", 0.2, seed=0)
    assert np.intersect1d(train, val).size == 0 and train.size + val.size == len(bank)
    assert val.size == round(0.2 * len(bank))
    again = split_rows(bank, "samples", 0.2, seed=0)
    assert np.array_equal(again[0], train) and np.array_equal(again[1], val)
    assert not np.array_equal(split_rows(bank, "samples", 0.2, seed=1)[1], val)


def test_object_split_keeps_each_object_on_one_side(bank: SampleBank) -> None:
    train, val = split_rows(bank, "objects", 0.34, seed=0)
    train_objects = {bank.object_ids[i] for i in train}
    val_objects = {bank.object_ids[i] for i in val}
    assert train_objects and val_objects and not train_objects & val_objects
    assert len(train_objects | val_objects) == 3


def test_bad_splits_and_an_unreadable_dataset_are_named_errors(bank: SampleBank, tmp_path) -> None:
    with pytest.raises(DataError, match="strictly between"):
        split_rows(bank, "samples", 1.0)
    with pytest.raises(storage.StorageError):
        SampleBank.load(str(tmp_path / "nothing-here"))


def test_covers_are_what_storage_says_for_every_sample(bank: SampleBank, dataset_url: str) -> None:
    dataset = storage.open_dataset(dataset_url)
    covers = require_covers(bank, "this test")
    assert bank.schema_version >= 2 and len(covers) == len(dataset)
    ambiguous = 0
    for i in range(len(dataset)):
        found = dataset.ambiguity(i)
        np.testing.assert_array_equal(covers.covers_of(i), found.covers)
        np.testing.assert_array_equal(covers.universe_of(i), found.universe_rows)
        np.testing.assert_array_equal(covers.support[i].astype(bool), mask_to_bools(found.support, 32))
        np.testing.assert_allclose(covers.marginals[i], found.marginals(32), rtol=1e-6)
        assert (covers.counts[i], covers.exact[i]) == (found.count, found.exact)
        label = dataset.masks(i)[1]
        assert covers.nearest(i, label) == label and covers.covers_universe(i, label)
        ambiguous += found.count > 1
    assert ambiguous > len(dataset) // 2, "the test dataset should have ties to learn from"


def test_batches_carry_marginals_support_and_padded_covers(bank: SampleBank) -> None:
    covers = require_covers(bank, "this test")
    rows = [3, 40, 41]
    plain = bank.batch(rows, 64, seed=0, epoch=0)
    assert plain.covers is None and plain.cover_mask is None
    batch = bank.batch(rows, 64, seed=0, epoch=0, with_covers=True)
    assert batch.marginals is not None and batch.support is not None
    assert batch.covers is not None and batch.cover_mask is not None
    assert torch.equal(batch.points, plain.points)
    for slot, row in enumerate(rows):
        listed = covers.covers_of(row)
        assert int(batch.cover_mask[slot].sum()) == listed.size
        for k, mask in enumerate(listed.tolist()):
            assert batch.covers[slot, k].numpy().astype(bool).tolist() == mask_to_bools(mask, 32).tolist()
        assert not batch.covers[slot, listed.size :].any()
        assert torch.equal(batch.marginals[slot], torch.from_numpy(covers.marginals[row]))


def test_max_objects_draws_are_nested_and_validation_never_changes(bank: SampleBank, dataset_url: str) -> None:
    base = TrainOptions(data=dataset_url, out=Path("unused"), seed=3)
    full_train, val = run_rows(bank, base)
    drawn = {}
    for count in (1, 2, 3):
        rows, val_rows = run_rows(bank, TrainOptions(data=dataset_url, out=Path("unused"), seed=3, max_objects=count))
        assert np.array_equal(val_rows, val), "validation rows must not depend on the subset"
        drawn[count] = rows
    objects = {count: {bank.object_ids[i] for i in rows} for count, rows in drawn.items()}
    assert [len(objects[c]) for c in (1, 2, 3)] == [1, 2, 3]
    assert objects[1] < objects[2] < objects[3]
    assert np.isin(drawn[1], drawn[2]).all() and np.array_equal(drawn[3], full_train)
    # every training sample of a drawn object, no other
    train_of = {o: {int(i) for i in full_train if bank.object_ids[i] == o} for o in objects[3]}
    assert set(drawn[2].tolist()) == set().union(*(train_of[o] for o in objects[2]))
    with pytest.raises(DataError, match="training side holds 3 objects; give 1 to 3"):
        training_subset(bank, full_train, max_objects=4)


def test_sample_fractions_are_nested_and_seeded(bank: SampleBank) -> None:
    train, _ = split_rows(bank, "objects", 0.34, seed=0)
    quarter = training_subset(bank, train, sample_fraction=0.25, seed=1)
    half = training_subset(bank, train, sample_fraction=0.5, seed=1)
    assert quarter.size == int(np.floor(0.25 * train.size + 0.5)) and half.size == int(np.floor(0.5 * train.size + 0.5))
    assert np.isin(quarter, half).all() and np.isin(half, train).all()
    assert np.array_equal(training_subset(bank, train, sample_fraction=1.0, seed=1), train)
    assert not np.array_equal(training_subset(bank, train, sample_fraction=0.5, seed=2), half)
    both = training_subset(bank, train, max_objects=1, sample_fraction=0.5, seed=1)
    assert len({bank.object_ids[i] for i in both}) == 1
    assert training_subset(bank, train, sample_fraction=1e-9, seed=1).size == 1
    with pytest.raises(DataError, match=r"sample fraction 0.0 must lie in \(0, 1\]"):
        training_subset(bank, train, sample_fraction=0.0)


def test_a_version_1_dataset_has_no_covers_and_names_the_relabel(v1_dataset_url: str, bank: SampleBank) -> None:
    old = SampleBank.load(v1_dataset_url)
    assert old.schema_version == 1 and old.covers is None
    assert np.array_equal(old.labels, bank.labels) and np.array_equal(old.view_state, bank.view_state)
    batch = old.batch([0, 1], 64, seed=0, epoch=0, with_covers=True)
    assert batch.marginals is None and batch.support is None and batch.covers is None
    with pytest.raises(DataError) as info:
        require_covers(old, "target 'mincover'")
    message = str(info.value)
    assert "\n" not in message and "version-1 dataset" in message and "target 'mincover'" in message
    assert f"datagen shards relabel {v1_dataset_url} --out NEW_URL" in message


def test_the_config_hash_is_the_datasets_own_record(v1_dataset_url: str, tmp_path: Path) -> None:
    """Never recomputed: that would hash this machine's datagen files, not the dataset's."""
    copy = tmp_path / "copy"
    shutil.copytree(v1_dataset_url, copy)
    info = json.loads((copy / "dataset.json").read_text())
    info["config_hash"] = "f" * 64
    (copy / "dataset.json").write_text(json.dumps(info))
    assert SampleBank.load(str(copy)).config_hash == "f" * 64
