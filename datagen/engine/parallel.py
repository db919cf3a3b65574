"""Run one function over many tasks of a dataset side by side: on Ray when a cluster is named or more
than one local worker is asked for, in this process otherwise.

What the `shards` commands that touch every task (``relabel``) use to scale with the machine or the
cluster: each call works on one task through `storage` alone (reads its shard, writes and commits its
own), so calls share nothing but the store, and a call that fails stops the command with its error.
At most `IN_FLIGHT_PER_CPU` calls per CPU are in flight: the results of 100,000 tasks never wait in
memory at once.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any, TypeVar

Result = TypeVar("Result")
IN_FLIGHT_PER_CPU = 4


def run_each(
    function: Callable[..., Result],
    calls: Iterable[tuple[Any, ...]],
    workers: int = 1,
    address: str | None = None,
) -> Iterator[Result]:
    """``function(*args)`` for every ``args`` of ``calls``, results as they finish (in ``calls`` order
    when run here). ``address``: a Ray cluster (or ``auto``); ``workers`` > 1 without one: a local Ray
    of that many CPUs."""
    if address is None and workers <= 1:
        for args in calls:
            yield function(*args)
        return
    yield from _on_ray(function, calls, workers, address)


def _on_ray(
    function: Callable[..., Result], calls: Iterable[tuple[Any, ...]], workers: int, address: str | None
) -> Iterator[Result]:
    import ray

    from datagen.engine.driver import ensure_ray

    ensure_ray(address, None if address else workers)
    remote = ray.remote(num_cpus=1, max_retries=3)(function)
    limit = max(1, int(ray.cluster_resources().get("CPU", workers))) * IN_FLIGHT_PER_CPU
    pending: list[Any] = []
    for args in calls:
        pending.append(remote.remote(*args))
        if len(pending) >= limit:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        yield ray.get(done[0])
