"""Benchmark: exact labels (docs/pipeline.md section 7) against a naive HiGHS model, on real meshes.

    python benchmarks/labels.py [--meshes DIR] [--alphas 1 5 10] [--naive-stride A=S ...]

For every mesh of DIR (default ../shared/meshes) at size 0.15 m, rotation 0, refiner ``none`` and
``targets`` imaging, the imaging and the long-tail cases are computed once per mesh, then the
coverage table per alpha. For every case it times:

- ours: `TaskCover.label` (filter the task's minimal masks, forced views, greedy + LP bound or MIP,
  lexicographic tie-break), wall clock per call; the per-task reduction (`TaskCover(...)`, once per
  task and alpha) is reported separately;
- naive: one row per key of U (no merging of identical rows, no dominance), columns = the views not
  in S, one HiGHS MIP minimising the cardinality, then the same lexicographic tie-break done
  naively as a second weighted HiGHS MIP (maximise sum 2^(m-1-rank(v)) x_v with sum x_v = k*),
  both with gaps 0, threads 1, HiGHS defaults otherwise. Model building from the masks is timed.

It also reports the label-size distribution, how optimality was proven (counts of
`CoverResult.proof`), and how often classic greedy set cover (most uncovered keys of U first, ties
to the lowest view) is larger than the optimum. Naive labels are checked against ours.

The naive model is slow on non-degenerate problems (alpha 5), so it runs on a deterministic
subsample: every S-th case of the (mesh, case) order, per alpha (``--naive-stride``); the output
says which. Ratios are taken on the naive subsample only (same cases for both sides). Times are
single-threaded (OPENBLAS 1, HiGHS threads 1); p99 is numpy's linearly interpolated percentile.
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import highspy  # noqa: E402
import numpy as np  # noqa: E402

from datagen.pipeline.cases import long_tail_cases  # noqa: E402
from datagen.pipeline.coverage import coverage_table, filter_to_ground_truth  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.objects.spec import ObjectOptions, mesh_file_spec  # noqa: E402
from datagen.pipeline.random_streams import Purpose, stream  # noqa: E402
from datagen.pipeline.refine import RefineRequest, make_refiner, refined_keys  # noqa: E402
from datagen.pipeline.scanning import scan_task  # noqa: E402
from datagen.pipeline.setcover import CoverResult, TaskCover, cover_model  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402

REPO_ROOT = Path(__file__).resolve().parents[1]
MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb"}
SIZE_M = 0.15
DEFAULT_ALPHAS = (1, 5, 10)
DEFAULT_NAIVE_STRIDE = {1: 1, 5: 4, 10: 2}
"""Naive model on every S-th case per alpha (deterministic), chosen so that it runs in ~6 minutes."""
NAIVE_TIME_LIMIT = 60.0
TARGET_MEDIAN_S = 0.020
TARGET_P99_S = 0.5
TARGET_SPEEDUP = 5.0
TARGET_ALPHA = 10


# ---------------------------------------------------------------------------------------------------------
# The naive baseline
# ---------------------------------------------------------------------------------------------------------


def naive_highs(time_limit: float) -> highspy.Highs:
    solver = highspy.Highs()
    solver.setOptionValue("output_flag", False)
    solver.setOptionValue("threads", 1)
    solver.setOptionValue("time_limit", float(time_limit))
    solver.setOptionValue("mip_rel_gap", 0.0)
    solver.setOptionValue("mip_abs_gap", 0.0)
    solver.setOptionValue("random_seed", 0)
    return solver


def naive_model(
    universe: np.ndarray, columns: list[int], costs: list[float], cardinality: int | None, maximise: bool
) -> highspy.HighsLp:
    """Binary model over ``columns``: one row per key (sum of its covering columns >= 1), an
    optional row sum(x) == cardinality (`setcover.cover_model` on the unreduced keys)."""
    return cover_model(universe, columns, costs, maximise=maximise, cardinality=cardinality)


def naive_solve(lp: highspy.HighsLp, time_limit: float) -> list[float] | None:
    solver = naive_highs(time_limit)
    solver.passModel(lp)
    solver.run()
    if solver.getModelStatus() != highspy.HighsModelStatus.kOptimal:
        return None
    return list(solver.getSolution().col_value)


def naive_label(masks: np.ndarray, case: int, num_views: int, time_limit: float) -> int | None:
    """Label of case S by the naive model; None when HiGHS does not prove optimality in time."""
    universe = masks[(masks & np.uint64(case)) == 0]
    if universe.size == 0:
        return 0
    columns = [v for v in range(num_views) if not case >> v & 1]
    m = len(columns)
    values = naive_solve(naive_model(universe, columns, [1.0] * m, None, False), time_limit)
    if values is None:
        return None
    size = round(sum(values))
    weights = [float(2 ** (m - 1 - rank)) for rank in range(m)]
    values = naive_solve(naive_model(universe, columns, weights, size, True), time_limit)
    if values is None:
        return None
    return sum(1 << v for v, x in zip(columns, values, strict=True) if x > 0.5)


# ---------------------------------------------------------------------------------------------------------
# Classic greedy set cover on the keys of U
# ---------------------------------------------------------------------------------------------------------


def greedy_size(masks: np.ndarray, case: int, num_views: int) -> int:
    """Classic greedy on U's keys: the view covering most uncovered keys, ties to the lowest view."""
    universe = masks[(masks & np.uint64(case)) == 0]
    distinct, weight = np.unique(universe, return_counts=True)
    bits = ((distinct[:, None] >> np.arange(num_views, dtype=np.uint64)[None, :]) & np.uint64(1)).astype(np.int64)
    open_weight = weight.astype(np.int64)
    size = 0
    while open_weight.any():
        best = int(np.argmax(open_weight @ bits))
        open_weight = open_weight * (bits[:, best] == 0)
        size += 1
    return size


# ---------------------------------------------------------------------------------------------------------
# Per-mesh data
# ---------------------------------------------------------------------------------------------------------


@dataclass
class AlphaStats:
    ours: list[float] = field(default_factory=list)
    ours_on_naive: list[float] = field(default_factory=list)
    naive: list[float] = field(default_factory=list)
    naive_failed: int = 0
    naive_mismatch: list[str] = field(default_factory=list)
    setup: list[float] = field(default_factory=list)
    sizes: Counter[int] = field(default_factory=Counter)
    proofs: Counter[str] = field(default_factory=Counter)
    greedy_worse: int = 0
    greedy_excess: Counter[int] = field(default_factory=Counter)
    rows_before: list[int] = field(default_factory=list)
    rows_after: list[int] = field(default_factory=list)
    per_mesh: dict[str, list[float]] = field(default_factory=dict)


def mesh_views(path: Path, config: GenerationConfig) -> tuple[list[np.ndarray], list[int], float]:
    """P_i (refiner none, filtered to P_gt) and the long-tail cases of task (mesh, rotation 0)."""
    started = time.perf_counter()
    spec = mesh_file_spec(path, ObjectOptions(size=SIZE_M))
    prepared = prepare_object(spec, config)
    scan = scan_task(prepared, 0, config, build_view_space(config.view_space))
    observations = list(scan.observations)
    refiner = make_refiner(config)
    requests = [RefineRequest(o, config.seed, spec.object_id, 0) for o in observations]
    refined = [refined_keys(o, r) for o, r in zip(observations, refiner.refine(requests), strict=True)]
    per_view = filter_to_ground_truth(refined, scan.ground_truth.keys)
    cases = long_tail_cases(scan.visible_keys(), stream(config.seed, spec.object_id, 0, Purpose.CASES))
    return per_view, cases, time.perf_counter() - started


def ms(seconds: float) -> str:
    return f"{seconds * 1e3:.2f}"


def quantiles(values: list[float]) -> tuple[float, float, float]:
    if not values:
        return float("nan"), float("nan"), float("nan")
    array = np.asarray(values)
    return float(np.median(array)), float(np.percentile(array, 99)), float(array.max())


def format_table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(c.ljust(widths[i]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(header))]
    lines.append("  ".join("-" * w for w in widths))
    for row in rows:
        lines.append("  ".join(c.ljust(widths[i]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(row)))
    return "\n".join(lines)


def parse_strides(items: list[str], alphas: list[int]) -> dict[int, int]:
    strides = {a: DEFAULT_NAIVE_STRIDE.get(a, 1) for a in alphas}
    for item in items:
        alpha, _, stride = item.partition("=")
        strides[int(alpha)] = int(stride)
    return strides


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", type=Path, default=REPO_ROOT.parent / "shared" / "meshes")
    parser.add_argument("--alphas", type=int, nargs="+", default=list(DEFAULT_ALPHAS))
    parser.add_argument(
        "--naive-stride", nargs="*", default=[], metavar="ALPHA=S", help="naive model on every S-th case"
    )
    parser.add_argument("--naive-time-limit", type=float, default=NAIVE_TIME_LIMIT)
    args = parser.parse_args()
    meshes = sorted(p for p in args.meshes.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if not meshes:
        print(f"no meshes in {args.meshes}", file=sys.stderr)
        return 1
    strides = parse_strides(args.naive_stride, args.alphas)
    base = GenerationConfig(imaging="targets", refiner="none")
    stats = {alpha: AlphaStats() for alpha in args.alphas}
    counters = dict.fromkeys(args.alphas, 0)
    begun = time.perf_counter()
    imaging_seconds = 0.0
    total_cases = 0
    for path in meshes:
        per_view, cases, seconds = mesh_views(path, base)
        imaging_seconds += seconds
        total_cases += len(cases)
        print(f"{path.name}: {len(cases)} cases, imaging + cases {seconds:.2f} s", file=sys.stderr, flush=True)
        for alpha in args.alphas:
            config = base.model_copy(update={"alpha": alpha})
            s = stats[alpha]
            coverage = coverage_table(per_view, alpha)
            started = time.perf_counter()
            solver = TaskCover(coverage.masks, config.num_views, config.solver_time_limit)
            s.setup.append(time.perf_counter() - started)
            mesh_times = s.per_mesh.setdefault(path.name, [])
            for case in cases:
                started = time.perf_counter()
                result: CoverResult = solver.label(case)
                elapsed = time.perf_counter() - started
                s.ours.append(elapsed)
                mesh_times.append(elapsed)
                s.sizes[result.objective] += 1
                s.proofs[result.proof] += 1
                s.rows_before.append(result.rows_before)
                s.rows_after.append(result.rows_after)
                excess = greedy_size(coverage.masks, case, config.num_views) - result.objective
                if excess > 0:
                    s.greedy_worse += 1
                    s.greedy_excess[excess] += 1
                take_naive = counters[alpha] % strides[alpha] == 0
                counters[alpha] += 1
                if not take_naive:
                    continue
                started = time.perf_counter()
                naive = naive_label(coverage.masks, case, config.num_views, args.naive_time_limit)
                naive_elapsed = time.perf_counter() - started
                s.naive.append(naive_elapsed)
                s.ours_on_naive.append(elapsed)
                if naive is None:
                    s.naive_failed += 1
                elif naive != result.label:
                    s.naive_mismatch.append(f"{path.name} case {case:#x}: ours {result.views} naive {naive:#x}")
    total = time.perf_counter() - begun

    print()
    print(
        f"Labels on {len(meshes)} meshes of {args.meshes} (size {SIZE_M} m, rotation 0, refiner none, targets), "
        f"{total_cases} long-tail cases per alpha; run {total:.0f} s (imaging + cases {imaging_seconds:.0f} s)."
    )
    print("ours = TaskCover.label (incl. tie-break); naive = one row per key, MIP + weighted tie-break MIP.")
    print("Ratio columns: naive / ours on the naive subsample (same cases); 'sum' compares total time.")
    print()
    header = [
        "alpha", "labels", "ours med ms", "ours p99 ms", "ours max ms", "setup ms/task",
        "naive cases", "naive med ms", "naive p99 ms", "med ratio", "sum ratio", "naive fail/mismatch",
    ]  # fmt: skip
    rows = []
    for alpha in args.alphas:
        s = stats[alpha]
        om, op, ox = quantiles(s.ours)
        nm, np99, _ = quantiles(s.naive)
        sub_median = quantiles(s.ours_on_naive)[0]
        stride_note = "all" if strides[alpha] == 1 else f"1/{strides[alpha]}"
        rows.append(
            [
                str(alpha),
                str(len(s.ours)),
                ms(om),
                ms(op),
                ms(ox),
                ms(float(np.mean(s.setup))),
                f"{len(s.naive)} ({stride_note})",
                ms(nm),
                ms(np99),
                f"{nm / sub_median:.1f}x",
                f"{sum(s.naive) / sum(s.ours_on_naive):.1f}x",
                f"{s.naive_failed}/{len(s.naive_mismatch)}",
            ]
        )
    print(format_table(header, rows))
    print()
    header = ["alpha", "U rows med/max", "reduced rows med/max", "proofs", "greedy > optimum", "greedy excess"]
    rows = []
    for alpha in args.alphas:
        s = stats[alpha]
        proofs = " ".join(f"{k}:{v}" for k, v in sorted(s.proofs.items()))
        excess = " ".join(f"+{k}:{v}" for k, v in sorted(s.greedy_excess.items())) or "-"
        rows.append(
            [
                str(alpha),
                f"{int(np.median(s.rows_before))}/{max(s.rows_before)}",
                f"{int(np.median(s.rows_after))}/{max(s.rows_after)}",
                proofs,
                f"{s.greedy_worse}/{len(s.ours)} ({100 * s.greedy_worse / len(s.ours):.1f}%)",
                excess,
            ]
        )
    print(format_table(header, rows))
    print()
    print("Label-size distribution (size:count):")
    for alpha in args.alphas:
        print(f"  alpha {alpha:>2}: " + " ".join(f"{k}:{v}" for k, v in sorted(stats[alpha].sizes.items())))
    print()
    header = ["mesh", *[f"a={a} med/p99 ms" for a in args.alphas]]
    rows = []
    for path in meshes:
        cells = []
        for alpha in args.alphas:
            m, p, _ = quantiles(stats[alpha].per_mesh[path.name])
            cells.append(f"{ms(m)}/{ms(p)}")
        rows.append([path.name, *cells])
    print("Ours per mesh:")
    print(format_table(header, rows))
    for alpha in args.alphas:
        for line in stats[alpha].naive_mismatch[:5]:
            print(f"naive mismatch (alpha {alpha}): {line}")
    if TARGET_ALPHA in stats:
        s = stats[TARGET_ALPHA]
        om, op, _ = quantiles(s.ours)
        ratio = quantiles(s.naive)[0] / quantiles(s.ours_on_naive)[0]
        sum_ratio = sum(s.naive) / sum(s.ours_on_naive)
        print()
        print(f"Targets at alpha {TARGET_ALPHA}:")
        print(f"  median {ms(om)} ms <= {ms(TARGET_MEDIAN_S)} ms: {'PASS' if om <= TARGET_MEDIAN_S else 'FAIL'}")
        print(f"  p99 {ms(op)} ms <= {ms(TARGET_P99_S)} ms: {'PASS' if op <= TARGET_P99_S else 'FAIL'}")
        print(
            f"  speed-up over naive {ratio:.1f}x (median), {sum_ratio:.1f}x (total) >= {TARGET_SPEEDUP:.0f}x: "
            f"{'PASS' if min(ratio, sum_ratio) >= TARGET_SPEEDUP else 'FAIL'}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
