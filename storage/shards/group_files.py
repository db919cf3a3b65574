"""Where a shard group's members live: a folder of files (layouts 1-4) or one ZIP file (layout 5 on).

A Zarr v3 group is a set of named members (``zarr.json``, ``<array>/zarr.json``, ``<array>/c/0/0``).
Layouts 1 to 4 keep each member as a file of its own, about 40 files a task: at 100,000 tasks four
million files, and a reader on an object store pays a request per member. From layout 5 a task's
group is one uncompressed ZIP of the same members (zarr's own ``ZipStore`` opens it), read with one
request; a packed dataset keeps each task's ZIP as a member of a large tar (`storage.dataset.pack`), and
`ZipGroup` then reads that byte range of the tar.

Both kinds answer the same three questions (`GroupFiles`): a member's bytes, which members are
there, and a read-only zarr store for what the fast decoders leave to zarr.
"""

from __future__ import annotations

import io
import os
import struct
import zipfile
from collections.abc import Iterable, Mapping
from typing import Any, Protocol

from zarr.core.buffer import default_buffer_prototype
from zarr.storage import FsspecStore, LocalStore, MemoryStore

from storage.store.location import Location, is_temporary

ZIP_SUFFIX = ".zip"
"""A shard path ending so is a `ZipGroup` (``shards/<task>/<attempt>.zarr.zip``)."""
ZIP_TIME = (1980, 1, 1, 0, 0, 0)
"""Every member's timestamp (ZIP's earliest): the same arrays always give the same bytes."""
LOCAL_HEADER = struct.Struct("<4sHHHHHIIIHH")
"""A ZIP local file header; its last two fields are the lengths of the name and extra field."""
LOCAL_MAGIC = b"PK\x03\x04"


class GroupFiles(Protocol):
    """The members of one shard group, wherever they are stored."""

    location: Location
    relative: str
    """The shard as the index and commit record name it (for messages)."""

    def read(self, member: str) -> bytes:
        """Member ``member`` (``<array>/zarr.json``...); `FileNotFoundError` when it is not there."""
        ...

    def members(self) -> set[str]:
        """Paths of the non-empty members (temporaries of interrupted writes left out)."""
        ...

    def zarr_store(self) -> Any:
        """A read-only zarr store of the group; `FileNotFoundError` when it is not there, and for a ZIP
        whose directory cannot be read `zipfile.BadZipFile`."""
        ...


def group_files(location: Location, relative: str, span: tuple[str, int, int] | None = None) -> GroupFiles:
    """The group at ``relative``: a `ZipGroup` for a ``.zip`` path (or a ``span`` of a pack), else a
    `FolderGroup`."""
    if span is not None or relative.endswith(ZIP_SUFFIX):
        return ZipGroup(location, relative, span)
    return FolderGroup(location, relative)


class FolderGroup:
    """A group stored as a folder of files (layouts 1-4). Metadata members are kept once read: the
    verification and the decoders read each ``zarr.json`` (on S3 a request each)."""

    def __init__(self, location: Location, relative: str) -> None:
        self.location, self.relative = location, relative
        self._metadata: dict[str, bytes] = {}
        self._members: set[str] | None = None

    def read(self, member: str) -> bytes:
        if not member.endswith("zarr.json"):
            return self.location.read_bytes(f"{self.relative}/{member}")
        found = self._metadata.get(member)
        if found is None:
            found = self._metadata[member] = self.location.read_bytes(f"{self.relative}/{member}")
        return found

    def members(self) -> set[str]:
        if self._members is None:
            if self.location.is_local:
                relative: Iterable[str] = local_files(self.location.path(self.relative))
            else:
                root = self.location.path(self.relative).strip("/")
                try:
                    found = self.location.fs.find(self.location.path(self.relative), detail=True)
                except FileNotFoundError:
                    found = {}
                sized = (str(path).strip("/") for path, info in found.items() if info.get("size"))
                relative = (path.removeprefix(root).strip("/") for path in sized)
            self._members = {path for path in relative if not is_temporary(path)}
        return self._members

    def zarr_store(self) -> Any:
        return zarr_store(self.location, self.relative, read_only=True)


def zarr_store(location: Location, relative: str, read_only: bool) -> Any:
    """zarr's store for the folder group at ``relative``."""
    if location.is_local:
        return LocalStore(location.path(relative), read_only=read_only)
    return FsspecStore.from_url(
        location.url_of(relative), storage_options=location.storage_options or None, read_only=read_only
    )


def local_files(top: str) -> list[str]:
    """Paths, relative to ``top`` and sorted, of the non-empty files below local folder ``top`` (none
    when it is missing): what fsspec's ``find`` lists there, without its cost (about 3 ms for a shard
    of 30 files, a tenth of that here), which a streaming reader pays for every shard."""
    found: list[str] = []
    folders = [("", top)]
    while folders:
        prefix, folder = folders.pop()
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            continue
        for entry in entries:
            try:
                if entry.is_dir():
                    folders.append((f"{prefix}{entry.name}/", entry.path))
                elif entry.stat().st_size:
                    found.append(f"{prefix}{entry.name}")
            except FileNotFoundError:
                continue  # gone since the listing (a temporary file renamed into place)
    return sorted(found)


class ZipGroup:
    """A group stored as one uncompressed ZIP: the whole file (or its ``span`` of a pack: file, offset,
    size) is fetched once, on first use, with one request; its members are slices of it.

    Members must be stored uncompressed, as the writer stores them; anything else, or a
    directory that does not parse, reads as missing members, which every reader names as damage.
    """

    def __init__(self, location: Location, relative: str, span: tuple[str, int, int] | None = None) -> None:
        self.location, self.relative, self.span = location, relative, span
        self._data: memoryview | None = None
        self._entries: dict[str, tuple[int, int]] | None = None

    def _bytes(self) -> memoryview:
        if self._data is None:
            if self.span is None:
                self._data = _whole_file(self.location, self.relative)
            else:
                self._data = _file_range(self.location, *self.span)
        return self._data

    def entries(self) -> dict[str, tuple[int, int]]:
        """{member: (start, size)} of the stored members; `FileNotFoundError` when the file is missing,
        `zipfile.BadZipFile` when its directory is damaged."""
        if self._entries is None:
            self._entries = zip_entries(self._bytes())
        return self._entries

    def read(self, member: str) -> bytes:
        try:
            start, size = self.entries()[member]
        except KeyError:
            raise FileNotFoundError(f"{self.relative}: no member {member}") from None
        return bytes(self._bytes()[start : start + size])

    def members(self) -> set[str]:
        try:
            entries = self.entries()
        except (FileNotFoundError, zipfile.BadZipFile, ValueError):
            return set()
        return {name for name, (_, size) in entries.items() if size and not is_temporary(name)}

    def zarr_store(self) -> Any:
        """The members in zarr's read-only memory store (what zarr reads a ZIP into anyway)."""
        prototype = default_buffer_prototype()
        members = {name: prototype.buffer.from_bytes(self.read(name)) for name in sorted(self.entries())}
        return MemoryStore(members, read_only=True)


def zip_entries(data: memoryview) -> dict[str, tuple[int, int]]:
    """{member: (start, size)} of a ZIP's stored (uncompressed) members; a compressed member is an error
    (`zipfile.BadZipFile`): the writer never makes one and the fast paths read members as slices."""
    entries: dict[str, tuple[int, int]] = {}
    with zipfile.ZipFile(_BufferFile(data)) as archive:
        for info in archive.infolist():
            if info.compress_type != zipfile.ZIP_STORED:
                raise zipfile.BadZipFile(f"member {info.filename} is compressed")
            header = bytes(data[info.header_offset : info.header_offset + LOCAL_HEADER.size])
            if len(header) < LOCAL_HEADER.size:
                raise zipfile.BadZipFile(f"member {info.filename} lies past the end")
            fields = LOCAL_HEADER.unpack(header)
            if fields[0] != LOCAL_MAGIC:
                raise zipfile.BadZipFile(f"member {info.filename} has no local header")
            start = info.header_offset + LOCAL_HEADER.size + fields[-2] + fields[-1]
            if start + info.file_size > len(data):
                raise zipfile.BadZipFile(f"member {info.filename} is truncated")
            entries[info.filename] = (start, info.file_size)
    return entries


def zip_bytes(members: Mapping[str, bytes]) -> bytes:
    """An uncompressed ZIP of ``members`` in sorted order with fixed timestamps and modes: the same
    members always give the same bytes. Chunks are compressed already (Blosc), so ZIP compression
    would only cost time."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as archive:
        for name in sorted(members):
            info = zipfile.ZipInfo(name, date_time=ZIP_TIME)
            info.create_system = 3  # unix, whatever the writing machine
            info.external_attr = 0o644 << 16
            archive.writestr(info, members[name])
    return out.getvalue()


class _BufferFile(io.RawIOBase):
    """A read-only, seekable file over a buffer, without copying it (zipfile reads the directory)."""

    def __init__(self, data: memoryview) -> None:
        self._data, self._at = data, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._at

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._at, io.SEEK_END: len(self._data)}[whence]
        self._at = max(0, base + offset)
        return self._at

    def read(self, size: int | None = -1) -> bytes:
        end = len(self._data) if size is None or size < 0 else min(len(self._data), self._at + size)
        found = bytes(self._data[self._at : end])
        self._at = max(self._at, end)
        return found

    def readinto(self, buffer: Any) -> int:
        found = self.read(len(buffer))
        buffer[: len(found)] = found
        return len(found)


def _whole_file(location: Location, relative: str) -> memoryview:
    return memoryview(location.read_bytes(relative))


def _file_range(location: Location, relative: str, offset: int, size: int) -> memoryview:
    """``size`` bytes of a file from ``offset`` (one ranged request on an object store)."""
    if location.is_local:
        with open(location.path(relative), "rb") as handle:
            data = os.pread(handle.fileno(), size, offset)
    else:
        data = bytes(location.fs.cat_file(location.path(relative), start=offset, end=offset + size))
    if len(data) != size:
        raise FileNotFoundError(f"{relative}: {size} bytes wanted from {offset}, {len(data)} stored")
    return memoryview(data)
