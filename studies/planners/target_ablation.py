"""Benchmark: which training target and decoding make a planner that beats random views.

    python -m studies.planners.target_ablation --data URL --out DIR [--steps 12000] [--threads 2]
        [--targets label,marginal,mincover,support] [--decodings threshold,tuned,size]

For each target (the paper's SCLoss on the stored label, and each ambiguity-aware one) one `osvp
train` run (`small`, lambda 2, held-out objects for validation, the same number of gradient steps),
then for each decoding:

- on the six unseen watertight meshes (rotations 0 and 4, initial views 0, 8, 16, 24: 48 runs):
  coverage, views, movement, and the lifts over the best fixed view set of the training data and over
  random views at the planner's own view count, run by run (`fixed:match=`, `random:match=`), beside
  the dataset's own labels (`oracle`, the ceiling) and random views at the oracle's count;
- on the samples of the held-out training objects: F1 against the stored label and against the
  nearest minimum cover, and the share of predictions that cover U.

Prints one Markdown table and writes it, with every number behind it, into DIR.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from studies.planners.runs import TrainSpec, held_out, matched, pm, row_of, train, unseen


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", required=True, help="a schema-version-2 dataset (`shards relabel` adds the covers)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--steps", type=int, default=12000)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--targets", default="label,marginal,mincover,support")
    parser.add_argument("--decodings", default="threshold,tuned,size")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    targets, decodings = args.targets.split(","), args.decodings.split(",")

    checkpoints = {
        t: train(TrainSpec(f"target-{t}", target=t), args.data, args.out, args.steps, args.threads) for t in targets
    }
    samples = {t: held_out(path, args.data, decodings, args.threads) for t, path in checkpoints.items()}
    planners = ["oracle", "random"]
    for target in targets:
        for decoding in decodings:
            planners += matched(f"osvp+{decoding}:{checkpoints[target]}")
    result = unseen(planners, args.out, "unseen", fixed_from=args.data)

    lines = [
        "| target | decoding | coverage % | views | movement m | lift over fixed % | lift over random % "
        "| F1 stored label | F1 nearest cover | covers U |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name in ("oracle", "random"):
        row = row_of(result, name)
        lines.append(
            f"| {name} | - | {pm(row, 'coverage')} | {pm(row, 'views')} | {pm(row, 'movement')} | "
            f"{pm(row, 'lift_fixed')} | - | - | - | - |"
        )
    for target in targets:
        for decoding in decodings:
            row = row_of(result, f"osvp+{decoding}:{checkpoints[target]}")
            figures = samples[target]["decodings"].get(decoding, {})
            lines.append(
                f"| {target} | {decoding} | {pm(row, 'coverage')} | {pm(row, 'views')} | {pm(row, 'movement')} | "
                f"{pm(row, 'lift_fixed')} | {pm(row, 'lift')} | {_f(figures, 'f1')} | {_f(figures, 'cover_f1')} | "
                f"{_f(figures, 'covers_u')} |"
            )
    table = "\n".join(lines)
    print(table)
    (args.out / "ablation.md").write_text(table + "\n")
    (args.out / "ablation.json").write_text(json.dumps({"held_out": samples, "unseen_rows": result["rows"]}, indent=1))


def _f(figures: dict[str, Any], key: str) -> str:
    value = figures.get(key)
    return "-" if value is None else f"{value:.3f}"


if __name__ == "__main__":
    main()
