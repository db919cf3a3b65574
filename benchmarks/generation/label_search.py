"""Benchmark: labels by the exact search against HiGHS's MIP, on the cases of real tasks.

    python -m benchmarks.generation.label_search [--objects builtin:torus_knot_3_5 builtin:bunny ...] [--refiner poco]

For each object (rotation 0, the default config otherwise, so the default POCO refiner), the task is
scanned, refined and its long-tail cases drawn once; then every case is labelled twice on the same
coverage table:

- baseline: HiGHS only (`SEARCH_NODE_BUDGET = 0`): LP bound, the MIP for the size when greedy does
  not meet the bound, the weighted MIP for the tie-break (the labeller before the search);
- search: the default path (LP bound, then `CoverSearch` for the size and the tie-break).

Both must give the same label for every case (checked). Printed per object: cases, how the size was
proven, seconds of each path (total, median, max) and the ratio baseline / search. Single-threaded.
"""

from __future__ import annotations

from benchmarks.common import limit_threads

limit_threads()

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from datagen.pipeline import setcover  # noqa: E402
from datagen.pipeline.cases import long_tail_cases  # noqa: E402
from datagen.pipeline.coverage import coverage_table  # noqa: E402
from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.objects.spec import ObjectSpec  # noqa: E402
from datagen.pipeline.random_streams import Purpose, stream  # noqa: E402
from datagen.pipeline.refine import make_refiner  # noqa: E402
from datagen.pipeline.scanning import scan_task  # noqa: E402
from datagen.pipeline.task import refine_views  # noqa: E402
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402

DEFAULT_OBJECTS = ("builtin:torus_knot_3_5", "builtin:torus_knot", "builtin:gear", "builtin:mug")


def label_all(solver: setcover.TaskCover, cases: list[int], budget: int) -> tuple[list[int], list[float], Counter[str]]:
    original = setcover.SEARCH_NODE_BUDGET
    setcover.SEARCH_NODE_BUDGET = budget
    try:
        labels, seconds, proofs = [], [], Counter[str]()
        for case in cases:
            clock = time.perf_counter()
            result = solver.label(case)
            seconds.append(time.perf_counter() - clock)
            labels.append(result.label)
            proofs[result.proof] += 1
        return labels, seconds, proofs
    finally:
        setcover.SEARCH_NODE_BUDGET = original


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--objects", nargs="+", default=list(DEFAULT_OBJECTS))
    parser.add_argument("--refiner", default="poco")
    args = parser.parse_args()
    config = GenerationConfig(refiner=args.refiner)
    refiner = make_refiner(config, "cpu")
    view_space = build_view_space(config.view_space)
    with tempfile.TemporaryDirectory() as folder:
        listing = Path(folder) / "objects.txt"
        listing.write_text("\n".join(args.objects) + "\n")
        entries = read_objects_file(listing).entries
    specs = [entry for entry in entries if isinstance(entry, ObjectSpec)]
    for entry in entries:
        if not isinstance(entry, ObjectSpec):
            print(f"skipped: {entry}")
    print(f"refiner {args.refiner}, alpha {config.alpha}, rotation 0; seconds per path, all cases of the task")
    print("object | cases | size proven by (search path) | HiGHS only: total / median / max | search: same | ratio")
    totals = [0.0, 0.0]
    for spec in specs:
        with single_threaded_blas(), fixed_torch_threads():
            prepared = prepare_object(spec, config)
            scan = scan_task(prepared, 0, config, view_space)
            views = refine_views(scan, refiner, config, spec.object_id, 0)
        cases = long_tail_cases(views.sets.visible, stream(config.seed, spec.object_id, 0, Purpose.CASES))
        solver = setcover.TaskCover(coverage_table(views.sets.refined, config.alpha).masks, config.num_views)
        highs, highs_s, _ = label_all(solver, cases, 0)
        search, search_s, proofs = label_all(solver, cases, setcover.SEARCH_NODE_BUDGET)
        if highs != search:
            wrong = sum(a != b for a, b in zip(highs, search, strict=True))
            raise SystemExit(f"{spec.name}: {wrong} labels differ between the two paths")
        totals[0] += sum(highs_s)
        totals[1] += sum(search_s)

        def row(values: list[float]) -> str:
            return f"{sum(values):.2f} / {np.median(values):.3f} / {max(values):.3f}"

        proven = " ".join(f"{k}:{v}" for k, v in sorted(proofs.items()))
        ratio = sum(highs_s) / max(sum(search_s), 1e-9)
        print(f"{spec.name} | {len(cases)} | {proven} | {row(highs_s)} | {row(search_s)} | {ratio:.1f}x")
    print(f"all objects: HiGHS only {totals[0]:.1f} s, search {totals[1]:.1f} s, ratio {totals[0] / totals[1]:.1f}x")


if __name__ == "__main__":
    main()
