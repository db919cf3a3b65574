"""Coverage against views of the oracle's labels as alpha varies, per refiner (`datagen evaluate`'s
machinery; docs/guide/evaluate.md).

Each scene is imaged once and refined once per refiner; every alpha then relabels the same refined
views, so the sweep costs one refinement per scene. Comparing refiners at one alpha mixes two
things (alpha means something else when a refiner raises every key's count); comparing coverage
at equal views along this curve does not.

    python -m studies.labels.label_frontier --objects examples/watertight-meshes.txt \\
        --refiner none --refiner poco --alphas 4,6,8,10,12,14,16
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from datagen.evaluate.episode import Episode, run_episode
from datagen.evaluate.oracle import OraclePlanner
from datagen.evaluate.report import markdown_table, summarise
from datagen.evaluate.run import parse_selection, refiner_config
from datagen.evaluate.scene import build_scene
from datagen.evaluate.situation import RefinedScene, Situation
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine.factory import make_refiner
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", required=True)
    parser.add_argument("--refiner", action="append", required=True)
    parser.add_argument("--alphas", default="4,6,8,10,12,14,16")
    parser.add_argument("--rotations", default="0,4")
    parser.add_argument("--initial-views", default="0,8,16,24")
    args = parser.parse_args()
    base = GenerationConfig()
    alphas = [int(a) for a in args.alphas.split(",")]
    rotations = parse_selection(args.rotations, base.rotations, "--rotations")
    initial_views = parse_selection(args.initial_views, base.num_views, "--initial-views")
    view_space = build_view_space(base.view_space)
    started = time.perf_counter()
    episodes: list[Episode] = []
    with single_threaded_blas(), fixed_torch_threads():
        for name in args.refiner:
            config = refiner_config(base, name)
            refiner = make_refiner(config)
            for spec in read_objects_file(args.objects).objects:
                prepared = prepare_object(spec, config)
                for rotation in rotations:
                    scene = build_scene(prepared, rotation, config, view_space)
                    refined = RefinedScene(scene, refiner, config)
                    for alpha in alphas:
                        relabelled = refined.relabelled(config.model_copy(update={"alpha": alpha}))
                        for initial in initial_views:
                            run = run_episode(OraclePlanner(), Situation(relabelled, initial))
                            episodes.append(dataclasses.replace(run, refiner=f"{name} alpha={alpha:02d}"))
    print(markdown_table(summarise(sorted(episodes, key=lambda e: e.refiner))))
    print(f"{len(episodes)} runs in {time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
