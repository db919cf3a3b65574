"""The sample contract (`storage.samples`: its batch, bits, resampling, splits and field registry)
against independent truth, and every read path built on it
(`storage.torch.OSVPDataset`, `storage.readers.memory`, osvp's `SampleBank`) giving identical tensors.

Truth here is hand-computed centres, Python's own integer bit operations, numpy's generators called
directly, and a brute-force split written out sample by sample; never the functions under test.
"""

from __future__ import annotations

import json
import random
from pathlib import Path

import numpy as np
import pytest
from support import storage as fx
from support.torch_data import Built, cached_dataset

from datagen.pipeline.keys import key_centres as pipeline_centres
from schemas.shard import LABEL_COLUMN, MASKS
from schemas.version import SCHEMA_VERSION
from storage import open_dataset
from storage.readers import load_memory
from storage.samples import (
    SAMPLE_FIELDS,
    SampleBatch,
    SampleField,
    ShardRows,
    SplitError,
    check_source,
    held_out_objects,
    key_centres,
    mask_bits,
    padded_covers,
    register_field,
    resample_cloud,
    resample_indices,
    resample_keys,
    split_by_object,
    split_by_sample,
)

torch = pytest.importorskip("torch")

# -- keys -> metres ----------------------------------------------------------------------------------


def test_key_centres_are_the_voxel_centres_computed_by_hand() -> None:
    keys = np.array([[0, 0, 0], [1, 2, 3], [-1, -5, 7]], dtype=np.int16)
    voxel, offset = 0.004, (0.25, 0.5, 0.75)
    # (key + 0.5 - offset) * voxel, worked out on paper
    expected = np.array([[0.001, 0.0, -0.001], [0.005, 0.008, 0.011], [-0.003, -0.02, 0.027]])
    centres = key_centres(keys, voxel, offset)
    assert centres.dtype == np.float32 and centres.shape == (3, 3)
    np.testing.assert_allclose(centres, expected, rtol=0, atol=1e-9)
    # any leading shape, and what the pipeline (the producer of the keys) means by a key's point
    many = np.random.default_rng(0).integers(-300, 300, size=(4, 50, 3)).astype(np.int16)
    config = fx.config()
    found = key_centres(many, config.voxel_size, config.grid_offset)
    assert found.shape == (4, 50, 3)
    truth = pipeline_centres(many.reshape(-1, 3), config.voxel_size, config.grid_offset).astype(np.float32)
    np.testing.assert_array_equal(found.reshape(-1, 3), truth)


# -- mask -> views -----------------------------------------------------------------------------------


def test_mask_bits_are_pythons_bit_operations() -> None:
    rng = random.Random(0)
    masks = [0, 1, 2**63, 2**64 - 1, *(rng.getrandbits(64) for _ in range(50))]
    masks += [rng.getrandbits(32) for _ in range(50)]
    for width in (1, 7, 32, 64):
        for mask in masks:
            row = mask_bits(mask, width)
            assert row.dtype == np.bool_ and row.shape == (width,)
            assert row.tolist() == [bool((mask >> v) & 1) for v in range(width)]
        rows = mask_bits(np.array(masks, dtype=np.uint64), width)
        assert rows.shape == (len(masks), width)
        assert rows.tolist() == [[bool((m >> v) & 1) for v in range(width)] for m in masks]


# -- resampling --------------------------------------------------------------------------------------


def test_resampling_is_numpys_stream_of_seed_epoch_index() -> None:
    for count, num, seed, epoch, index in ((10, 4, 0, 0, 0), (3, 5, 7, 2, 11), (1000, 6, 1, 3, 42)):
        rng = np.random.default_rng(np.random.SeedSequence([seed, epoch, index]))
        truth = rng.choice(count, size=num, replace=count < num, shuffle=False)
        assert resample_indices(count, num, seed, epoch, index).tolist() == truth.tolist()
    # the streams trained checkpoints and recipe results were drawn from, pinned
    assert resample_indices(10, 4, 0, 0, 0).tolist() == [5, 7, 4, 2]
    assert resample_indices(3, 5, 7, 2, 11).tolist() == [0, 1, 1, 2, 2]
    assert resample_indices(1000, 6, 1, 3, 42).tolist() == [922, 584, 989, 600, 116, 950]


def test_resampling_is_deterministic_and_independent_of_call_order() -> None:
    keys = np.random.default_rng(1).integers(-50, 50, size=(40, 3)).astype(np.int16)
    forward = {i: resample_keys(keys, 16, 3, 1, i) for i in range(20)}
    backward = {i: resample_keys(keys, 16, 3, 1, i) for i in reversed(range(20))}
    assert all(np.array_equal(forward[i], backward[i]) for i in range(20))
    assert len({forward[i].tobytes() for i in range(20)}) == 20  # each index its own stream
    assert not np.array_equal(resample_keys(keys, 16, 3, 2, 0), forward[0])  # another epoch
    assert not np.array_equal(resample_keys(keys, 16, 4, 1, 0), forward[0])  # another seed
    # without replacement while the cloud has enough points, with it only when it has fewer
    assert len({tuple(k) for k in resample_keys(keys, 40, 0, 0, 0).tolist()}) == 40
    few = resample_keys(keys[:5], 12, 0, 0, 0)
    assert few.shape == (12, 3) and {tuple(k) for k in few.tolist()} <= {tuple(k) for k in keys[:5].tolist()}
    empty = resample_keys(np.zeros((0, 3), dtype=np.int16), 8, 0, 0, 0)
    assert empty.dtype == np.int16 and empty.shape == (8, 3) and not empty.any()


# -- splits ------------------------------------------------------------------------------------------


def brute_object_split(object_ids: list[str], fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """The rule written out: sort the distinct objects, permute them with (seed, count), hold out
    round(fraction x count) of them (one at least for a positive fraction); then sample by sample."""
    objects = sorted(set(object_ids))
    order = np.random.default_rng(np.random.SeedSequence([seed, len(objects)])).permutation(len(objects))
    count = round(fraction * len(objects))
    if fraction > 0 and count == 0:
        count = 1
    held = [objects[int(order[k])] for k in range(count)]
    train, val = [], []
    for row, object_id in enumerate(object_ids):
        (val if object_id in held else train).append(row)
    return train, val


def test_the_object_split_keeps_objects_on_one_side_and_is_the_brute_force_rule() -> None:
    rng = random.Random(2)
    for objects in (1, 2, 3, 5, 12):
        names = [f"object-{k:02d}" for k in range(objects)]
        ids = [rng.choice(names) for _ in range(60)]
        for fraction in (0.0, 0.05, 0.2, 0.34, 0.5, 0.9, 1.0):
            for seed in range(4):
                train, val = split_by_object(ids, fraction, seed)
                assert (train.tolist(), val.tolist()) == brute_object_split(ids, fraction, seed)
                assert not {ids[i] for i in train} & {ids[i] for i in val}
                assert sorted([*train.tolist(), *val.tolist()]) == list(range(len(ids)))
                held = held_out_objects(sorted(set(ids)), fraction, seed)
                assert {ids[i] for i in val} == held
                if fraction > 0:
                    assert len(held) >= 1  # a small fraction of few objects still holds one out
    for bad in (-0.1, 1.5):
        with pytest.raises(SplitError, match=r"must lie in \[0, 1\]"):
            split_by_object(["a", "b"], bad, 0)


def test_the_sample_split_is_a_seeded_permutation() -> None:
    for total in (2, 10, 57):
        for fraction in (0.1, 0.2, 0.5):
            for seed in range(3):
                train, val = split_by_sample(total, fraction, seed)
                order = np.random.default_rng(np.random.SeedSequence([seed, total])).permutation(total)
                cut = max(1, round(fraction * total))
                assert val.tolist() == sorted(order[:cut].tolist()) and train.tolist() == sorted(order[cut:].tolist())
    with pytest.raises(SplitError, match="too few"):
        split_by_sample(1, 0.5, 0)
    with pytest.raises(SplitError, match="strictly between"):
        split_by_sample(10, 0.0, 0)


# -- the read paths ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Built:
    """3 objects x 2 rotations, points != observed (the storage/torch tests' dataset)."""
    return cached_dataset("small", tmp_path_factory.mktemp("contract_small"))


@pytest.fixture(scope="module")
def covered(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A version-2 dataset (minimum covers), 2 objects."""
    root = tmp_path_factory.mktemp("contract_v2") / "ds"
    fx.build_dataset(str(root), finalise_index=True)
    return root


def test_dataset_split_is_the_contracts_object_split(small: Built) -> None:
    dataset = open_dataset(small.url)
    ids = dataset.index.column("object_id").to_pylist()
    for fraction, seed in ((0.0, 0), (0.1, 0), (0.34, 4), (0.5, 1), (1.0, 2)):
        train, val = dataset.split(fraction, seed)
        expected = brute_object_split(ids, fraction, seed)
        assert [train.index.column("sample_id").to_pylist(), val.index.column("sample_id").to_pylist()] == [
            [dataset.index.column("sample_id")[i].as_py() for i in rows] for rows in expected
        ]
    assert len(dataset.split(0.1, 0)[1]) > 0  # 0.1 of 3 objects rounds to none: one is held out


def test_osvp_dataset_memory_and_sample_bank_give_identical_tensors(small: Built) -> None:
    data = pytest.importorskip("osvp.data")
    from storage.torch import OSVPDataset

    memory = load_memory(small.url)
    bank = data.SampleBank.load(small.url)
    for source in ("points", "observed"):
        reader = OSVPDataset(small.url, num_points=96, source=source, seed=5)
        held = load_memory(small.url, source)
        for epoch in (0, 3):
            reader.set_epoch(epoch)
            rows = list(range(len(reader)))
            whole = held.batch(rows, 96, 5, epoch)
            for i in rows:
                item = reader[i]
                for name, found in (("points", whole.points), ("view_state", whole.view_state), ("label", whole.label)):
                    assert torch.equal(item[name], torch.from_numpy(found[i])), (source, epoch, i, name)
            for start in range(0, len(rows), 5):  # other batch sizes, other orders: the same clouds
                chunk = rows[start : start + 5][::-1]
                piece = held.batch(chunk, 96, 5, epoch)
                assert all(np.array_equal(piece.points[slot], whole.points[i]) for slot, i in enumerate(chunk))
            if source == "points":
                batch = bank.batch(rows, 96, 5, epoch)
                assert torch.equal(batch.points, torch.from_numpy(memory.batch(rows, 96, 5, epoch).points))
                assert torch.equal(batch.points, torch.stack([reader[i]["points"] for i in rows]))
                assert torch.equal(batch.view_state, torch.stack([reader[i]["view_state"] for i in rows]))
                assert torch.equal(batch.label, torch.stack([reader[i]["label"] for i in rows]))
                # one batch type: the map-style loader's batch is the bank's, field for field
                (loaded,) = list(reader.loader(batch_size=len(rows)))
                assert isinstance(loaded, SampleBatch) and isinstance(batch, SampleBatch)
                for name in ("points", "view_state", "label", "index"):
                    assert torch.equal(getattr(loaded, name), getattr(batch, name)), name


def test_a_side_loaded_alone_is_that_side_of_a_whole_load(small: Built) -> None:
    dataset = open_dataset(small.url)
    train, val = split_by_object(dataset.index.column("object_id").to_pylist(), 0.34, 4)
    whole = load_memory(dataset)
    held_objects = sorted({whole.object_ids[i] for i in val.tolist()})
    by_objects = load_memory(small.url, objects=held_objects)
    by_rows = load_memory(small.url, rows=val[::-1])  # any order of rows
    assert by_objects.rows.tolist() == val.tolist() and by_rows.rows.tolist() == val[::-1].tolist()
    for part in (by_objects, by_rows):
        positions = np.arange(len(part))
        mine, theirs = part.batch(positions, 64, 2, 1), whole.batch(part.rows, 64, 2, 1)
        assert np.array_equal(mine.points, theirs.points) and np.array_equal(mine.label, theirs.label)
        for p, row in enumerate(part.rows.tolist()):
            assert np.array_equal(part.keys_of(p), dataset.keys(row))
            assert part.object_ids[p] == whole.object_ids[row]
    train_side = load_memory(small.url, rows=train, objects=held_objects)
    assert len(train_side) == 0 and train_side.keys.shape == (0, 3)
    with pytest.raises(IndexError, match="rows must lie in"):
        load_memory(dataset, rows=[len(dataset)])
    with pytest.raises(ValueError, match="repeat"):
        load_memory(dataset, rows=[0, 0])
    with pytest.raises(ValueError, match="source"):
        load_memory(dataset, "refined")  # type: ignore[arg-type]


def test_memory_holds_what_the_reader_serves_with_the_covers(covered: Path) -> None:
    dataset = open_dataset(str(covered))
    memory = load_memory(str(covered))
    assert (memory.schema_version, memory.num_views, len(memory)) == (SCHEMA_VERSION, dataset.num_views, len(dataset))
    assert memory.voxel_size == dataset.info.config.voxel_size
    assert memory.grid_offset.tolist() == list(dataset.info.config.grid_offset)
    packed = memory.covers
    assert packed is not None
    for i in range(len(dataset)):
        sample, found = dataset[i], dataset.ambiguity(i)
        assert np.array_equal(memory.keys_of(i), dataset.keys(i))
        assert (int(memory.view_state_masks[i]), int(memory.label_masks[i])) == dataset.masks(i)
        assert np.array_equal(memory.view_state[i], sample["view_state"].astype(np.float32))
        assert np.array_equal(memory.labels[i], sample["label"].astype(np.float32))
        assert np.array_equal(packed.covers_of(i), found.covers)
        assert np.array_equal(packed.universe_of(i), found.universe_rows)
        assert (int(packed.support[i]), int(packed.counts[i]), bool(packed.exact[i])) == (
            found.support,
            found.count,
            found.exact,
        )
    assert load_memory(str(covered), covers=False).covers is None
    part = load_memory(str(covered), rows=[len(dataset) - 1, 0])
    assert part.covers is not None
    for p, row in enumerate((len(dataset) - 1, 0)):
        assert np.array_equal(part.covers.covers_of(p), dataset.ambiguity(row).covers)
        assert np.array_equal(part.covers.universe_of(p), dataset.ambiguity(row).universe_rows)


def test_the_config_hash_is_the_datasets_own_record(covered: Path, tmp_path: Path) -> None:
    """Never recomputed: that would hash this machine's datagen files, not the dataset's."""
    copy = fx.copy_dataset(covered, tmp_path / "copy")
    info = json.loads((copy / "dataset.json").read_text())
    info["config_hash"] = "e" * 64
    (copy / "dataset.json").write_text(json.dumps(info))
    assert load_memory(str(copy)).config_hash == "e" * 64


def test_osvp_covers_from_memory_are_those_built_sample_by_sample() -> None:
    """Samples without listed covers at the start, middle and end (marginals zero there)."""
    covers_module = pytest.importorskip("osvp.covers")
    from storage import LabelAmbiguity
    from storage.readers import PackedCovers

    listed = [[], [0b0110, 0b1010], [], [0b0001], [0b1111, 0b0011, 0b0101], []]
    universe = [[0b1], [0b1000, 0b0100], [], [0b0010], [0b1100], [0b1]]
    found = [
        LabelAmbiguity(
            np.array(c, dtype=np.uint64),
            max(len(c), 1),
            True,
            int(np.bitwise_or.reduce(c or [0])),
            np.array(u, dtype=np.uint64),
        )
        for c, u in zip(listed, universe, strict=True)
    ]
    states = [0, 1, 0, 4, 0, 8]
    packed = PackedCovers(
        covers=np.array([m for c in listed for m in c], dtype=np.uint64),
        cover_offsets=np.cumsum([0, *(len(c) for c in listed)]).astype(np.int64),
        universe=np.array([m for u in universe for m in u], dtype=np.uint64),
        universe_offsets=np.cumsum([0, *(len(u) for u in universe)]).astype(np.int64),
        support=np.array([a.support for a in found], dtype=np.uint64),
        counts=np.array([a.count for a in found], dtype=np.int64),
        exact=np.ones(len(found), dtype=bool),
    )
    built = covers_module.CoverBank.build(found, states, 4)
    packed_bank = covers_module.CoverBank.from_packed(packed, states, 4)
    for name in ("covers", "cover_offsets", "universe", "universe_offsets", "view_states", "support", "marginals"):
        mine, theirs = getattr(packed_bank, name), getattr(built, name)
        assert mine.dtype == theirs.dtype and np.array_equal(mine, theirs), name
    assert np.array_equal(packed_bank.counts, built.counts) and np.array_equal(packed_bank.exact, built.exact)


# -- one batch type ------------------------------------------------------------------------------------
def test_a_sample_batch_as_tensors_shares_the_arrays_and_keeps_absent_fields_absent() -> None:
    arrays = SampleBatch(
        points=np.zeros((2, 4, 3), dtype=np.float32),
        view_state=np.eye(2, 3, dtype=np.float32),
        label=np.ones((2, 3), dtype=np.float32),
        index=np.array([7, 3], dtype=np.int64),
        support=np.zeros((2, 3), dtype=np.float32),
    )
    tensors = arrays.tensors()
    assert len(tensors) == 2 and set(tensors.as_dict()) == {"points", "view_state", "label", "index", "support"}
    assert tensors.covers is None and tensors.marginals is None and tensors.cover_mask is None
    arrays.points[1, 2, 0] = 5.0  # the same memory, no copy
    assert float(tensors.points[1, 2, 0]) == 5.0 and tensors.index.tolist() == [7, 3]
    assert tensors.to("cpu").as_dict().keys() == tensors.as_dict().keys()


def test_padded_covers_hold_each_listing_then_empty_rows() -> None:
    listed = [np.array([0b011, 0b110], dtype=np.uint64), np.zeros(0, dtype=np.uint64), np.array([0b100], np.uint64)]
    covers, valid = padded_covers(listed, 3)
    assert covers.shape == (3, 2, 3) and covers.dtype == np.float32 and valid.dtype == np.bool_
    assert valid.tolist() == [[True, True], [False, False], [True, False]]
    assert covers[0].tolist() == [[1, 1, 0], [0, 1, 1]] and covers[2, 0].tolist() == [0, 0, 1]
    assert not covers[1].any() and not covers[2, 1].any()
    empty, none = padded_covers([np.zeros(0, dtype=np.uint64)], 4)
    assert empty.shape == (1, 0, 4) and none.shape == (1, 0)


def test_resample_cloud_draws_from_its_stream() -> None:
    cloud = np.arange(30, dtype=np.float32).reshape(10, 3)
    for wanted in (4, 10, 25):
        rng = np.random.default_rng(np.random.SeedSequence([0, 10]))  # the draw, written out
        expected = cloud[rng.choice(10, size=wanted, replace=wanted > 10, shuffle=False)]
        assert np.array_equal(resample_cloud(cloud, wanted, (0, 10)), expected)
    assert np.array_equal(resample_cloud(np.zeros((0, 3), np.float32), 5, (0, 0)), np.zeros((5, 3), np.float32))


def test_every_reader_refuses_another_source_with_one_line() -> None:
    assert check_source("observed") == "observed"
    with pytest.raises(ValueError, match="use 'points' \\(refined\\) or 'observed'"):
        check_source("refined")


# -- per-sample fields: one registration, every batch reader ---------------------------------------------
def test_cloud_size_is_each_samples_stored_cloud_in_every_batch_reader(covered: Path) -> None:
    from storage.stream import ShardStream

    dataset = open_dataset(str(covered))
    for source in ("points", "observed"):
        truth = [dataset.keys(row, source).shape[0] for row in range(len(dataset))]
        rows = list(range(len(dataset)))[::-1]
        held = load_memory(dataset, source).batch(rows, 16, 0, 0)
        assert held.cloud_size is not None and held.cloud_size.tolist() == [truth[row] for row in rows]
        streamed = ShardStream(dataset, num_points=16, batch_size=4, source=source, seed=0)
        for batch in streamed.loader():
            assert batch.cloud_size.tolist() == [truth[row] for row in batch.index.tolist()]
    data = pytest.importorskip("osvp.data")
    sizes = data.SampleBank.load(str(covered)).batch([1, 0], 16, 0, 0).cloud_size
    assert sizes.tolist() == [dataset.keys(1).shape[0], dataset.keys(0).shape[0]]


def test_a_fields_reader_is_the_only_place_that_names_it(covered: Path) -> None:
    """Swapping the registered reader of a field changes what both batch readers give, unchanged."""
    from storage.stream import ShardStream

    def label_bits(rows: ShardRows) -> np.ndarray:  # a stand-in reader: each sample's label mask
        return np.asarray(rows.array(MASKS), dtype=np.int64)[rows.local, LABEL_COLUMN]

    with SAMPLE_FIELDS.replaced("cloud_size", SampleField("cloud_size", 1, label_bits)):
        dataset = open_dataset(str(covered))
        labels = dataset.index.column("label").to_numpy().astype(np.int64)
        held = load_memory(dataset).batch(range(len(dataset)), 8, 0, 0)
        assert held.cloud_size is not None and held.cloud_size.tolist() == labels.tolist()
        for batch in ShardStream(dataset, num_points=8, batch_size=3, seed=1).loader():
            assert batch.cloud_size.tolist() == labels[batch.index.numpy()].tolist()


def test_register_field_refuses_a_name_that_cannot_be_one_and_a_second_reader() -> None:
    for name in ("extra", "two words", ""):
        with pytest.raises(ValueError, match="cannot name a sample field"):
            register_field(name)
    with pytest.raises(ValueError, match="registered twice"):
        register_field("cloud_size")(lambda rows: rows.local)


def test_the_held_marginals_field_is_the_cover_banks_own_count(covered: Path) -> None:
    """osvp's CoverBank takes the marginals the load holds (the registered field, `listed_marginals`);
    they are the ones it computes from the packed covers itself, bit for bit."""
    covers_module = pytest.importorskip("osvp.covers")
    memory = load_memory(str(covered))
    assert memory.covers is not None
    held = memory.fields["marginals"]
    computed = covers_module.CoverBank.from_packed(memory.covers, memory.view_state_masks, memory.num_views)
    assert held.dtype == computed.marginals.dtype == np.float32
    assert np.array_equal(held, computed.marginals)
    given = covers_module.CoverBank.from_packed(memory.covers, memory.view_state_masks, memory.num_views, held)
    assert given.marginals is held or np.array_equal(given.marginals, held)


def test_padded_fields_are_batch_only(covered: Path) -> None:
    """The listed covers are padded per batch: the per-item reader refuses them by the field's own
    flag, and the in-memory reader gives them when a batch asks (or the load did)."""
    from storage.torch import OSVPDataset

    with pytest.raises(ValueError, match="vary in length per sample"):
        OSVPDataset(str(covered), fields=("covers",))
    memory = load_memory(str(covered))
    assert "covers" not in memory.batch([0, 1], 8, 0, 0).as_dict()
    assert {"covers", "cover_mask"} <= set(memory.batch([0, 1], 8, 0, 0, covers=True).as_dict())
    asked = load_memory(str(covered), fields=("covers", "cover_mask"))
    assert {"covers", "cover_mask"} <= set(asked.batch([0, 1], 8, 0, 0).as_dict())
