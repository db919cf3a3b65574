"""Benchmark: how many minimum covers each stored label was chosen from (what bounds a planner's F1).

    python benchmarks/label_ambiguity.py --data URL [--tasks 40] [--seed 0] [--max-size 6]

A label is the lexicographically smallest of the minimum covers of U(S). When a case admits many
minimum covers, a network that predicts *a* minimum cover, which covers just as much, still scores a
low F1 against the stored one. For a seeded sample of committed tasks, each stored case is relabelled
from the shard's own sets (P_i, alpha: the generator's code path) and every view set of the label's
size is tested against the reduced rows, which counts the minimum covers exactly. Printed:

- the share of samples whose minimum cover is unique, and the median / mean count;
- the expected F1 (micro-averaged over view bits, as `osvp eval`) of a planner that picks one of a
  case's minimum covers uniformly at random, against the stored label (a perfect "any minimum cover"
  planner's score), with the planner that predicts the stored label itself at 1.0 as the baseline;
- all by case size.

Cases whose label has more than ``--max-size`` views are skipped (counted), to bound the enumeration.
"""

from __future__ import annotations

import os

for _variable in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import itertools  # noqa: E402
from collections import defaultdict  # noqa: E402

import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402

import storage  # noqa: E402
from datagen.engine.relabel import relabel_task  # noqa: E402
from datagen.pipeline.coverage import coverage_table  # noqa: E402
from datagen.pipeline.setcover import mask_to_views, minimal_masks  # noqa: E402

CHUNK = 1 << 15


def minimum_covers(rows: npt.NDArray[np.uint64], candidates: list[int], size: int) -> list[int]:
    """Every set of ``size`` candidate views that meets every row (masks), by enumeration."""
    if size == 0:
        return [0]
    found: list[int] = []
    combos = itertools.combinations(candidates, size)
    while True:
        block = [sum(1 << v for v in combo) for combo in itertools.islice(combos, CHUNK)]
        if not block:
            return found
        masks = np.asarray(block, dtype=np.uint64)
        hit = np.ones(masks.size, dtype=bool)
        for row in rows:
            hit &= (masks & row) != 0
            if not hit.any():
                break
        found.extend(int(m) for m in masks[hit])


def expected_bits(label: int, covers: list[int], width: int) -> tuple[float, float, float]:
    """Expected (true positives, false positives, false negatives) of a uniformly chosen cover."""
    tp = fp = fn = 0.0
    for cover in covers:
        tp += (cover & label).bit_count()
        fp += (cover & ~label).bit_count()
        fn += (label & ~cover).bit_count()
    n = len(covers)
    return tp / n, fp / n, fn / n


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", required=True)
    parser.add_argument("--tasks", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-size", type=int, default=6)
    args = parser.parse_args()

    location = storage.open_location(args.data)
    info = storage.read_info(location)
    config = info.config
    records = storage.committed_tasks(location)
    rng = np.random.default_rng(args.seed)
    chosen = sorted(rng.choice(len(records), size=min(args.tasks, len(records)), replace=False).tolist())
    width = config.num_views
    counts: dict[int, list[int]] = defaultdict(list)
    bits: dict[int, np.ndarray] = defaultdict(lambda: np.zeros(3))
    skipped = 0
    for index in chosen:
        record = records[index]
        result = relabel_task(location, record, config, info.config_hash, info.config_hash)
        full = minimal_masks(coverage_table(result.sets.refined, config.alpha).masks)
        for sample in result.samples:
            size = sample.label.bit_count()
            if size > args.max_size:
                skipped += 1
                continue
            case_size = sample.case.bit_count()
            rows = full[(full & np.uint64(sample.case)) == 0]
            candidates = [v for v in range(width) if not (sample.case >> v) & 1]
            covers = minimum_covers(rows, candidates, size) if rows.size else [0]
            assert sample.label in covers, f"{record.task_id}: label {mask_to_views(sample.label)} is not a cover"
            counts[case_size].append(len(covers))
            bits[case_size] += expected_bits(sample.label, covers, width)
        print(
            f"task {record.task_id} ({result.object_name}, rotation {result.rotation}): {len(result.samples)} samples"
        )

    print(f"\n{args.data}: {len(chosen)} tasks, alpha {config.alpha}, refiner {config.refiner}; skipped {skipped}")
    print("| case size | samples | unique min cover | median covers | mean covers | F1 of a random min cover |")
    print("|---|---|---|---|---|---|")
    every, total = [], np.zeros(3)
    for case_size in sorted(counts):
        found = np.asarray(counts[case_size])
        every.extend(found.tolist())
        total += bits[case_size]
        print(row(str(case_size), found, bits[case_size]))
    print(row("all", np.asarray(every), total))


def row(name: str, found: npt.NDArray[np.int64], bits: npt.NDArray[np.float64]) -> str:
    tp, fp, fn = bits
    f1 = f"{2 * tp / (2 * tp + fp + fn):.3f}" if tp + fp + fn else "-"  # "-": every label empty
    unique = float(np.mean(found == 1)) if found.size else 0.0
    median = float(np.median(found)) if found.size else 0.0
    mean = float(found.mean()) if found.size else 0.0
    return f"| {name} | {found.size} | {unique:.1%} | {median:.0f} | {mean:.1f} | {f1} |"


if __name__ == "__main__":
    main()
