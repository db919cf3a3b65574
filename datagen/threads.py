"""Thread bounds for per-view math.

A tall-skinny matmul such as (100k x 3) @ (3 x 3) runs up to 100x slower with two OpenBLAS
threads than with one on a 2-core machine (limits.md, pitfall 1). Pipeline entry points wrap
their work in `single_threaded_blas`; parallelism comes from running tasks side by side.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import threadpool_limits


@contextmanager
def single_threaded_blas(threads: int = 1) -> Iterator[None]:
    with threadpool_limits(limits=threads, user_api="blas"):
        yield
