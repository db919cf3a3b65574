"""Where a dataset lives: a local path or any fsspec URL, and the few file operations the commit
protocol needs (atomic publish, first-writer-wins create)."""

from __future__ import annotations

import contextlib
import os
import posixpath
import re
import uuid
from dataclasses import dataclass, field
from typing import Any

import fsspec
from fsspec.implementations.local import LocalFileSystem
from pydantic import ValidationError

from schemas.errors import DatagenError


class StorageError(DatagenError):
    """The dataset location cannot be reached, read or written; the message says what to do. Its two
    kinds: `StoreUnreachable` (the store itself fails us) and `DamagedFile` (the dataset is damaged)."""


class StoreUnreachable(StorageError):
    """The store cannot be reached or refuses the request (a wrong endpoint or path, refused
    credentials, a missing bucket, a server down): nothing is known about the dataset's own files."""


TEMPORARY_MARK = ".tmp-"
"""Names of `_durable_temporary` files carry this; readers never open such a file."""
ZARR_PARTIAL = re.compile(r"\.[0-9a-f]{32}\.partial$")
"""zarr's LocalStore writes ``<name>.<uuid hex>.partial`` and renames it into place."""

REPAIR_COMMAND = "datagen shards repair"
RERUN_FIX = f"`{REPAIR_COMMAND} URL` re-runs the damaged tasks and finalises the index again"
"""The fix of a damaged task's file. `resume` and a re-submit cannot do it: the ledger has the task
done and the dataset has its commit record, so both find nothing to run."""


class DamagedFile(StorageError):
    """A file of the dataset is missing, truncated or corrupt (raised by readers, never silent).

    ``relative`` (the file's path in the dataset) and ``problem`` (what is wrong with it) let
    `storage.validate` print its own line; the message adds the URL and the fix. Built by
    `damaged`; the attributes survive pickling (a DataLoader worker re-raises it in the parent).
    """

    relative: str = ""
    problem: str = ""


def damaged(url: str, relative: str, problem: str, rerun_task: bool = False) -> DamagedFile:
    """One line naming the dataset, the file and the fix: `datagen shards repair URL` where re-running
    the task (or finalising the index again) mends it, else `datagen shards validate URL` to see all."""
    if rerun_task:
        fix = f"run `{REPAIR_COMMAND} {url}` (it re-runs the damaged tasks; `datagen shards validate {url}` lists them)"
    else:
        fix = f"run `datagen shards validate {url}`"
    error = DamagedFile(f"{url}: {relative}: {problem}; {fix}")
    error.relative, error.problem = relative, problem
    return error


def is_temporary(path: str) -> bool:
    """True for a temporary file of an unfinished or interrupted atomic write (ours or zarr's)."""
    name = path.rsplit("/", 1)[-1]
    return TEMPORARY_MARK in name or ZARR_PARTIAL.search(name) is not None


def first_validation_error(error: ValidationError) -> str:
    """``where: what`` of a pydantic error's first problem (its full text spans many lines)."""
    first = error.errors()[0]
    where = ".".join(str(part) for part in first["loc"])
    return f"{where}: {first['msg']}" if where else str(first["msg"])


def first_line(error: BaseException) -> str:
    """``Type: first line of the message``: enough to tell damage apart, still one line."""
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0] if text else 'no message'}"


@dataclass(frozen=True)
class Location:
    """A dataset root on a filesystem; paths below it are POSIX-style and relative."""

    fs: fsspec.AbstractFileSystem
    root: str
    url: str
    storage_options: dict[str, Any] = field(default_factory=dict)

    @property
    def is_local(self) -> bool:
        return isinstance(self.fs, LocalFileSystem)

    def path(self, relative: str) -> str:
        return posixpath.join(self.root, relative) if relative else self.root

    def url_of(self, relative: str) -> str:
        """A URL for a path below the root (for libraries that open URLs themselves, like zarr)."""
        path = self.path(relative)
        if self.is_local:
            return path
        protocol = self.fs.protocol if isinstance(self.fs.protocol, str) else self.fs.protocol[0]
        return f"{protocol}://{path.lstrip('/')}" if protocol == "memory" else f"{protocol}://{path}"

    def exists(self, relative: str) -> bool:
        return bool(self.fs.exists(self.path(relative)))

    def read_bytes(self, relative: str) -> bytes:
        if self.is_local:
            # The operating system's read directly: fsspec's local cat_file costs ~50 us more a file
            # (path normalising, a file object of its own), which a reader pays for every array.
            with open(self.path(relative), "rb") as file:
                return file.read()
        data = self.fs.cat_file(self.path(relative))
        return bytes(data)

    def write_atomic(self, relative: str, data: bytes) -> None:
        """Publish a whole file: readers see the old content or the new one, never a prefix."""
        target = self.path(relative)
        self.fs.makedirs(posixpath.dirname(target), exist_ok=True)
        if self.is_local:
            temporary = _durable_temporary(target, data)
            try:
                os.replace(temporary, target)
            except BaseException:
                _discard(temporary)
                raise
        else:
            # Object stores and the memory filesystem publish a single put whole.
            self.fs.pipe_file(target, data)

    def create_exclusive(self, relative: str, data: bytes) -> bool:
        """Publish a file only if none exists yet; True if this call created it.

        Local: a fully written temporary file is hard-linked into place, which fails atomically if
        the target exists. S3: a conditional put (``If-None-Match: *``), after a check (a store that
        ignores the condition still rarely sees two attempts of one task: the ledger makes them rare,
        and both write identical content by determinism). Other filesystems: check, then put.
        """
        target = self.path(relative)
        self.fs.makedirs(posixpath.dirname(target), exist_ok=True)
        if self.is_local:
            temporary = _durable_temporary(target, data)
            try:
                os.link(temporary, target)
                return True
            except FileExistsError:
                return False
            finally:
                os.unlink(temporary)
        if self.fs.exists(target):
            return False
        if not is_s3(self.url):
            self.fs.pipe_file(target, data)
            return True
        try:
            self.fs.pipe_file(target, data, mode="create")
        except FileExistsError:
            return False
        except OSError as exc:
            if _precondition_failed(exc):
                return False
            raise
        return True

    def listdir(self, relative: str) -> list[str]:
        """Names directly under a folder that hold a file, sorted; empty when it does not exist.

        On an object store the names come from the files below (one recursive listing): SeaweedFS
        keeps a folder whose every object was deleted as an empty prefix, so a swept attempt would
        otherwise be listed (and "removed") again by every later sweep.
        """
        if self.is_local:
            try:
                entries = self.fs.ls(self.path(relative), detail=False)
            except FileNotFoundError:
                return []
            return sorted(posixpath.basename(str(e).rstrip("/")) for e in entries)
        base = self.path(relative).strip("/")
        try:
            found = self.fs.find(self.path(relative))
        except FileNotFoundError:
            return []
        names = {str(path).strip("/").removeprefix(base).strip("/").split("/")[0] for path in found}
        return sorted(name for name in names if name)

    def remove(self, relative: str, recursive: bool = False) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.fs.rm(self.path(relative), recursive=recursive)


def _durable_temporary(target: str, data: bytes) -> str:
    """A fully written, fsynced file beside ``target``, to be moved or linked into place.

    A write that fails (a full disk) removes its partial file; only a killed process leaves one,
    which readers never open and `storage.validate` names as a leftover.
    """
    temporary = f"{target}{TEMPORARY_MARK}{uuid.uuid4().hex}"
    try:
        with open(temporary, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
    except BaseException:
        _discard(temporary)
        raise
    return temporary


def _precondition_failed(error: OSError) -> bool:
    """A conditional put refused because the object exists. s3fs turns that into FileExistsError
    only when the answer names the condition (AWS, moto); SeaweedFS answers 412 PreconditionFailed
    without it, which s3fs raises as a plain OSError."""
    cause = error.__cause__
    response = getattr(cause, "response", None)
    if not isinstance(response, dict):
        return False
    status = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
    return bool(response.get("Error", {}).get("Code") == "PreconditionFailed" or status == 412)


def _discard(path: str) -> None:
    with contextlib.suppress(OSError):
        os.unlink(path)


S3_SCHEMES = ("s3://", "s3a://")


def is_s3(url: str) -> bool:
    return url.startswith(S3_SCHEMES)


def environment_options(url: str) -> dict[str, Any]:
    """Endpoint and region of an S3 URL from this process's standard AWS variables.

    Read where the store is opened (driver, each worker, a laptop reading the dataset), never passed
    between processes: a worker in a cluster reaches MinIO at its own address, and credentials stay
    with botocore's usual chain (AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY, profiles), out of every
    log, ledger row and ``dataset.json``.
    """
    if not is_s3(url):
        return {}
    options: dict[str, Any] = {}
    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
    if endpoint:
        options["endpoint_url"] = endpoint
    region = os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION")
    if region:
        options["client_kwargs"] = {"region_name": region}
    return options


def open_location(url: str, storage_options: dict[str, Any] | None = None) -> Location:
    """The filesystem and root path for a dataset URL (a plain path means the local disk).

    For ``s3://`` the endpoint and region come from the environment (`environment_options`) unless
    ``storage_options`` gives them.
    """
    storage_options = {**environment_options(url), **(storage_options or {})}
    if is_s3(url):
        # Other processes write the store (workers, another driver, a resumed run): a listing cached
        # for the life of the (process-wide, shared) s3fs instance would hide their commits.
        storage_options.setdefault("use_listings_cache", False)
    try:
        fs, root = fsspec.core.url_to_fs(url, **storage_options)
    except ImportError as exc:
        if is_s3(url):
            fix = "pip install s3fs (the [s3] extra of datagen or datagen-reader)"
            raise StorageError(f"{url}: S3 needs s3fs; install it with: {fix}") from None
        raise StorageError(f"{url}: unsupported dataset URL ({exc}); use a local path or an fsspec URL") from None
    except ValueError as exc:
        raise StorageError(f"{url}: unsupported dataset URL ({exc}); use a local path or an fsspec URL") from None
    if isinstance(fs, LocalFileSystem):
        root = os.path.abspath(root)
    if is_s3(url) and hasattr(fs, "retries"):
        # s3fs retries failed calls itself (5 times) on top of botocore's own attempts
        # (storage_options' config_kwargs); one layer of retries keeps the bound what settings say.
        fs.retries = 1
    return Location(fs=fs, root=str(root).rstrip("/") or "/", url=url, storage_options=storage_options)
