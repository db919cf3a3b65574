"""``osvp train | eval | sweep-lambda``: train the one-shot view planner on a datagen dataset.

Every user error (a missing or damaged dataset, a checkpoint that does not fit, a bad option) is one
``error:`` line on stderr and exit code 2; progress goes to stderr, results to stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from osvp.checkpoint import load_checkpoint
from osvp.data import DataError, SampleBank, split_rows
from osvp.loss import DEFAULT_LAMBDA
from osvp.metrics import SetMetrics
from osvp.network import PRESETS
from osvp.prior import ViewStatePrior
from osvp.train import EpochReport, TrainOptions, evaluate_rows, train
from schemas.errors import DatagenError

PAPER_LAMBDAS = (0.75, 1.0, 1.25, 1.5, 1.75, 2.0)
EXIT_USER_ERROR = 2


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        return int(args.run(args))
    except DatagenError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="osvp", description=__doc__.splitlines()[0] if __doc__ else None)
    commands = parser.add_subparsers(required=True, metavar="COMMAND")

    def common(sub: argparse.ArgumentParser) -> None:
        sub.add_argument("--data", required=True, help="dataset URL or path (written by datagen)")
        sub.add_argument("--batch-size", type=int, default=32)
        sub.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N")
        sub.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")

    def training(sub: argparse.ArgumentParser) -> None:
        common(sub)
        sub.add_argument("--out", type=Path, required=True, help="folder for checkpoints, metrics.csv, curves.png")
        sub.add_argument("--preset", choices=sorted(PRESETS), default="small")
        sub.add_argument("--epochs", type=int, default=30)
        sub.add_argument("--lr", type=float, default=None, help="AdamW learning rate (default: the preset's)")
        sub.add_argument("--seed", type=int, default=0)
        sub.add_argument("--split", choices=("samples", "objects"), default="samples")
        sub.add_argument("--val-fraction", type=float, default=0.2)
        sub.add_argument("--source", choices=("points", "observed"), default="points")
        sub.add_argument("--resume", action="store_true", help="continue the run in --out from its last epoch")

    train_cmd = commands.add_parser("train", help="train a planner; best.pt holds the best validation F1")
    training(train_cmd)
    train_cmd.add_argument("--lambda", dest="lambda_", type=float, default=DEFAULT_LAMBDA, help="SCLoss weight of 1s")
    train_cmd.set_defaults(run=_train)

    eval_cmd = commands.add_parser("eval", help="precision, recall, F1 and exact-set accuracy of a checkpoint")
    common(eval_cmd)
    eval_cmd.add_argument("--checkpoint", type=Path, required=True)
    eval_cmd.add_argument(
        "--split",
        choices=("all", "train", "val"),
        default="all",
        help="'val': the run's validation samples; 'train': the samples it trained on (the paper's validation "
        "is drawn from those)",
    )
    eval_cmd.add_argument("--points", type=int, default=None, help="points per cloud (must be the checkpoint's)")
    eval_cmd.add_argument("--json", action="store_true")
    eval_cmd.set_defaults(run=_eval)

    sweep_cmd = commands.add_parser("sweep-lambda", help="train one planner per lambda: the paper's Table I")
    training(sweep_cmd)
    sweep_cmd.add_argument("--lambdas", default=",".join(str(v) for v in PAPER_LAMBDAS))
    sweep_cmd.set_defaults(run=_sweep)
    return parser


def _options(args: argparse.Namespace, out: Path, lambda_: float, resume: bool) -> TrainOptions:
    return TrainOptions(
        data=args.data,
        out=out,
        preset=args.preset,
        lambda_=lambda_,
        epochs=args.epochs,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        device=args.device,
        seed=args.seed,
        split=args.split,
        val_fraction=args.val_fraction,
        source=args.source,
        resume=resume,
    )


def _load(url: str, source: str = "points") -> SampleBank:
    started = time.perf_counter()
    bank = SampleBank.load(url, source, progress=_bar("reading samples"))  # type: ignore[arg-type]
    seconds = time.perf_counter() - started
    _clear()
    _note(f"read {len(bank)} samples in {seconds:.1f} s ({len(bank) / max(seconds, 1e-9):.0f} samples/s)")
    return bank


def _train(args: argparse.Namespace) -> int:
    options = _options(args, args.out, args.lambda_, args.resume)
    options.check()
    bank = _load(args.data, args.source)
    outcome = train(options, on_epoch=_epoch_line, on_batch=_bar("training"), bank=bank)
    _note(f"best validation F1 {outcome.best_f1:.4f} at epoch {outcome.best_epoch}; {args.out / 'best.pt'}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    checkpoint = load_checkpoint(args.checkpoint)
    bank = _load(args.data, checkpoint.source)
    checkpoint.require(bank.num_views, args.points)
    stored = checkpoint.training["options"]
    same_data = checkpoint.training["config_hash"] == bank.config_hash
    if args.split != "all" and not same_data:
        raise DataError(
            f"--split {args.split} needs the dataset {checkpoint.path} was trained on; give it or use --split all"
        )
    train_rows, val_rows = split_rows(bank, stored["split"], stored["val_fraction"], stored["seed"])
    rows = {"all": np.arange(len(bank), dtype=np.int64), "train": train_rows, "val": val_rows}[args.split]
    options = TrainOptions(
        data=args.data,
        out=Path("."),
        lambda_=float(stored["lambda_"]),
        batch_size=args.batch_size,
        device=args.device,
        seed=int(stored["seed"]),
    )
    loss, metrics = evaluate_rows(checkpoint.network(args.device), bank, rows, checkpoint.num_points, options)
    # The prior is fitted on the run's own training samples when this is its dataset, else on all.
    fitted_on = train_rows if same_data else np.arange(len(bank), dtype=np.int64)
    prior = ViewStatePrior.fit(bank.view_state[fitted_on], bank.labels[fitted_on], options.lambda_)
    baseline = SetMetrics()
    baseline.add(torch.from_numpy(prior.probabilities(bank.view_state[rows])), torch.from_numpy(bank.labels[rows]))
    result = {"samples": len(rows), "loss": loss, **metrics.as_dict(), "view_state_prior": baseline.as_dict()}
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print("| planner | samples | precision | recall | F1 | exact set | SCLoss |\n|---|---|---|---|---|---|---|")
        for name, scores, value in (("network", metrics, f"{loss:.4f}"), ("view-state prior", baseline, "-")):
            print(
                f"| {name} | {len(rows)} | {scores.precision:.4f} | {scores.recall:.4f} | {scores.f1:.4f} | "
                f"{scores.exact_accuracy:.4f} | {value} |"
            )
    return 0


def _sweep(args: argparse.Namespace) -> int:
    try:
        lambdas = [float(v) for v in args.lambdas.split(",")]
    except ValueError:
        raise DataError(f"--lambdas {args.lambdas!r}: give numbers separated by commas, e.g. 0.75,1.25") from None
    bank = _load(args.data, args.source)
    rows = []
    for lambda_ in lambdas:
        out = args.out / f"lambda-{lambda_:g}"
        resume = (out / "last.pt").exists()
        options = _options(args, out, lambda_, resume)
        done = load_checkpoint(out / "last.pt").epoch if resume else 0
        _note(f"lambda {lambda_:g}: {out}" + (f" (resuming after epoch {done})" if resume else ""))
        outcome = train(options, on_epoch=_epoch_line, on_batch=_bar("training"), bank=bank)
        best = outcome.history[outcome.best_epoch - 1]
        rows.append((lambda_, best["recall"], best["precision"], best["f1"], outcome.best_epoch))
    print("| lambda | recall | precision | F1 | best epoch |\n|---|---|---|---|---|")
    for lambda_, recall, precision, f1, epoch in rows:
        print(f"| {lambda_:g} | {recall:.4f} | {precision:.4f} | {f1:.4f} | {epoch} |")
    return 0


def _epoch_line(report: EpochReport) -> None:
    row = report.row
    _clear()
    _note(
        f"epoch {report.epoch}/{report.epochs}: loss {row['train_loss']:.4f} val {row['val_loss']:.4f} "
        f"P {row['precision']:.3f} R {row['recall']:.3f} F1 {row['f1']:.3f} exact {row['exact_accuracy']:.3f} "
        f"{row['seconds']:.0f} s, {row['train_samples_per_s']:.0f} samples/s"
        f" (loader {row['loader_samples_per_s']:.0f}/s)" + (" *best" if report.best else "")
    )


def _bar(label: str) -> Callable[..., None]:
    def show(done: int, total: int, loss: float | None = None) -> None:
        if not sys.stderr.isatty():
            return
        width = 30
        filled = int(width * done / max(total, 1))
        extra = f" loss {loss:.4f}" if loss is not None else ""
        sys.stderr.write(f"\r{label} [{'#' * filled}{'.' * (width - filled)}] {done}/{total}{extra}  ")
        sys.stderr.flush()

    return show


def _clear() -> None:
    if sys.stderr.isatty():
        sys.stderr.write("\r" + " " * 100 + "\r")


def _note(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
