"""``osvp train | eval | ship | soup | sweep-lambda``: train the one-shot view planner on a datagen dataset.

Every user error (a missing or damaged dataset, a checkpoint that does not fit, a bad option) is one
``error:`` line on stderr and exit code 2; progress goes to stderr, results to stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from osvp.architectures import ARCHITECTURES, DEFAULT_ARCHITECTURE, architecture_help, preset_names
from osvp.checkpoint import Checkpoint, load_checkpoint
from osvp.data import DataError, SampleBank
from osvp.decoding import Decoding, parse_decoding
from osvp.loss import DEFAULT_LAMBDA, is_next_view, targets
from osvp.metrics import decoded_metrics
from osvp.prior import ViewStatePrior
from osvp.stream import MEMORY_LIMIT_GB, VAL_CAP, choose_streaming
from osvp.train import (
    RECIPE_LAMBDA,
    EpochReport,
    TrainOptions,
    case_fields,
    covers_needed,
    next_view_figures,
    predict_rows,
    require_next_view_data,
    run_rows,
    train,
)
from schemas.errors import DatagenError

PAPER_LAMBDAS = (0.75, 1.0, 1.25, 1.5, 1.75, 2.0)
EXIT_USER_ERROR = 2
EVAL_DECODINGS = ("threshold", "tuned", "size")
PRIOR_DECODINGS = ("threshold", "size")
SELECTION = {
    "size_cover_f1": "F1 (against the nearest minimum cover, size decoding)",
    "f1": "F1 (label bits, p > 0.5)",
    "best_view_accuracy": "best-view accuracy (the highest-scored open view is the best next view)",
    "gain_mae": "mean gain error",
    "chosen_gain_ratio": "gain ratio (what the highest-scored open view sees of what the best one would)",
}


def main(argv: Sequence[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if getattr(args, "threads", 0):
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
        sub.add_argument(
            "--network",
            choices=sorted(ARCHITECTURES),
            default=DEFAULT_ARCHITECTURE,
            help=architecture_help(),
        )
        sub.add_argument("--preset", choices=preset_names(), default="small", help="the network's size (default small)")
        sub.add_argument("--epochs", type=int, default=30)
        sub.add_argument(
            "--steps",
            type=int,
            default=None,
            help="train for about this many gradient steps instead of --epochs (epochs follow the training set's "
            "size; the learning rate halves after 80%% of them): equal optimisation for learning curves",
        )
        sub.add_argument("--lr", type=float, default=None, help="AdamW learning rate (default: the preset's)")
        sub.add_argument("--seed", type=int, default=0)
        sub.add_argument(
            "--split",
            choices=("samples", "objects"),
            default="samples",
            help="validation by held-out samples (the paper's) or held-out objects (recommended for learning curves)",
        )
        sub.add_argument("--val-fraction", type=float, default=0.2)
        sub.add_argument(
            "--val-data",
            default=None,
            help="validate on every sample of this dataset (e.g. a split's validation objects, made apart) and train "
            "on all of --data; best.pt is then chosen on objects the run never trained on",
        )
        sub.add_argument(
            "--case-balance",
            type=float,
            default=0.0,
            metavar="P",
            help="draw training samples with probability count(case size)^-P (0: each once, the default; 1: every "
            "case size alike): the long-tail cases hold few large ones, the situations a next-best-view planner "
            "meets after its first views",
        )
        sub.add_argument(
            "--mix-data",
            default=None,
            metavar="URL",
            help="draw --mix-fraction of every epoch's training samples from this dataset too (of the same view "
            "space, schema and voxel: synthetic objects beside real ones); validation never mixes",
        )
        sub.add_argument(
            "--mix-fraction",
            type=float,
            default=0.0,
            metavar="F",
            help="the share of each epoch's samples drawn from --mix-data, in (0, 1); --steps count them too",
        )
        sub.add_argument(
            "--init",
            type=Path,
            default=None,
            help="start from this checkpoint's weights (the same --network and --preset): fine-tune a planner "
            "pre-trained on other data; the optimiser and its learning rate start afresh",
        )
        sub.add_argument("--source", choices=("points", "observed"), default="points")
        sub.add_argument("--resume", action="store_true", help="continue the run in --out from its last epoch")
        sub.add_argument(
            "--target",
            choices=targets(),
            default="",
            help="loss (default: the network's best measured one, mincover for osvp and scvp, best_view for nbvnet): "
            "label is the stored label's SCLoss (the paper's); with a version-2 dataset marginal, mincover (the "
            "nearest minimum cover) or support (the label without punishing other covers' views); with a version-3 "
            "dataset gain regresses every view's gain (a PCNBV-style planner, played step by step by `datagen "
            "evaluate`: train it with --source observed, what it sees there), best_view classifies the best next "
            "view (NBVNet's) and near_best does so with credit for views that see nearly as much (soft classes)",
        )
        sub.add_argument(
            "--max-objects",
            type=int,
            default=None,
            help="train on this many of the training objects (seeded and nested: the first 10 of 20 are the 10)",
        )
        sub.add_argument(
            "--sample-fraction",
            type=float,
            default=1.0,
            help="train on this seeded, nested fraction of the training samples, in (0, 1]; validation is unchanged",
        )
        sub.add_argument(
            "--stream",
            action="store_true",
            default=None,
            help="read the training samples shard by shard every epoch instead of holding them in memory "
            "(chosen by itself when the dataset needs more than --memory-limit)",
        )
        sub.add_argument(
            "--memory-limit",
            type=float,
            default=MEMORY_LIMIT_GB,
            metavar="GB",
            help="stream when the samples would need more memory than this (estimated from the index; default "
            "%(default)g)",
        )
        sub.add_argument(
            "--fit-rows",
            type=int,
            default=0,
            help="also score this many training samples (a seeded draw) every epoch: the fit_ columns of "
            "metrics.csv, how well the network fits its own training data beside the held-out figures (default 0)",
        )
        sub.add_argument("--workers", type=int, default=2, help="DataLoader workers reading shards when streaming")
        sub.add_argument("--shuffle-buffer", type=int, default=4096, help="samples the stream mixes at once")
        sub.add_argument(
            "--val-cap",
            type=int,
            default=VAL_CAP,
            help="when streaming, validate on at most this many validation samples (a seeded draw, held in "
            "memory; 0: all)",
        )

    train_cmd = commands.add_parser(
        "train", help="train a planner; best.pt holds the best validation F1 (nearest minimum cover when known)"
    )
    training(train_cmd)
    train_cmd.add_argument(
        "--lambda",
        dest="lambda_",
        type=float,
        default=RECIPE_LAMBDA,
        help=f"SCLoss weight of 1s (default {RECIPE_LAMBDA:g}, measured best here; the paper's {DEFAULT_LAMBDA})",
    )
    train_cmd.set_defaults(run=_train)

    eval_cmd = commands.add_parser(
        "eval", help="precision, recall, F1, nearest-cover F1, covers-U share and views of a checkpoint, per decoding"
    )
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
    eval_cmd.add_argument(
        "--decoding",
        action="append",
        default=None,
        help="a decoding to report (repeatable: threshold, threshold=T, tuned, size, topk=K; "
        "default: threshold, tuned and size)",
    )
    eval_cmd.add_argument("--json", action="store_true")
    eval_cmd.set_defaults(run=_eval)

    ship_cmd = commands.add_parser(
        "ship", help="make a checkpoint a planner shipped inside osvp (slim file, training card, sha256)"
    )
    ship_cmd.add_argument("--checkpoint", type=Path, required=True, help="the run's best.pt")
    ship_cmd.add_argument("--name", required=True, help="the planner's name: shipped:NAME")
    ship_cmd.add_argument(
        "--folder", type=Path, default=None, help="where to write NAME.pt and NAME.md (default: osvp's shipped/)"
    )
    ship_cmd.add_argument(
        "--data-name",
        action="append",
        default=[],
        metavar="URL=NAME",
        help="record a dataset URL of the run under NAME (repeatable; default: its last path part)",
    )
    ship_cmd.add_argument(
        "--commands", type=Path, default=None, help="a file of the commands that made it, for the card"
    )
    ship_cmd.add_argument("--scores", type=Path, default=None, help="a Markdown file of its scores, for the card")
    ship_cmd.set_defaults(run=_ship)

    soup_cmd = commands.add_parser(
        "soup", help="average the weights of checkpoints of one network (a run and its fine-tunes) into one"
    )
    soup_cmd.add_argument("checkpoints", type=Path, nargs="+", help="two or more checkpoints of one network")
    soup_cmd.add_argument("--out", type=Path, required=True, help="the soup's checkpoint file")
    soup_cmd.set_defaults(run=_soup)

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
        network=args.network,
        lambda_=lambda_,
        epochs=args.epochs,
        steps=args.steps,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        device=args.device,
        seed=args.seed,
        split=args.split,
        val_fraction=args.val_fraction,
        source=args.source,
        resume=resume,
        target=args.target,
        max_objects=args.max_objects,
        sample_fraction=args.sample_fraction,
        stream=args.stream,
        memory_limit_gb=args.memory_limit,
        workers=args.workers,
        shuffle_buffer=args.shuffle_buffer,
        val_cap=args.val_cap,
        fit_rows=args.fit_rows,
        val_data=args.val_data,
        init=args.init,
        case_balance=args.case_balance,
        mix_data=args.mix_data,
        mix_fraction=args.mix_fraction,
    )


def _streaming(options: TrainOptions) -> bool:
    """Whether the run streams; says so in one line when it does."""
    fields = case_fields(options.architecture)
    streaming, why = choose_streaming(options.data, options.stream, options.memory_limit_gb, options.source, fields)
    if streaming:
        _note(why)
    return streaming


def _load(url: str, source: str = "points", covers_for: str | None = None, fields: Sequence[str] = ()) -> SampleBank:
    started = time.perf_counter()
    reading = _bar("reading samples")
    bank = SampleBank.load(url, source, progress=reading, covers_for=covers_for, fields=fields)  # type: ignore[arg-type]
    seconds = time.perf_counter() - started
    _clear()
    _note(f"read {len(bank)} samples in {seconds:.1f} s ({len(bank) / max(seconds, 1e-9):.0f} samples/s)")
    return bank


def _train(args: argparse.Namespace) -> int:
    options = _options(args, args.out, args.lambda_, args.resume)
    options.check()
    require_next_view_data(options)
    streaming = _streaming(options)
    fields = case_fields(options.architecture)
    bank = None if streaming else _load(args.data, args.source, covers_needed(options.target), fields)
    options = replace(options, stream=streaming)
    outcome = train(options, on_epoch=_epoch_line, on_batch=_bar("training"), bank=bank)
    figure = SELECTION[outcome.best_metric]
    _note(f"best validation {figure} {outcome.best_score:.4f} at epoch {outcome.best_epoch}; {args.out / 'best.pt'}")
    return 0


def _ship(args: argparse.Namespace) -> int:
    from osvp import shipped
    from osvp.shipping import ship

    names = {}
    for pair in args.data_name:
        url, sep, name = pair.rpartition("=")
        if not sep or not url or not name:
            raise DataError(f"--data-name {pair!r}: give URL=NAME")
        names[url] = name
    folder = args.folder or shipped.HERE
    read = {
        key: path.read_text() if path is not None else ""
        for key, path in (("commands", args.commands), ("scores", args.scores))
    }
    done = ship(args.checkpoint, folder, args.name, names, read["commands"], read["scores"])
    print(f"wrote {done.path} ({done.size / 1e6:.2f} MB) and {done.card}; sha256 {done.sha256}")
    if args.name in shipped.SHIPPED and shipped.SHIPPED[args.name].sha256 != done.sha256:
        print(f"record it in osvp/shipped/__init__.py: ShippedPlanner(name={args.name!r}, sha256={done.sha256!r})")
    return 0


def _soup(args: argparse.Namespace) -> int:
    from osvp.soup import make_soup
    from osvp.train import file_sha256

    out = make_soup(args.checkpoints, args.out)
    print(f"wrote {out}: the mean of {len(args.checkpoints)} checkpoints' weights; sha256 {file_sha256(out)}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    checkpoint = load_checkpoint(args.checkpoint)
    decodings = _decodings(args.decoding, checkpoint)
    options = _stored_options(checkpoint, args)
    bank = _load(args.data, checkpoint.source, covers_needed(checkpoint.target), case_fields(options.architecture))
    checkpoint.require(bank.num_views, args.points)
    same_data = checkpoint.training["config_hash"] == bank.config_hash
    if args.split != "all" and not same_data:
        raise DataError(
            f"--split {args.split} needs the dataset {checkpoint.path} was trained on; give it or use --split all"
        )
    if args.split == "val" and options.val_data is not None:
        raise DataError(
            f"{checkpoint.path} validated on another dataset ({options.val_data}); score it with "
            f"--data {options.val_data} --split all"
        )
    everything = np.arange(len(bank), dtype=np.int64)
    # The run's own rows on its dataset; on another one (--split all only) every sample, also for the prior.
    train_rows, val_rows = run_rows(bank, options) if same_data else (everything, everything)
    rows = {"all": everything, "train": train_rows, "val": val_rows}[args.split]
    loss, probabilities = predict_rows(checkpoint.network(args.device), bank, rows, checkpoint.num_points, options)
    covers = bank.covers.take(rows) if bank.covers is not None else None
    state, labels = bank.view_state[rows], bank.labels[rows]
    network = {d.spec: decoded_metrics(probabilities, state, labels, d, covers).as_dict() for d in decodings}
    prior = ViewStatePrior.fit(bank.view_state[train_rows], bank.labels[train_rows], options.lambda_)
    guessed = prior.probabilities(state)
    baseline = {name: decoded_metrics(guessed, state, labels, name, covers).as_dict() for name in PRIOR_DECODINGS}
    result = {
        "samples": len(rows),
        "loss": loss,
        "target": checkpoint.target,
        "default_decoding": checkpoint.decoding,
        "tuned_threshold": checkpoint.tuned_threshold,
        "decodings": network,
        "view_state_prior": baseline,
    }
    next_view: dict[str, float] = {}
    if is_next_view(checkpoint.target):  # a next-best-view planner is judged by its next view
        next_view = result["next_view"] = next_view_figures(bank, rows, probabilities, checkpoint.target)
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    if next_view:
        figures = ", ".join(f"{SELECTION.get(k, k)} {v:.4f}" for k, v in next_view.items())
        print(f"next-best-view planner ({checkpoint.target}), {len(rows)} samples: {figures}\n")
    print(
        "| planner | decoding | samples | precision | recall | F1 | exact set | nearest-cover F1 | covers U | views "
        f"| label views | {checkpoint.target} loss |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
    )
    tuned = f"tuned ({checkpoint.tuned_threshold:.2f})" if checkpoint.tuned_threshold is not None else "tuned"
    named = {"threshold": "threshold 0.5", "tuned": tuned}
    table = [("network", spec, scores, f"{loss:.4f}") for spec, scores in network.items()]
    table += [("view-state prior", spec, scores, "-") for spec, scores in baseline.items()]
    for planner, spec, scores, value in table:
        print(
            f"| {planner} | {named.get(spec, spec)} | {len(rows)} | {scores['precision']:.4f} | {scores['recall']:.4f} "
            f"| {scores['f1']:.4f} | {scores['exact_accuracy']:.4f} | {_maybe(scores, 'cover_f1')} "
            f"| {_maybe(scores, 'covers_u')} | {scores['views']:.2f} | {scores['label_views']:.2f} | {value} |"
        )
    return 0


def _decodings(asked: list[str] | None, checkpoint: Checkpoint) -> list[Decoding]:
    """The decodings ``osvp eval`` reports: those asked for, else threshold, tuned (when the
    checkpoint has a tuned threshold) and size."""
    names = asked or [n for n in EVAL_DECODINGS if n != "tuned" or checkpoint.tuned_threshold is not None]
    try:
        return [parse_decoding(name, checkpoint.tuned_threshold) for name in names]
    except ValueError as exc:
        raise DataError(f"--decoding: {exc}") from None


def _stored_options(checkpoint: Checkpoint, args: argparse.Namespace) -> TrainOptions:
    """The run's options that decide its rows, resampling and loss (defaults for older checkpoints)."""
    stored = checkpoint.training["options"]
    return TrainOptions(
        data=args.data,
        out=Path("."),
        lambda_=float(stored["lambda_"]),
        batch_size=args.batch_size,
        device=args.device,
        seed=int(stored["seed"]),
        split=stored["split"],
        val_fraction=float(stored["val_fraction"]),
        target=checkpoint.target,
        network=checkpoint.architecture.name,
        preset=checkpoint.preset.name,
        max_objects=stored.get("max_objects"),
        sample_fraction=float(stored.get("sample_fraction", 1.0)),
        val_data=stored.get("val_data"),
    )


def _maybe(scores: dict[str, float], key: str) -> str:
    """A figure only version-2 data has, or '-'."""
    return f"{scores[key]:.4f}" if key in scores else "-"


def _sweep(args: argparse.Namespace) -> int:
    try:
        lambdas = [float(v) for v in args.lambdas.split(",")]
    except ValueError:
        raise DataError(f"--lambdas {args.lambdas!r}: give numbers separated by commas, e.g. 0.75,1.25") from None
    first = _options(args, args.out, lambdas[0], False)
    streaming = _streaming(first)
    needs = covers_needed(first.target)
    bank = None if streaming else _load(args.data, args.source, needs, case_fields(first.architecture))
    rows = []
    for lambda_ in lambdas:
        out = args.out / f"lambda-{lambda_:g}"
        resume = (out / "last.pt").exists()
        options = replace(_options(args, out, lambda_, resume), stream=streaming)
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
    covers = f" cover F1 {row['cover_f1']:.3f} covers U {row['covers_u']:.3f}" if "cover_f1" in row else ""
    size = f" cover F1 {row['size_cover_f1']:.3f}" if "size_cover_f1" in row else f" F1 {row['size_f1']:.3f}"
    gains = f" best view {row['best_view_accuracy']:.3f}" if "best_view_accuracy" in row else ""
    gains += f" gain error {row['gain_mae']:.4f}" if "gain_mae" in row else ""
    gains += f" gain ratio {row['chosen_gain_ratio']:.3f}" if "chosen_gain_ratio" in row else ""
    gains += f" fit F1 {row['fit_size_cover_f1']:.3f}" if "fit_size_cover_f1" in row else ""
    gains += ";" if gains else ""
    _clear()
    _note(
        f"epoch {report.epoch}/{report.epochs}: loss {row['train_loss']:.4f} val {row['val_loss']:.4f}{gains} "
        f"P {row['precision']:.3f} R {row['recall']:.3f} F1 {row['f1']:.3f} exact {row['exact_accuracy']:.3f}"
        f"{covers} views {row['views']:.2f}/{row['label_views']:.2f}; size:{size} views {row['size_views']:.2f}; "
        f"tuned {row['tuned_threshold']:.2f}: {row['tuned_f1']:.3f}; "
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
