"""storage.stream: `ShardStream` yields every selected sample once per epoch, across DataLoader workers
and ranks, with the tensors of the map-style reader (`storage.torch.OSVPDataset`, ``Dataset[i]``); its
order is fixed by (seed, epoch, workers, world size); a restart after K batches yields the uninterrupted
tail; a damaged shard is the map-style reader's `StorageError`; and it reads from S3.

The dataset: the storage tests' two built-ins committed 4 times over (8 shards, the newest version:
`support.storage.build_many_tasks`).
"""

from __future__ import annotations

import os
import uuid
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import pytest
import torch
from support import storage as fx
from support.s3_servers import BUCKET, REGION, S3Server

from schemas.shard import array_names
from storage import ShardReader, StorageError, open_dataset
from storage.dataset import shard_path
from storage.samples import SampleBatch, split_by_object
from storage.shards import whole_array
from storage.shards.codec import _decode_whole  # the codec's own decoder (an internal)
from storage.stream import ShardStream
from storage.torch import OSVPDataset

NUM_POINTS = 128
BATCH = 16
COPIES = 4
"""8 shards of 49 or 45 samples."""


@pytest.fixture(scope="module")
def many(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("stream") / "many"
    fx.build_many_tasks(str(root), COPIES)
    return root


def stream(url: str | Path, **options: object) -> ShardStream:
    base: dict[str, object] = {"num_points": NUM_POINTS, "batch_size": BATCH, "seed": 7, "shuffle_buffer": 64}
    return ShardStream(str(url), **{**base, **options})  # type: ignore[arg-type]


def batches(source: ShardStream, workers: int = 0) -> list[SampleBatch[torch.Tensor]]:
    return list(source.loader(num_workers=workers, multiprocessing_context="fork" if workers else None))


def by_index(found: Iterable[SampleBatch[torch.Tensor]]) -> dict[int, dict[str, torch.Tensor]]:
    """Samples by dataset row; a row met twice fails."""
    out: dict[int, dict[str, torch.Tensor]] = {}
    for batch in found:
        for slot, row in enumerate(batch.index.tolist()):
            assert row not in out, f"row {row} yielded twice"
            out[row] = {name: value[slot] for name, value in batch.as_dict().items()}
    return out


def order(found: Iterable[SampleBatch[torch.Tensor]]) -> list[int]:
    return [row for batch in found for row in batch.index.tolist()]


# ---------------------------------------------------------------------------------------------------------
# tensors: those of the map-style reader
# ---------------------------------------------------------------------------------------------------------


def test_one_epoch_is_every_sample_once_with_the_map_style_tensors(many: Path) -> None:
    source = stream(many, epoch=3, covers=True)
    found = batches(source)
    samples = by_index(found)
    dataset = open_dataset(str(many))
    assert sorted(samples) == list(range(len(dataset))) == list(range(source.num_samples))
    assert all(b.points.shape[0] == BATCH for b in found[:-1]) and 0 < found[-1].points.shape[0] <= BATCH
    first = found[0]
    n = dataset.num_views
    assert first.points.shape == (BATCH, NUM_POINTS, 3) and first.points.dtype == torch.float32
    for name in ("view_state", "label", "marginals", "support"):
        assert getattr(first, name).shape == (BATCH, n) and getattr(first, name).dtype == torch.float32, name
    assert first.index.dtype == torch.int64 and first.cover_mask.dtype == torch.bool
    assert first.covers.shape[:2] == first.cover_mask.shape and first.covers.shape[2] == n
    mapped = OSVPDataset(str(many), num_points=NUM_POINTS, seed=7)
    mapped.set_epoch(3)
    for row, sample in samples.items():
        expected = mapped[row]
        for name in ("points", "view_state", "label", "index"):
            assert torch.equal(sample[name], expected[name]), (row, name)
        stored = dataset[row]
        assert torch.equal(sample["marginals"], torch.from_numpy(stored["marginals"]))
        assert torch.equal(sample["support"], torch.from_numpy(stored["support"].astype(np.float32)))
        listed = int(sample["cover_mask"].sum())
        assert bool(sample["cover_mask"][:listed].all()) and not bool(sample["cover_mask"][listed:].any())
        assert torch.equal(sample["covers"][:listed], torch.from_numpy(stored["covers"].astype(np.float32)))
        assert not bool(sample["covers"][listed:].any())


def test_observed_clouds_and_a_version_1_dataset(tmp_path: Path) -> None:
    fx.build_dataset(str(tmp_path / "v1"), schema_version=1, finalise_index=True)
    source = stream(tmp_path / "v1", source="observed")
    samples = by_index(batches(source))
    mapped = OSVPDataset(str(tmp_path / "v1"), num_points=NUM_POINTS, source="observed", seed=7)
    assert sorted(samples) == list(range(len(mapped)))
    stored = open_dataset(str(tmp_path / "v1"))
    for row, sample in samples.items():
        assert set(sample) == {"points", "view_state", "label", "index", "cloud_size"}
        assert torch.equal(sample["points"], mapped[row]["points"])
        assert int(sample["cloud_size"]) == stored.keys(row, "observed").shape[0]
    with pytest.raises(ValueError, match="version 2"):
        stream(tmp_path / "v1", covers=True)


# ---------------------------------------------------------------------------------------------------------
# exactly once across workers and ranks, and the order
# ---------------------------------------------------------------------------------------------------------


def test_every_sample_once_across_two_workers(many: Path) -> None:
    single = by_index(batches(stream(many, epoch=1)))
    source = stream(many, epoch=1, num_workers=2)
    found = batches(source, workers=2)
    assert len(found) == len(source)
    two = by_index(found)
    assert two.keys() == single.keys() == set(range(source.num_samples))
    for row in single:  # tensors never depend on the worker count
        assert torch.equal(two[row]["points"], single[row]["points"])


def test_a_batch_is_one_storage_and_workers_change_no_tensor(many: Path) -> None:
    """Every tensor of a batch is a contiguous view of one storage (one shared-memory segment from a
    worker), and each sample's every tensor is the same from 2 workers as from the main process."""
    single = by_index(batches(stream(many, epoch=1, covers=True)))
    found = batches(stream(many, epoch=1, covers=True, num_workers=2), workers=2)
    for batch in found:
        tensors = batch.as_dict()
        assert all(t.is_contiguous() for t in tensors.values())
        assert len({t.untyped_storage().data_ptr() for t in tensors.values()}) == 1
    two = by_index(found)
    assert two.keys() == single.keys()
    for row, sample in single.items():
        assert sample.keys() == two[row].keys()
        for name, value in sample.items():
            assert value.dtype == two[row][name].dtype, (row, name)
            if name not in ("covers", "cover_mask"):  # padded to each batch's longest listing
                assert torch.equal(value, two[row][name]), (row, name)


def test_every_sample_once_across_two_ranks_of_two_workers(many: Path) -> None:
    ranks = [stream(many, epoch=2, rank=rank, world_size=2, num_workers=2) for rank in (0, 1)]
    found = [batches(source, workers=2) for source in ranks]
    rows = [set(by_index(part)) for part in found]
    assert not rows[0] & rows[1]
    assert rows[0] | rows[1] == set(range(ranks[0].num_samples))
    assert [len(part) for part in found] == [len(source) for source in ranks]
    # drop_last: every rank (and worker) yields as many full batches as every other, none twice.
    even = [stream(many, epoch=2, rank=rank, world_size=2, num_workers=2, drop_last=True) for rank in (0, 1)]
    found = [batches(source, workers=2) for source in even]
    assert len(found[0]) == len(found[1]) > 0 and all(b.index.numel() == BATCH for p in found for b in p)
    kept = [set(by_index(part)) for part in found]
    assert not kept[0] & kept[1] and len(kept[0] | kept[1]) > 0.7 * even[0].num_samples


def test_the_order_follows_seed_and_epoch(many: Path) -> None:
    first = order(batches(stream(many, epoch=4, num_workers=2), workers=2))
    assert first == order(batches(stream(many, epoch=4, num_workers=2), workers=2))
    assert first != order(batches(stream(many, epoch=5, num_workers=2), workers=2))
    assert first != order(batches(stream(many, epoch=4, seed=8, num_workers=2), workers=2))
    source = stream(many, num_workers=2)
    source.set_epoch(4)
    assert order(batches(source, workers=2)) == first
    # The shuffle mixes shards: the first batch holds samples of more than one shard.
    shards = open_dataset(str(many)).index.column("shard").to_pylist()
    assert len({shards[row] for row in first[:BATCH]}) > 1


@pytest.mark.filterwarnings("ignore:This DataLoader will create 3 worker processes")
@pytest.mark.parametrize(("workers", "rank"), [(0, 0), (2, 0), (2, 1), (3, 0)])
def test_a_restart_after_k_batches_yields_the_uninterrupted_tail(many: Path, workers: int, rank: int) -> None:
    # 30 rows left out: the parts differ in size, so some worker runs out before another.
    rows = np.arange(30, open_dataset(str(many)).index.num_rows)
    options = {"epoch": 6, "num_workers": workers, "rank": rank, "world_size": 2 if rank else 1, "rows": rows}
    source = stream(many, **options)
    whole = batches(source, workers)
    counts = source.batch_counts(max(workers, 1))
    assert workers < 2 or len(set(counts)) > 1, counts
    for consumed in sorted({1, 2, len(whole) // 2, len(whole) - 1, len(whole)}):
        restarted = stream(many, **options)
        restarted.load_state_dict(source.state_dict(consumed=consumed))
        tail = batches(restarted, workers)
        assert len(tail) == len(whole) - consumed
        for a, b in zip(tail, whole[consumed:], strict=True):
            assert a.as_dict().keys() == b.as_dict().keys()
            for name, value in a.as_dict().items():
                assert torch.equal(value, getattr(b, name)), (consumed, name)
        skipped = stream(many, **options, skip=consumed)  # the same as a constructor argument
        assert order(batches(skipped, workers)) == order(whole[consumed:])
    with pytest.raises(ValueError, match="other seed"):
        stream(many, **{**options, "seed": 1}).load_state_dict(source.state_dict(consumed=1))


def test_a_selection_by_object_reads_only_its_shards(many: Path) -> None:
    dataset = open_dataset(str(many))
    ids = dataset.index.column("object_id").to_pylist()
    train, val = split_by_object(ids, 0.5, seed=0)
    source = stream(many, rows=train)
    assert sorted(by_index(batches(source))) == train.tolist()
    shards = dataset.index.column("shard").to_pylist()
    assert set(source.shards) == {shards[row] for row in train.tolist()} and len(source.shards) == COPIES
    held = sorted({ids[row] for row in val.tolist()})
    assert sorted(by_index(batches(stream(many, objects=held)))) == val.tolist()
    picked = np.random.default_rng(0).choice(len(dataset), 50, replace=False)
    assert sorted(by_index(batches(stream(many, rows=picked)))) == sorted(picked.tolist())
    with pytest.raises(ValueError, match="more than once"):
        stream(many, rows=[1, 1])


def test_whole_arrays_are_zarrs_arrays(many: Path) -> None:
    """`whole_array` decodes the writer's layouts itself (one chunk; one shard file of inner chunks)
    and gives exactly what zarr reads; an array it does not decode is read through zarr."""
    dataset = open_dataset(str(many))
    layouts = set()
    for relative in sorted(set(dataset.index.column("shard").to_pylist()))[:2]:
        reader = ShardReader(dataset.location, relative)
        for name in array_names(dataset.info.schema_version):
            decoded = _decode_whole(reader.files, name)
            assert decoded is not None, name
            with fx.shard_group(many / relative) as group:  # zarr's own read of the one-file group
                stored = np.asarray(group[name][...])
            assert decoded.dtype == stored.dtype and np.array_equal(decoded, stored), name
            meta = reader.files.read(f"{name}/zarr.json").decode()
            layouts.add("sharding_indexed" in meta)
    assert layouts == {True, False}, "both layouts were decoded"
    reader = ShardReader(dataset.location, dataset.index.column("shard")[0].as_py())
    kept = (many / reader.relative).read_bytes()
    fx.corrupt_member(many / reader.relative, "masks/zarr.json")
    try:  # metadata it cannot read: zarr's read, and zarr's error
        with pytest.raises(StorageError, match="masks"):
            whole_array(ShardReader(dataset.location, reader.relative, verify=False), "masks")
    finally:
        (many / reader.relative).write_bytes(kept)


# ---------------------------------------------------------------------------------------------------------
# damage, as the map-style reader reports it
# ---------------------------------------------------------------------------------------------------------

SHARD = shard_path(sorted(fx.task_ids())[0], fx.ATTEMPT)


def damage(root: Path, array: str, how: str) -> None:
    """The array's one chunk (or shard) member deleted from the shard's ZIP, or cut to half its bytes."""
    if how == "deleted":
        fx.zip_without(root / SHARD, f"{array}/c/0/0")
    else:
        member = next(name for name in zipfile.ZipFile(root / SHARD).namelist() if name.startswith(f"{array}/c/"))
        fx.truncate_member(root / SHARD, member)


@pytest.mark.parametrize(("array", "how"), [("points_keys", "deleted"), ("masks", "truncated")])
def test_a_damaged_shard_is_the_readers_storage_error(tmp_path: Path, array: str, how: str) -> None:
    root = tmp_path / "ds"
    fx.build_dataset(str(root), finalise_index=True)
    damage(root, array, how)
    dataset = open_dataset(str(root))
    row = dataset.index.column("shard").to_pylist().index(SHARD)
    with pytest.raises(StorageError) as mapped:
        OSVPDataset(str(root), num_points=NUM_POINTS)[row]
    with pytest.raises(StorageError) as streamed:
        batches(stream(root))
    assert str(streamed.value) == str(mapped.value) and type(streamed.value) is type(mapped.value)
    assert "\n" not in str(streamed.value) and SHARD in str(streamed.value)
    with pytest.raises(StorageError) as in_worker:  # re-raised in the parent from a worker process
        batches(stream(root, num_workers=2), workers=2)
    assert str(mapped.value) in str(in_worker.value)


# ---------------------------------------------------------------------------------------------------------
# S3
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def s3_copy(moto_s3: S3Server, many: Path) -> Iterator[tuple[str, dict[str, object]]]:
    """The dataset uploaded to moto's server; the URL and the storage options that reach it (the
    AWS variables are unset, so only the options can)."""
    import s3fs

    prefix = f"stream-{uuid.uuid4().hex[:8]}"
    client = moto_s3.client()
    for path in sorted(many.rglob("*")):
        if path.is_file():
            client.upload_file(str(path), BUCKET, f"{prefix}/{path.relative_to(many).as_posix()}")
    options = {
        "key": moto_s3.key_id,
        "secret": moto_s3.secret,
        "endpoint_url": moto_s3.endpoint,
        "client_kwargs": {"region_name": REGION},
    }
    with pytest.MonkeyPatch.context() as patch:
        for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_ENDPOINT_URL", "AWS_ENDPOINT_URL_S3"):
            patch.delenv(name, raising=False)
        yield f"s3://{BUCKET}/{prefix}", options
    s3fs.S3FileSystem.clear_instance_cache()


@pytest.mark.s3
def test_streaming_from_s3_equals_the_local_stream(s3_copy: tuple[str, dict[str, object]], many: Path) -> None:
    url, options = s3_copy
    remote = stream(url, epoch=2, num_workers=2, read_ahead=4, storage_options=options)
    found = batches(remote, workers=2)
    local = batches(stream(many, epoch=2, num_workers=2), workers=2)
    assert order(found) == order(local) and sorted(order(found)) == list(range(remote.num_samples))
    for a, b in zip(found, local, strict=True):
        assert a.as_dict().keys() == b.as_dict().keys()
        for name, value in a.as_dict().items():
            assert torch.equal(value, getattr(b, name)), name
