"""A sample field added from this module alone (no other file touched) reaches every reader.

The toy field holds each sample's label mask and finishes a batch as the number of views its label
holds: one `register_field` here, and the in-memory reader, the shard stream (in the main process
and in DataLoader workers), the map-style `OSVPDataset` and its loader, ``Dataset[i]`` and the
export layouts' `Dataset.sample`, and osvp's `SampleBank` all give it, equal to the label counted
with Python's own integer bits from the index.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest
from support import storage as fx

from schemas.shard import LABEL_COLUMN, MASKS
from storage import open_dataset
from storage.readers import load_memory
from storage.samples import (
    SAMPLE_FIELDS,
    BatchFacts,
    Held,
    Positions,
    SampleBatch,
    ShardRows,
    Stacked,
    fields_for,
    register_field,
)

torch = pytest.importorskip("torch")

TOY = "toy_label_views"


def _label_views(held: Held, positions: Positions, facts: BatchFacts) -> npt.NDArray[np.float32]:
    assert isinstance(held, Stacked)
    masks = held.values[positions]
    return np.array([bin(int(mask)).count("1") for mask in masks.tolist()], dtype=np.float32)


def _label_masks(rows: ShardRows) -> npt.NDArray[np.uint64]:
    return np.asarray(rows.array(MASKS), dtype=np.uint64)[rows.local, LABEL_COLUMN]


@pytest.fixture
def toy() -> Iterator[str]:
    register_field(TOY, finish=_label_views)(_label_masks)
    try:
        yield TOY
    finally:
        SAMPLE_FIELDS.pop(TOY)


@pytest.fixture(scope="module")
def covered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("toy_field") / "ds"
    fx.build_dataset(str(root), finalise_index=True)
    return root


def _truth(root: Path) -> list[float]:
    labels = open_dataset(str(root)).index.column("label").to_pylist()
    return [float(bin(int(label)).count("1")) for label in labels]


def _check(batch: SampleBatch[object], truth: list[float]) -> int:
    found = np.asarray(batch.field(TOY))
    index = np.asarray(batch.index).tolist()
    assert found.dtype == np.float32 and found.shape == (len(index),)
    assert found.tolist() == [truth[row] for row in index]
    assert TOY in batch.extra and TOY in batch.as_dict()
    return len(index)


def test_a_field_registered_here_reaches_every_reader(covered: Path, toy: str) -> None:
    from storage.stream import ShardStream
    from storage.torch import OSVPDataset

    truth = _truth(covered)
    total = len(truth)
    assert total > 4 and len(set(truth)) > 1  # labels of different sizes: the field says something
    assert toy in {field.name for field in fields_for(open_dataset(str(covered)).info.schema_version)}

    memory = load_memory(str(covered))
    rows = list(range(total))[::-1]
    assert _check(memory.batch(rows, 8, 0, 0), truth) == total
    held = memory.held[toy]  # what memory keeps: the masks the field's hold read, per sample
    assert isinstance(held, Stacked) and held.values.tolist() == memory.label_masks.tolist()

    seen = 0
    for batch in ShardStream(str(covered), num_points=8, batch_size=3, seed=2).loader():
        seen += _check(batch, truth)
    assert seen == total
    workers = ShardStream(str(covered), num_points=8, batch_size=3, seed=2, num_workers=2)
    assert sum(_check(batch, truth) for batch in workers.loader()) == total

    dataset = open_dataset(str(covered))  # Dataset[i] and the export's `Dataset.sample`: one sample's batch row
    for i in range(total):
        assert dataset[i][toy].dtype == np.float32 and float(dataset[i][toy]) == truth[i]
        assert set(dataset.sample(i, [toy, "label"])) == {"sample_id", "label", toy}
        assert float(dataset.sample(i, [toy])[toy]) == truth[i]

    mapped = OSVPDataset(str(covered), num_points=8)
    for i in range(total):
        assert float(mapped[i][toy]) == truth[i]
    assert sum(_check(batch, truth) for batch in mapped.loader(batch_size=4)) == total

    data = pytest.importorskip("osvp.data")
    bank = data.SampleBank.load(str(covered))
    assert _check(bank.batch([2, 0, 1], 8, 0, 0), truth) == 3


def test_the_toy_field_is_gone_with_its_registration(covered: Path) -> None:
    batch = load_memory(str(covered)).batch([0], 8, 0, 0)
    assert TOY not in batch.as_dict()
    with pytest.raises(KeyError, match=TOY):
        batch.field(TOY)
