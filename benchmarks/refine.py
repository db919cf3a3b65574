"""Benchmark: seconds per single-view ``poco`` refinement on CPU, next to the imaging time per view.

    python benchmarks/refine.py [--meshes DIR] [--names cow,fandisk] [--views 0,8,16,24]
                                [--threads 2] [--weights datagen/data/poco_small.pt]

For each mesh (default: the built-ins mug and torus_knot, plus cow and fandisk from ../shared/meshes
when present), prepared at the default size (clamped into [0.05, 0.15] m), rotation 0:

- imaging s/view: `scan_task` (P_gt + 32 views) wall time / 32;
- for the shipped weights and for the ``official`` preset (random init; timing only): the median wall
  seconds of one single-view refinement (band, sensor-empty, kNN tables, encoder, decoder), the
  number of queried keys, and the carve refiner's time for comparison.

torch runs with ``--threads`` threads (2 by default, the target setting); BLAS is single-threaded.
One warm-up call per model precedes the timed ones. Target: <= 1 s per view for the shipped weights.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.refine.base import RefineRequest  # noqa: E402
from datagen.pipeline.refine.carve import CarveRefiner  # noqa: E402
from datagen.pipeline.refine.poco.checkpoint import load_checkpoint  # noqa: E402
from datagen.pipeline.refine.poco.inputs import query_keys  # noqa: E402
from datagen.pipeline.refine.poco.network import PocoModel  # noqa: E402
from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS, PocoRefiner  # noqa: E402
from datagen.pipeline.scanning import scan_task  # noqa: E402
from datagen.pipeline.thread_limits import single_threaded_blas  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", type=Path, default=ROOT.parent / "shared" / "meshes")
    parser.add_argument("--names", default="cow,fandisk")
    parser.add_argument("--builtins", default="mug,torus_knot")
    parser.add_argument("--views", default="0,8,16,24")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--weights", type=Path, default=BUILTIN_WEIGHTS)
    parser.add_argument("--no-official", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.set_flush_denormal(True)
    config = GenerationConfig()
    views = [int(v) for v in args.views.split(",")]

    lines = [f"builtin:{name}" for name in args.builtins.split(",") if name]
    for name in args.names.split(","):
        matches = sorted(args.meshes.glob(f"{name}.*")) if args.meshes.is_dir() else []
        if matches:
            lines.append(f"{matches[0]} name={name}")
    objects_file = Path("/tmp/datagen_bench_refine_objects.txt")
    objects_file.write_text("\n".join(lines) + "\n")
    specs = read_objects_file(objects_file).objects

    models = {}
    if args.weights.is_file():
        models["shipped"] = load_checkpoint(args.weights)
    else:
        print(f"(no weights at {args.weights}; skipping the shipped model)")
    if not args.no_official:
        torch.manual_seed(0)
        models["official"] = PocoModel("official").eval()
    refiners = {name: PocoRefiner(config, model, name, 0.5) for name, model in models.items()}
    carve = CarveRefiner(config)

    print(f"torch threads {torch.get_num_threads()}, views {views}")
    header = (
        f"{'object':<12} {'model':<22} {'queries':>8} {'refine s/view':>14} {'carve s/view':>13} {'imaging s/view':>15}"
    )
    print(header)
    print("-" * len(header))
    with single_threaded_blas():
        for spec in specs:
            prepared = prepare_object(spec, config)
            started = time.perf_counter()
            imaging = scan_task(prepared, 0, config, build_view_space(config.view_space))
            imaging_per_view = (time.perf_counter() - started) / len(imaging.observations)
            requests = [RefineRequest(imaging.observations[v], 0, spec.object_id, 0) for v in views]
            queries = statistics.mean(query_keys(r.observation, config)[1].size for r in requests)
            carve_times = []
            for request in requests:
                t0 = time.perf_counter()
                carve.refine([request])
                carve_times.append(time.perf_counter() - t0)
            for name, refiner in refiners.items():
                refiner.refine(requests[:1])  # warm-up
                times = []
                for request in requests:
                    t0 = time.perf_counter()
                    refiner.refine([request])
                    times.append(time.perf_counter() - t0)
                label = f"{name} ({refiner.model.preset.name})"
                print(
                    f"{spec.name:<12} {label:<22} {queries:>8.0f} {statistics.median(times):>14.3f} "
                    f"{statistics.median(carve_times):>13.3f} {imaging_per_view:>15.3f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
