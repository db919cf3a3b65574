"""Pack a finished dataset for shipping: its tasks in a few large tar files, with one manifest.

A dataset as written keeps three files a task (its shard, index fragment and commit record): 300,000
files at 100,000 tasks, which object stores, the Hugging Face Hub and copy tools handle badly. `pack`
writes the same tasks into tar files of about ``target_bytes`` each (512 MB by default; WebDataset
shards are ~1 GB, MosaicML's 64 MB), in task id order, each task two members named by its task id:

- ``<task>.zarr.zip``: its shard, byte for byte (a Zarr v3 group in an uncompressed ZIP);
- ``<task>.index.parquet``: its index rows.

That is a WebDataset shard (one WebDataset sample a task, keyed by task id), so `webdataset` and any
tar reader read the packs as they are. The packed dataset's manifest (`storage.dataset.manifest`, ``packed``)
is the only index: its tasks table names each task's pack and the byte range of its ZIP there, so
`storage.open_dataset` and the streaming reader read a task with one ranged read, as from an unpacked
dataset. A packed dataset has no commit records and is read-only; `storage.validate` checks it like any
other. At about 60 samples and 0.3-5 MB a task, a 512 MB pack holds 6,000 to 100,000 samples.
"""

from __future__ import annotations

import io
import os
import tarfile
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, BinaryIO

import pyarrow as pa

from schemas.dataset import CARD_FILE, DATASET_FILE, PACK_BYTES
from schemas.index import CommitRecord
from schemas.shard import single_file
from storage.dataset.info import read_info
from storage.dataset.manifest import MANIFEST_FILE, Manifest, read_manifest, read_tasks, record_of, write_segment
from storage.dataset.writer import FAILURES, holds_dataset
from storage.store.errors import check_store
from storage.store.location import Location, StorageError, open_location
from storage.store.parquet import parquet_bytes, read_index_table

PACKS = "packs"
DEFAULT_PACK_BYTES = PACK_BYTES
SHARD_MEMBER = ".zarr.zip"
INDEX_MEMBER = ".index.parquet"
READ_AHEAD = 16
"""Tasks read side by side ahead of the one being written (an object store's latency overlaps)."""


@dataclass(frozen=True)
class PackProgress:
    tasks_done: int
    tasks_total: int
    packs: int
    bytes_written: int


@dataclass(frozen=True)
class PackSummary:
    source: str
    out: str
    tasks: int
    samples: int
    packs: int
    bytes_written: int
    seconds: float


def pack_dataset(
    url: str,
    out_url: str,
    target_bytes: int = DEFAULT_PACK_BYTES,
    storage_options: dict[str, Any] | None = None,
    progress: Callable[[PackProgress], None] | None = None,
) -> PackSummary:
    """Write the finalised dataset at ``url`` packed at ``out_url`` (a new location); see the module."""
    started = time.perf_counter()
    source = open_location(url, storage_options)
    check_store(source)
    info = read_info(source)
    if not single_file(info.schema_version):
        raise StorageError(
            f"{url}: a version-{info.schema_version} dataset keeps a folder of files per task; packing needs "
            f"one file per task (version 5): `datagen shards relabel {url} --out NEW_URL` writes it"
        )
    manifest = read_manifest(source)
    if manifest is None:
        raise StorageError(f"{url}: the dataset has no finalised index; finish its job (`datagen resume JOB`) first")
    if manifest.packed:
        raise StorageError(f"{url}: already packed")
    if target_bytes < 1:
        raise StorageError(f"--pack-bytes {target_bytes}: give a positive number of bytes")
    target = open_location(out_url, storage_options)
    check_store(target)
    if holds_dataset(target) or target.exists(MANIFEST_FILE):
        raise StorageError(f"{out_url}: already holds a dataset; pack writes a new one, give an empty --out")
    records = [record_of(row) for row in read_tasks(source, manifest).to_pylist()]
    writer = _PackWriter(target, target_bytes)
    spans: dict[str, dict[str, Any]] = {"pack": {}, "pack_offset": {}, "pack_size": {}}

    def written() -> Iterator[tuple[CommitRecord, pa.Table]]:
        """Each task written into its pack, then its record and index rows as the packed dataset has them."""
        for done, (record, shard, rows) in enumerate(_read_ahead(source, records), start=1):
            pack = writer.next_pack(len(shard))
            member = f"{pack}/{record.task_id}{SHARD_MEMBER}"
            index_rows = _renamed(rows, member)
            _, offset, size = writer.add(record.task_id, shard, parquet_bytes(index_rows))
            for column, value in (("pack", pack), ("pack_offset", offset), ("pack_size", size)):
                spans[column][record.task_id] = value
            fragment = f"{pack}/{record.task_id}{INDEX_MEMBER}"
            yield record.model_copy(update={"shard": member, "index_fragment": fragment}), index_rows
            if progress:
                progress(PackProgress(done, len(records), writer.count, writer.total))

    segment = write_segment(target, info.schema_version, written(), **spans)
    writer.close()
    for relative in _failure_files(source):
        target.write_atomic(relative, source.read_bytes(relative))
    if source.exists(CARD_FILE):  # the dataset card travels with the data (`datagen shards card`)
        target.write_atomic(CARD_FILE, source.read_bytes(CARD_FILE))
    packed = Manifest(schema_version=info.schema_version, segments=[segment], packed=True)
    target.write_atomic(MANIFEST_FILE, packed.model_dump_json(indent=1).encode())
    target.write_atomic(DATASET_FILE, source.read_bytes(DATASET_FILE))  # last: a dataset once it is there
    return PackSummary(
        source=url,
        out=out_url,
        tasks=len(records),
        samples=segment.num_samples,
        packs=writer.count,
        bytes_written=writer.total,
        seconds=time.perf_counter() - started,
    )


def _read_ahead(source: Location, records: list[CommitRecord]) -> Iterator[tuple[CommitRecord, bytes, pa.Table]]:
    """Each task's shard bytes and index rows, in order, `READ_AHEAD` tasks read side by side."""

    def read(record: CommitRecord) -> tuple[CommitRecord, bytes, pa.Table]:
        return record, source.read_bytes(record.shard), read_index_table(source, record.index_fragment)

    with ThreadPoolExecutor(max_workers=READ_AHEAD) as pool:
        for start in range(0, len(records), 4 * READ_AHEAD):
            yield from pool.map(read, records[start : start + 4 * READ_AHEAD])


def _renamed(rows: pa.Table, shard: str) -> pa.Table:
    """The index rows with their ``shard`` the task's member path in its pack."""
    where = rows.schema.get_field_index("shard")
    return rows.set_column(where, rows.schema.field("shard"), pa.array([shard] * rows.num_rows, pa.string()))


def _failure_files(source: Location) -> list[str]:
    return [f"{FAILURES}/{name}" for name in source.listdir(FAILURES) if name.endswith(".json")]


class _PackWriter:
    """Tar files of about ``target`` bytes under ``packs/``, each written whole before it is published
    (a temporary file renamed into place on local disk; one streamed upload on an object store)."""

    def __init__(self, location: Location, target: int) -> None:
        self.location, self.target = location, target
        self.count = 0
        self.total = 0
        self._tar: tarfile.TarFile | None = None
        self._file: BinaryIO | None = None
        self._temporary = ""

    @property
    def _name(self) -> str:
        return f"{PACKS}/pack-{self.count - 1:05d}.tar"

    def next_pack(self, size: int) -> str:
        """The pack the next task of ``size`` bytes goes to (a new one when the current would pass the
        target size)."""
        if self._tar is None or (self._tar.offset > 0 and self._tar.offset + size > self.target):
            self._finish()
            self._start()
        return self._name

    def add(self, task_id: str, shard: bytes, fragment: bytes) -> tuple[str, int, int]:
        """Add a task's two members; (pack, offset, size) of its shard's bytes in the pack."""
        assert self._tar is not None
        offset = self._member(f"{task_id}{SHARD_MEMBER}", shard)
        self._member(f"{task_id}{INDEX_MEMBER}", fragment)
        return self._name, offset, len(shard)

    def _member(self, name: str, data: bytes) -> int:
        """Write one member (fixed owner, mode and time: the same tasks give the same bytes); the offset
        of its data."""
        assert self._tar is not None
        info = tarfile.TarInfo(name)
        info.size, info.mode, info.mtime = len(data), 0o644, 0
        header = info.tobuf(self._tar.format, self._tar.encoding, self._tar.errors)
        offset = self._tar.offset + len(header)
        self._tar.addfile(info, io.BytesIO(data))
        self.total += len(data)
        return offset

    def _start(self) -> None:
        self.count += 1
        target = self.location.path(self._name)
        self.location.fs.makedirs(target.rsplit("/", 1)[0], exist_ok=True)
        if self.location.is_local:
            self._temporary = f"{target}.tmp-{uuid.uuid4().hex}"
            self._file = open(self._temporary, "wb")  # noqa: SIM115 (closed by _finish)
        else:
            self._file = self.location.fs.open(target, "wb")
        self._tar = tarfile.open(fileobj=self._file, mode="w", format=tarfile.PAX_FORMAT)  # noqa: SIM115

    def _finish(self) -> None:
        if self._tar is None or self._file is None:
            return
        self._tar.close()
        if self.location.is_local:
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self._temporary, self.location.path(self._name))
        else:
            self._file.close()
        self._tar = self._file = None

    def close(self) -> None:
        self._finish()
