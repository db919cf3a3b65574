"""Fixed plans remembered per dataset, so that choosing them is paid once, not at every evaluation.

Choosing the best fixed view set of every size is an exact search over every single-view case of the
training dataset: 17 minutes for the 1,368 tasks of the real-object split on 2 cores, against 3 s a
mesh for the evaluation itself. The plans depend only on the dataset's committed tasks, the initial
views asked for and the search's settings, so they are kept in ``DATAGEN_HOME/cache/fixed-plans`` under
a key made of exactly those: the dataset's config hash and every committed shard (a task re-run under
a new attempt is another key), the initial views, the node budget and `CACHE_VERSION`. A cache file
that cannot be read is chosen again and rewritten; a cache folder that cannot be written costs the
search, never the evaluation.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

from datagen.evaluate.fixed import NODE_BUDGET, FixedPlans, case_weights, choose_fixed_plans

CACHE_VERSION = 1
"""Raised when what the search chooses changes, so older cache files are not read."""


def dataset_key(url: str, initial_views: tuple[int, ...], storage_options: dict[str, Any] | None = None) -> str:
    """The cache key of ``url``'s fixed plans for ``initial_views``: its committed shards, config and the search."""
    from storage import open_dataset

    dataset = open_dataset(url, storage_options)
    digest = hashlib.sha256()
    head = {"version": CACHE_VERSION, "config": dataset.info.config_hash, "views": sorted(initial_views)}
    digest.update(json.dumps({**head, "budget": NODE_BUDGET}, sort_keys=True).encode())
    for shard in sorted(dataset.samples.shards):
        digest.update(b"\0" + shard.encode())
    return digest.hexdigest()


def cached_fixed_plans(
    url: str,
    initial_views: tuple[int, ...],
    cache: Path | None,
    storage_options: dict[str, Any] | None = None,
) -> tuple[FixedPlans, bool]:
    """The fixed plans of ``url`` for ``initial_views`` from ``cache`` (a folder), or chosen and kept
    there; (plans, whether they came from the cache). ``cache`` None: always chosen, never kept."""
    if cache is None:
        return choose_fixed_plans(case_weights(url, storage_options), url, initial_views), False
    path = cache / f"{dataset_key(url, initial_views, storage_options)}.json"
    try:
        return FixedPlans.from_record(json.loads(path.read_text()), url), True
    except (OSError, ValueError, KeyError, TypeError):
        pass  # absent or unreadable: choose again
    plans = choose_fixed_plans(case_weights(url, storage_options), url, initial_views)
    try:
        cache.mkdir(parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        temporary.write_text(json.dumps(plans.to_record()))
        temporary.replace(path)
    except OSError:
        pass  # a read-only home still evaluates, only without remembering
    return plans, False
