"""Benchmark: what bounds the POCO refiner's two largest costs, on one task's real inputs.

    python -m benchmarks.generation.refiner_bounds                     # builtin:mug, every 6th refinement
    python -m benchmarks.generation.refiner_bounds --object builtin:capsule --every 3 --compile

The decoder's neighbour table (each query's K nearest input points) and the decoder's layers are
most of a task's refinement (benchmarks/generation/results/task-cost.md). This script runs one task
as the pipeline does, keeps the (input points, queries) of some of its refinements, and times, on
exactly those, in one thread and in one run:

- the neighbour table by every exact kNN search at hand: pykdtree on float64 (``poco_version`` 2's),
  pykdtree on float32, scipy's cKDTree (version 1's), scikit-learn's KDTree when installed, and a
  brute force (torch ``cdist`` + ``topk``) on the first 4,096 queries, scaled; each as a ratio to
  version 2's search;
- the decoder's neighbour part (`InterpAttentionKHeadsNet.pooled_inference`, which is nearly all of
  the decoder) on 1,024-query chunks of the captured queries, against its FLOP floor (its
  multiply-adds at this machine's single-thread float32 matmul rate), beside the same arithmetic in
  the channels-last layout and, with ``--compile``, under ``torch.compile`` (inductor; the compile
  time is printed, not counted).

Timings are the best of ``--repeats``; every ratio compares measurements of the same run.
"""

from __future__ import annotations

from benchmarks.common import limit_threads

limit_threads()

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from torch import Tensor  # noqa: E402

from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.refine import make_refiner  # noqa: E402
from datagen.pipeline.refine.poco.network import InterpAttentionKHeadsNet, PocoModel  # noqa: E402
from datagen.pipeline.refine.poco.refiner import PocoRefiner  # noqa: E402
from datagen.pipeline.task import run_task  # noqa: E402
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402

CHUNK = 1024
"""Queries per decoder chunk (`PocoModel.decode_inference`'s sub-chunk for the small preset)."""
BRUTE_QUERIES = 4096


def capture(object_line: str, every: int) -> tuple[PocoModel, list[tuple[Tensor, Tensor, Tensor]]]:
    """Run one task (rotation 0, the default config) and keep (latents, points, queries) of every
    ``every``-th refinement: the decoder's inputs, from which its neighbour table is built."""
    with tempfile.TemporaryDirectory() as folder:
        listing = Path(folder) / "objects.txt"
        listing.write_text(object_line + "\n", encoding="utf-8")
        spec = read_objects_file(listing).objects[0]
    config = GenerationConfig()
    refiner = make_refiner(config)
    if not isinstance(refiner, PocoRefiner):
        raise SystemExit("the default config's refiner is not poco")
    kept: list[tuple[Tensor, Tensor, Tensor]] = []
    seen = 0
    original = PocoModel.decode_inference

    def keep(self: PocoModel, latents: Tensor, points: Tensor, queries: Tensor, knn: Tensor, chunk: int) -> Tensor:
        nonlocal seen
        if seen % every == 0:
            kept.append((latents.clone(), points.clone(), queries.clone()))
        seen += 1
        return original(self, latents, points, queries, knn, chunk)

    PocoModel.decode_inference = keep  # type: ignore[method-assign]
    try:
        with single_threaded_blas(), fixed_torch_threads():
            run_task(prepare_object(spec, config), 0, config, build_view_space(config.view_space), refiner)
    finally:
        PocoModel.decode_inference = original  # type: ignore[method-assign]
    return refiner.model, kept


def best_of(repeats: int, work: Callable[[], Any]) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        work()
        best = min(best, time.perf_counter() - start)
    return best


def knn_searches(k: int) -> dict[str, Callable[[np.ndarray, np.ndarray], Any]]:
    """Exact kNN searches by name: (source (N, 3) float64, targets (M, 3) float64) -> indices."""
    from pykdtree.kdtree import KDTree
    from scipy.spatial import cKDTree

    searches: dict[str, Callable[[np.ndarray, np.ndarray], Any]] = {
        "pykdtree float64 (version 2)": lambda s, t: KDTree(s).query(t, k=k)[1],
        "pykdtree float32": lambda s, t: KDTree(s.astype(np.float32)).query(t.astype(np.float32), k=k)[1],
        "scipy cKDTree (version 1)": lambda s, t: cKDTree(s).query(t, k=k, workers=1)[1],
    }
    try:
        from sklearn.neighbors import KDTree as SkKDTree

        searches["scikit-learn KDTree"] = lambda s, t: SkKDTree(s).query(t, k=k)[1]
    except ImportError:
        pass

    def brute(source: np.ndarray, targets: np.ndarray) -> Any:
        src, dst = torch.from_numpy(source), torch.from_numpy(targets[:BRUTE_QUERIES])
        return torch.topk(torch.cdist(dst, src), k, dim=1, largest=False).indices

    searches["brute force (cdist + topk)"] = brute
    return searches


def pooled_channels_last(
    decoder: InterpAttentionKHeadsNet, terms: Tensor, query_terms: Tensor, index: Tensor
) -> Tensor:
    """The same arithmetic as `pooled_inference` with channels last: rows (M, K, L) gathered whole."""
    m, k = index.shape[1:]
    rows = terms.index_select(0, index.reshape(-1)).view(m, k, -1)
    h = (rows + query_terms.unsqueeze(1)).relu_()
    h = F.linear(h, decoder.fc2.weight.flatten(1), decoder.fc2.bias).relu_()
    h = F.linear(h, decoder.fc3.weight.flatten(1), decoder.fc3.bias).relu_()
    attention = torch.softmax(F.linear(h, decoder.fc_query.weight.flatten(1), decoder.fc_query.bias), dim=1)
    return torch.bmm(attention.mean(dim=2).unsqueeze(1), h).squeeze(1)


def matmul_gflops() -> float:
    """Single-thread float32 matmul rate (2048^2), best of 3."""
    a = torch.randn(2048, 2048)
    seconds = best_of(3, lambda: a @ a)
    return 2 * 2048**3 / seconds / 1e9


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--object", default="builtin:mug", help="objects-file line of the task (default builtin:mug)")
    parser.add_argument("--every", type=int, default=6, help="keep every n-th refinement (default 6)")
    parser.add_argument("--repeats", type=int, default=3, help="timings per measurement; the best counts")
    parser.add_argument("--compile", action="store_true", help="also time the decoder under torch.compile")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    model, kept = capture(args.object, args.every)
    decoder = model.projection
    k = decoder.k
    queries_total = sum(int(q.shape[2]) for _, _, q in kept)
    print(f"{args.object}: {len(kept)} refinements kept, {queries_total:,} queries, K = {k}")

    print("\nneighbour table (each query's K nearest inputs), CPU seconds summed over the kept refinements:")
    times: dict[str, float] = {}
    for name, search in knn_searches(k).items():
        total = 0.0
        for _, points, queries in kept:
            source = points[0].T.double().numpy()
            targets = queries[0].T.double().numpy()
            seconds = best_of(args.repeats, lambda f=search, s=source, t=targets: f(s, t))
            total += seconds * (targets.shape[0] / min(targets.shape[0], BRUTE_QUERIES) if "brute" in name else 1)
        times[name] = total
    base = times["pykdtree float64 (version 2)"]
    for name, seconds in times.items():
        print(f"  {name:32s} {seconds:7.3f} s  {seconds / base:5.2f}x  {seconds / queries_total * 1e6:5.2f} us a query")

    rate = matmul_gflops()
    per_pair = 2 * decoder.latent_size * decoder.latent_size * 2 + 2 * decoder.latent_size * decoder.heads
    print(f"\ndecoder neighbour part, 1,024-query chunks (float32 matmul: {rate:.0f} GFLOP/s on one thread):")
    layouts: dict[str, Callable[[Tensor, Tensor, Tensor, Tensor], Tensor]] = {
        "channels first (the pipeline's)": lambda t, tl, q, i: decoder.pooled_inference(t, q, i),
        "channels last": lambda t, tl, q, i: pooled_channels_last(decoder, tl, q[0].T.contiguous(), i),
    }
    if args.compile:
        compiled = torch.compile(decoder.pooled_inference, dynamic=True)
        layouts["torch.compile (inductor)"] = lambda t, tl, q, i: compiled(t, q, i)
    with torch.inference_mode():
        chunks = []
        for latents, points, queries in kept:
            terms = decoder.point_terms(latents, points)
            index = model.query_knn(points, queries)
            query_terms = decoder.query_terms(queries)
            for start in range(0, queries.shape[2] - CHUNK + 1, CHUNK):
                stop = start + CHUNK
                chunks.append((terms, terms[0].T.contiguous(), query_terms[:, :, start:stop], index[:, start:stop]))
        flops = len(chunks) * CHUNK * k * per_pair
        floor = flops / (rate * 1e9)
        first = None
        for name, run in layouts.items():
            if "compile" in name:
                start = time.perf_counter()
                run(*chunks[0])
                print(f"  ({name}: compiled in {time.perf_counter() - start:.1f} s)")
            seconds = sum(best_of(args.repeats, lambda f=run, c=c: f(*c)) for c in chunks)
            first = seconds if first is None else first
            print(
                f"  {name:32s} {seconds:7.3f} s  {seconds / first:5.2f}x the pipeline's  "
                f"{seconds / floor:5.1f}x its FLOP floor ({flops / 1e9:.1f} GFLOP: {floor:.3f} s)"
            )


if __name__ == "__main__":
    main()
