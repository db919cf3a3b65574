"""Next-best-view checkpoints alone, as ensembles and as weight soups, on the validation objects (issue 49).

    python -m studies.planners.real_objects.ensemble_val WORK/real-val-none CKPT [CKPT ...] \\
        [--out studies/planners/real_objects/results/ensemble-val.md --replace]

Each checkpoint is scored on every sample of the dataset by the selection figure of the next-view
targets, the chosen view's gain ratio (what the highest-scored open view sees of what the best one
would; `osvp.train.next_view_figures`), and every pair and larger group of them as an ensemble: the
mean over its members of each one's softmax over the open views (a member's scores say which open
view is best, so each is normalised over those before they are averaged). A soup (`osvp soup`) is one
network; give its file as a checkpoint to set it beside the ensemble of its ingredients.
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
from osvp.checkpoint import Checkpoint, load_checkpoint
from osvp.data import SampleBank
from osvp.loss import is_next_view
from osvp.train import TrainOptions, case_fields, next_view_figures, predict_rows

from benchmarks.common import add_report_options, check_report
from studies.planners.runs import write_markdown

BATCH = 64


def open_softmax(
    probabilities: npt.NDArray[np.float32], view_state: npt.NDArray[np.float32]
) -> npt.NDArray[np.float64]:
    """Each row's softmax over its open views of the logits behind ``probabilities`` (sigmoids); 0 elsewhere."""
    p = np.clip(probabilities.astype(np.float64), 1e-12, 1 - 1e-12)
    logits = np.where(view_state < 0.5, np.log(p) - np.log1p(-p), -np.inf)
    logits -= logits.max(axis=1, keepdims=True)
    weights = np.exp(logits)
    return weights / weights.sum(axis=1, keepdims=True)


def checkpoint_probabilities(checkpoint: Checkpoint, bank: SampleBank) -> npt.NDArray[np.float32]:
    """The checkpoint's probabilities on every sample, resampled as its own validation did."""
    stored = checkpoint.training["options"]
    options = TrainOptions(
        data=bank.url,
        out=Path("."),
        batch_size=BATCH,
        seed=int(stored["seed"]),
        target=checkpoint.target,
        network=checkpoint.architecture.name,
        preset=checkpoint.preset.name,
        lambda_=float(stored["lambda_"]),
    )
    rows = np.arange(len(bank), dtype=np.int64)
    _, probabilities = predict_rows(checkpoint.network(), bank, rows, checkpoint.num_points, options)
    return probabilities


def score_rows(bank: SampleBank, named: dict[str, npt.NDArray[np.float32]]) -> list[tuple[str, float, float]]:
    """(members, chosen gain ratio, best-view accuracy) of each checkpoint and of each group of two or more."""
    rows = np.arange(len(bank), dtype=np.int64)
    state = bank.view_state
    soft = {name: open_softmax(p, state) for name, p in named.items()}
    found = []
    for size in range(1, len(named) + 1):
        for group in itertools.combinations(sorted(named), size):
            mean = np.mean([soft[name] for name in group], axis=0).astype(np.float32)
            figures = next_view_figures(bank, rows, named[group[0]] if size == 1 else mean, "near_best")
            found.append((" + ".join(group), figures["chosen_gain_ratio"], figures["best_view_accuracy"]))
    return found


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", help="the validation dataset (every sample is scored)")
    parser.add_argument("checkpoints", nargs="+", help="next-best-view checkpoints; NAME=FILE names a row")
    add_report_options(parser)
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    loaded: dict[str, Checkpoint] = {}
    for given in args.checkpoints:
        name, sep, path = given.partition("=")
        loaded[name if sep else Path(given).parent.name or given] = load_checkpoint(path if sep else given)
    for name, checkpoint in loaded.items():
        if not is_next_view(checkpoint.target):
            parser.error(f"{name}: target {checkpoint.target!r} is not a next-view target")
    fields = tuple(sorted({field for c in loaded.values() for field in case_fields(c.architecture)}))
    bank = SampleBank.load(args.data, "points", fields=fields)
    named = {name: checkpoint_probabilities(checkpoint, bank) for name, checkpoint in loaded.items()}
    lines = [
        f"# Checkpoints, ensembles and soups on `{Path(args.data).name}` ({len(bank)} samples)",
        "",
        "| members | chosen gain ratio | best-view accuracy |",
        "|---|---:|---:|",
    ]
    lines += [f"| {members} | {ratio:.4f} | {accuracy:.4f} |" for members, ratio, accuracy in score_rows(bank, named)]
    print("\n".join(lines))
    if args.out is not None:
        write_markdown(args.out, "studies.planners.real_objects.ensemble_val", argv, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
