"""Benchmark: how many input cases the long-tail sampling draws per task (docs/pipeline.md section 6).

    python -m benchmarks.generation.cases [--meshes DIR] [--seed 0]

For every mesh of DIR (default ../shared/meshes), prepared at size 0.15 m, rotation 0, and for both
imaging modes, it runs the whole task (`datagen.pipeline.task.run_task`, refiner none, default config) and
prints:

- cases: the number of drawn cases (32 singletons + the multi-view cases);
- per size: the number of cases of each size m = 1, 2, ... (as ``m:count``);
- G[1]: the total gain of the trajectories' second views (the normaliser of need(m));
- |V|: the number of keys of the union of all V_i;
- scan s / task s: the scan (P_gt + imaging) and the whole task (scan + refine + label), seconds.

Single-threaded (OPENBLAS/OMP threads 1, solver threads 1).
"""

from __future__ import annotations

from benchmarks.common import SHARED_MESHES, limit_threads

limit_threads()

import argparse  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from datagen.pipeline.cases import greedy_trajectories  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.objects.spec import ObjectOptions, ObjectSpec, mesh_file_spec  # noqa: E402
from datagen.pipeline.refine import make_refiner  # noqa: E402
from datagen.pipeline.task import run_task  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402

MESH_SUFFIXES = {".obj", ".ply", ".stl", ".off", ".glb"}
SIZE_M = 0.15
MODES = ("targets", "pixels")


def mesh_spec(path: Path) -> ObjectSpec:
    return mesh_file_spec(path, ObjectOptions(size=SIZE_M))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", type=Path, default=SHARED_MESHES)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    paths = sorted(p for p in args.meshes.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if not paths:
        raise SystemExit(f"no meshes in {args.meshes}")

    header = f"{'mesh':<16} {'imaging':<8} {'cases':>5} {'G[1]':>7} {'|V|':>7} {'scan s':>7} {'task s':>7}  per size"
    print(header)
    print("-" * len(header))
    totals: dict[str, list[int]] = {mode: [] for mode in MODES}
    for path in paths:
        spec = mesh_spec(path)
        for mode in MODES:
            config = GenerationConfig(imaging=mode, seed=args.seed)
            view_space = build_view_space(config.view_space)
            prepared = prepare_object(spec, config)
            started = time.perf_counter()
            result = run_task(prepared, 0, config, view_space, make_refiner(config))
            seconds = time.perf_counter() - started
            trajectories = greedy_trajectories(result.sets.visible)
            union = np.unique(np.concatenate(result.sets.visible)).size
            sizes = Counter(case.bit_count() for case in result.cases)
            per_size = " ".join(f"{m}:{sizes[m]}" for m in sorted(sizes))
            totals[mode].append(len(result.cases))
            print(
                f"{path.stem:<16} {mode:<8} {len(result.cases):>5} {int(trajectories.gains[1]):>7} "
                f"{union:>7} {result.seconds['scan']:>7.2f} {seconds:>7.2f}  {per_size}",
                flush=True,
            )
    print()
    for mode in MODES:
        counts = totals[mode]
        print(f"{mode:<8} cases per task: min {min(counts)}, median {int(np.median(counts))}, max {max(counts)}")


if __name__ == "__main__":
    main()
