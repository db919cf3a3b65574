"""One SHA-256 over a dataset's content, for comparing two runs of the same job (a local run and a
cluster run, a run with faults and one without): every committed task's shard arrays, every sample's
points, observed keys and masks, and every index column except the volatile ones (times, attempts,
hosts), all in task and sample-id order, so that neither the order tasks finished in nor which node
ran them changes it. Two datasets with the same digest hold the same samples, byte for byte.

    python scripts/dataset_digest.py URL [URL ...]   # per dataset: DIGEST  SAMPLES  DISTINCT-IDS  URL

S3 URLs use the standard AWS variables (AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, ...).
"""

from __future__ import annotations

import hashlib
import sys

import numpy as np

from schemas.index import VOLATILE_COLUMNS
from schemas.shard import array_names
from storage import committed_tasks, open_dataset, open_location
from storage.shards import ShardReader


def _update(digest: hashlib._Hash, name: str, value: object) -> None:
    digest.update(name.encode() + b"\0")
    if isinstance(value, np.ndarray):
        digest.update(str((value.dtype.str, value.shape)).encode())
        digest.update(np.ascontiguousarray(value).tobytes())
    else:
        digest.update(repr(value).encode())


def dataset_digest(url: str) -> tuple[str, int, int]:
    """(hex SHA-256 of the dataset's content, number of samples, number of distinct sample ids)."""
    dataset, location = open_dataset(url), open_location(url)
    digest = hashlib.sha256()
    _update(digest, "schema_version", dataset.info.schema_version)
    for record in sorted(committed_tasks(location), key=lambda r: r.task_id):
        shard = ShardReader(location, record.shard)
        for name in array_names(dataset.info.schema_version):
            _update(digest, f"{record.task_id}/{name}", np.asarray(shard.array(name)))
    ids = dataset.index.column("sample_id").to_pylist()
    for i in sorted(range(len(ids)), key=ids.__getitem__):
        for source in ("points", "observed"):
            _update(digest, f"{ids[i]}/{source}", np.asarray(dataset.keys(i, source)))
        _update(digest, f"{ids[i]}/masks", dataset.masks(i))
    columns = [name for name in dataset.index.column_names if name not in VOLATILE_COLUMNS]
    table = dataset.index.select(columns).sort_by("sample_id")
    for name in columns:
        _update(digest, f"index/{name}", table.column(name).to_pylist())
    return digest.hexdigest(), len(ids), len(set(ids))


def main(urls: list[str]) -> int:
    if not urls:
        print(__doc__.strip().splitlines()[4].strip(), file=sys.stderr)
        return 2
    for url in urls:
        value, samples, distinct = dataset_digest(url)
        print(f"{value}  {samples}  {distinct}  {url}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
