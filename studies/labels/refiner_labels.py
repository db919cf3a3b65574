"""Benchmark: how each refiner changes the labels, on real watertight meshes (single-view cases).

    python -m studies.labels.refiner_labels [--objects examples/watertight-meshes.txt]
        [--refiners none,carve,poisson,poco] [--alpha 10]

For every object, rotation 0 of a config with ``rotations = 1``, every refiner runs the whole task
(`run_task`: imaging, refinement of all 32 single views and of the multi-view cases, P_full at
``alpha``, exact labels). Only the 32 single-view cases are reported: the label is the smallest set
of further views that covers P_full minus P(O_v), so "views" below counts the input view too
(|label| + 1, the paper's convention: its network predicts 5.8 +- 1.0 views).

Printed per refiner: the distribution of views, mean +- std, the share of empty labels (the one
view already covers P_full), |P_full| and the refined cloud's size over the observed one, and the
task's refinement seconds. A refiner changes both sides of the cover: P(O_v) (the input covers
more) and P_full (refined views see more keys, so more keys reach alpha).
"""

from __future__ import annotations

from benchmarks.common import REPO_ROOT, limit_threads

limit_threads()

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

from datagen.errors import DatagenError  # noqa: E402
from datagen.pipeline.objects.objects_file import read_objects_file  # noqa: E402
from datagen.pipeline.objects.prepare import prepare_object  # noqa: E402
from datagen.pipeline.refine import make_refiner  # noqa: E402
from datagen.pipeline.task import run_task  # noqa: E402
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas  # noqa: E402
from datagen.pipeline.viewspace import build_view_space  # noqa: E402
from schemas.config import GenerationConfig  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=Path, default=REPO_ROOT / "examples" / "watertight-meshes.txt")
    parser.add_argument("--refiners", default="none,carve,poisson,poco")
    parser.add_argument("--alpha", type=int, default=10)
    args = parser.parse_args()
    specs = read_objects_file(args.objects).objects
    if not specs:
        print(f"no objects in {args.objects} (are the shared meshes present?)")
        return
    refiners = [name for name in args.refiners.split(",") if name]
    sizes: dict[str, list[int]] = {name: [] for name in refiners}
    print(f"{len(specs)} objects, rotations = 1, alpha = {args.alpha}, single-view cases only")
    header = f"{'object':<12} {'refiner':<8} {'views mean':>10} {'empty':>6} {'|P_full|':>9} {'P/O':>5} {'task s':>7}"
    print(header)
    print("-" * len(header))
    for spec in specs:
        for name in refiners:
            config = GenerationConfig(rotations=1, alpha=args.alpha, refiner=name)  # type: ignore[arg-type]
            try:
                refiner = make_refiner(config)
            except DatagenError as error:
                print(f"{spec.name:<12} {name:<8} skipped: {error}")
                continue
            started = time.perf_counter()
            with single_threaded_blas(), fixed_torch_threads():
                prepared = prepare_object(spec, config)
                result = run_task(prepared, 0, config, build_view_space(config.view_space), refiner)
            seconds = time.perf_counter() - started
            singles = [s for s in result.samples if s.case.bit_count() == 1]
            views = [s.label.bit_count() + 1 for s in singles]
            sizes[name].extend(views)
            growth = statistics.mean(s.points.size / max(1, s.observed.size) for s in singles)
            empty = sum(1 for s in singles if s.empty_label)
            print(
                f"{spec.name[:12]:<12} {name:<8} {statistics.mean(views):>10.2f} {empty:>6} "
                f"{singles[0].full_size:>9} {growth:>5.2f} {seconds:>7.1f}",
                flush=True,
            )
    print()
    print("views per single-view case (input view included), all objects:")
    every = sorted({v for values in sizes.values() for v in values})
    print(f"{'refiner':<8} " + " ".join(f"{v:>4}" for v in every) + f" {'mean +- std':>14}")
    for name, values in sizes.items():
        if not values:
            continue
        counts = Counter(values)
        spread = statistics.pstdev(values)
        print(
            f"{name:<8} "
            + " ".join(f"{counts.get(v, 0):>4}" for v in every)
            + f" {statistics.mean(values):>7.2f} +- {spread:.2f}"
        )


if __name__ == "__main__":
    main()
