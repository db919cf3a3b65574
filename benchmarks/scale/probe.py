"""One reader operation on one dataset, run in a process of its own by `benchmarks.scale.dataset_commands`.

    python benchmarks/scale/probe.py OPERATION URL REPORT.json

It writes to REPORT the seconds the operation itself took (its imports apart: `floor` measures those)
and, on S3, the requests it made (every call s3fs sends to the server, counted where s3fs sends it).
Run by path, so that an older source tree first on ``PYTHONPATH`` is the one measured.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from typing import Any

BATCH = 32
POINTS = 2048
WORKERS = 2


def _open(url: str) -> Any:
    import storage

    return storage.open_dataset(url)


def _map_style(url: str) -> Any:
    """The map-style reader's first batch: `OSVPDataset` with the shard-aware shuffle, 2 workers."""
    from torch.utils.data import DataLoader

    from storage.torch import OSVPDataset, ShardShuffleSampler, collate_samples

    dataset = OSVPDataset(url, num_points=POINTS)
    sampler = ShardShuffleSampler(dataset, seed=0)
    loader = DataLoader(dataset, batch_size=BATCH, sampler=sampler, num_workers=WORKERS, collate_fn=collate_samples)
    return next(iter(loader))


def _streaming(url: str) -> Any:
    """The streaming reader's first batch: `ShardStream`, 2 workers."""
    from storage.stream import ShardStream

    stream = ShardStream(url, num_points=POINTS, batch_size=BATCH, num_workers=WORKERS)
    return next(iter(stream.loader()))


def _sample(url: str) -> Any:
    """Open, then read the last sample (its shard verified first)."""
    dataset = _open(url)
    return dataset[len(dataset) - 1]


def _command(*args: str) -> Callable[[str], Any]:
    """A `datagen` command on the dataset, run in this process (its output to stdout), so that its
    requests are counted too."""

    def run(url: str) -> Any:
        from datagen.cli.main import app

        return app([*args, url], standalone_mode=False)

    return run


PROBES: dict[str, Callable[[str], Any]] = {
    "floor": lambda url: None,
    "open": _open,
    "sample": _sample,
    "map-style": _map_style,
    "streaming": _streaming,
    "ls": _command("shards", "ls"),
    "stats": _command("shards", "stats"),
}
"""The operations, by name (`floor`: the imports and start-up every probe pays, nothing more)."""


def _count_s3_requests() -> list[int]:
    """Count every request s3fs sends (its one place that calls the S3 API)."""
    try:
        import s3fs
    except ImportError:
        return [0]
    count = [0]
    original = s3fs.S3FileSystem._call_s3

    async def counted(self: Any, method: Any, *args: Any, **kwargs: Any) -> Any:
        count[0] += 1
        return await original(self, method, *args, **kwargs)

    s3fs.S3FileSystem._call_s3 = counted  # type: ignore[method-assign]
    return count


def main() -> None:
    operation, url, report = sys.argv[1:4]
    import torch  # noqa: F401

    import storage  # noqa: F401  (the imports are the floor's, not the operation's)

    requests = _count_s3_requests()
    started = time.perf_counter()
    PROBES[operation](url)
    seconds = time.perf_counter() - started
    with open(report, "w") as handle:
        json.dump({"seconds": seconds, "requests": requests[0]}, handle)


if __name__ == "__main__":
    main()
