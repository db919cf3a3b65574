"""Thread bounds for per-view math.

A tall-skinny matmul such as (100k x 3) @ (3 x 3) runs up to 100x slower with two OpenBLAS
threads than with one on a 2-core machine (measured when the pipeline was built). Pipeline entry points wrap
their work in `single_threaded_blas`; parallelism comes from running tasks side by side.

Workers also hold torch (the ``poco`` refiner) to a fixed count with `fixed_torch_threads`: its
reductions split work by thread, so a fixed count per worker is what keeps refinements
bit-identical whatever the number of workers (docs/pipeline.md section 9).
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

from threadpoolctl import threadpool_limits

WORKER_TORCH_THREADS = 1
"""torch threads per worker: parallelism comes from one worker per core."""


@contextmanager
def single_threaded_blas(threads: int = 1) -> Iterator[None]:
    with threadpool_limits(limits=threads, user_api="blas"):
        yield


@contextmanager
def fixed_torch_threads(threads: int = WORKER_TORCH_THREADS) -> Iterator[None]:
    """torch's intra-op thread count while inside (a no-op when torch was never imported)."""
    torch = sys.modules.get("torch")
    if torch is None:
        yield
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
