"""The in-memory sample bank against storage's own reader, and the two splits."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from osvp.data import DataError, SampleBank, split_rows

import storage


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
