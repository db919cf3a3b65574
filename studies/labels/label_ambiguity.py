"""Benchmark: how many minimum covers each label is chosen from, and what listing them costs.

    python -m studies.labels.label_ambiguity --data URL [--tasks 40] [--seed 0]

A label is the lexicographically smallest of the minimum covers of U(S); when a case admits many, a
network that predicts *another* minimum cover (covering just as much with just as few views) still
scores a low F1 against the stored one. For a seeded sample of committed tasks, every stored case is
labelled again from the shard's own sets (P_i, alpha: the generator's code path) twice in the same
run: labels alone (the baseline, what schema version 1 paid) and labels with every minimum cover
listed (`label_cover_cap`, schema version 2). Printed:

- per label, the seconds of both (median, p99, max) and their ratio: the labels budget is p99 <= 0.5 s
  and median <= 20 ms per label at alpha 10;
- the share of labels whose minimum cover is unique, the median / mean count, how many counts are
  lower bounds (past the cap), by case size;
- the F1 (micro-averaged over view bits, as `osvp eval`) of a planner that returns one of a case's
  minimum covers uniformly at random, against the stored label: the score of a perfect "any minimum
  cover" planner, with the stored label itself at 1.0. Exact where the count is exact; over the listed
  covers otherwise.
"""

from __future__ import annotations

from benchmarks.common import limit_threads

limit_threads()

import argparse  # noqa: E402
import time  # noqa: E402
from collections import defaultdict  # noqa: E402

import numpy as np  # noqa: E402
import numpy.typing as npt  # noqa: E402

import storage  # noqa: E402
from datagen.pipeline.coverage import coverage_table  # noqa: E402
from datagen.pipeline.keys import pack_keys  # noqa: E402
from datagen.pipeline.objectives import cover_solver  # noqa: E402
from schemas.shard import MASKS, VIEW_STATE_COLUMN  # noqa: E402


def expected_bits(label: int, covers: tuple[int, ...]) -> tuple[float, float, float]:
    """Expected (true positives, false positives, false negatives) of a uniformly chosen cover."""
    tp = fp = fn = 0.0
    for cover in covers:
        tp += (cover & label).bit_count()
        fp += (cover & ~label).bit_count()
        fn += (label & ~cover).bit_count()
    n = len(covers)
    return tp / n, fp / n, fn / n


def timed_labels(solver, cases: list[int]) -> tuple[list, list[float]]:  # type: ignore[no-untyped-def]
    results, seconds = [], []
    for case in cases:
        started = time.perf_counter()
        results.append(solver.label(case))
        seconds.append(time.perf_counter() - started)
    return results, seconds


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", required=True)
    parser.add_argument("--tasks", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    dataset = storage.open_dataset(args.data)
    config = dataset.info.config
    records = storage.committed_tasks(dataset.location)
    rng = np.random.default_rng(args.seed)
    chosen = sorted(rng.choice(len(records), size=min(args.tasks, len(records)), replace=False).tolist())
    alone: list[float] = []
    listed: list[float] = []
    counts: dict[int, list[int]] = defaultdict(list)
    capped: dict[int, int] = defaultdict(int)
    bits: dict[int, npt.NDArray[np.float64]] = defaultdict(lambda: np.zeros(3))
    for index in chosen:
        record = records[index]
        shard = storage.ShardReader(dataset.location, record.shard)
        refined_keys, offsets = shard.array("refined_keys"), shard.array("refined_offsets")
        packed = pack_keys(refined_keys)
        refined = [packed[offsets[v] : offsets[v + 1]] for v in range(config.num_views)]
        masks = coverage_table(refined, config.alpha).masks
        cases = [int(c) for c in shard.array(MASKS)[:, VIEW_STATE_COLUMN]]
        labels, seconds_alone = timed_labels(cover_solver(masks, config, list_covers=False), cases)
        results, seconds_listed = timed_labels(cover_solver(masks, config), cases)
        alone += seconds_alone
        listed += seconds_listed
        for case, label, result in zip(cases, labels, results, strict=True):
            assert result.label == label.label, f"{record.task_id}: listing the covers changed a label"
            if not label.label:
                continue
            found = result.ambiguity
            size = case.bit_count()
            counts[size].append(found.count)
            capped[size] += not found.exact
            bits[size] += expected_bits(label.label, found.covers)
        print(f"task {record.task_id} ({shard.attributes.object_name}): {len(cases)} labels")

    print(f"\n{args.data}: {len(chosen)} tasks, {len(alone)} labels, alpha {config.alpha}, refiner {config.refiner}")
    print(f"cover cap {config.label_cover_cap}\n")
    print("| seconds per label | median | p99 | max |\n|---|---|---|---|")
    for name, values in (("labels alone (baseline)", alone), ("labels + every minimum cover", listed)):
        found = np.asarray(values)
        print(f"| {name} | {np.median(found):.4f} | {np.percentile(found, 99):.4f} | {found.max():.4f} |")
    ratio = np.median(listed) / np.median(alone), np.percentile(listed, 99) / np.percentile(alone, 99)
    print(f"| ratio | {ratio[0]:.2f} | {ratio[1]:.2f} | |\n")
    print("| case size | labels | unique min cover | median covers | mean covers | capped | F1 of a random min cover |")
    print("|---|---|---|---|---|---|---|")
    every, total, all_capped = [], np.zeros(3), 0
    for size in sorted(counts):
        found = np.asarray(counts[size])
        every.extend(found.tolist())
        total += bits[size]
        all_capped += capped[size]
        print(row(str(size), found, capped[size], bits[size]))
    print(row("all", np.asarray(every), all_capped, total))


def row(name: str, found: npt.NDArray[np.int64], capped: int, bits: npt.NDArray[np.float64]) -> str:
    tp, fp, fn = bits
    f1 = f"{2 * tp / (2 * tp + fp + fn):.3f}" if tp + fp + fn else "-"
    unique = float(np.mean(found == 1)) if found.size else 0.0
    median = float(np.median(found)) if found.size else 0.0
    mean = float(found.mean()) if found.size else 0.0
    return f"| {name} | {found.size} | {unique:.1%} | {median:.0f} | {mean:.1f} | {capped} | {f1} |"


if __name__ == "__main__":
    main()
