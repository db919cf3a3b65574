"""Training: the OSVP network on a dataset's samples with a target loss, validated every epoch.

Deterministic on CPU for a fixed seed and thread count: the network is initialised inside a forked
torch RNG seeded from ``seed`` (never the global one), each epoch's dropout draws come from a fork
seeded by (seed, epoch), the batch order from a numpy stream (seed, epoch), and each sample's points
from `SampleBank.batch`'s own stream. So a run resumed from ``last.pt`` (written after every epoch)
continues with exactly the weights an uninterrupted run would have.

Every epoch validates on the same rows (``max_objects`` and ``sample_fraction`` only thin the
training side) with two decodings, the paper's 0.5 rule and ``size``, and picks the ``tuned``
threshold on those rows (`osvp.metrics.tune_threshold`), so each checkpoint carries the threshold
of its own weights. ``best.pt`` is the epoch with the best validation F1 against the nearest
minimum cover under the ``size`` decoding when the dataset has covers, else the best F1 against the
label bits at 0.5. A rule with nothing tuned on the rows it judges, and one that does not depend on
how a target calibrates its probabilities: a ``marginal`` network's probabilities are fractions of
covers, which 0.5 cuts almost entirely. The authors' selection reset every epoch; ours does not.

A dataset larger than ``memory_limit_gb`` (or any, with ``stream``) is streamed (`osvp.stream`): each
epoch reads the training rows shard by shard in ``workers`` DataLoader workers through a shuffle buffer
of ``shuffle_buffer`` samples, in an order fixed by (seed, epoch, workers), each cloud resampled from
the same stream (seed, epoch, row) as in memory; validation stays in memory, on at most ``val_cap`` of
the validation rows (a seeded draw). A streamed run resumed from ``last.pt`` continues exactly as well.

A run held in memory may draw a share of every epoch from a second dataset (``mix_data``,
`osvp.mixing`); ``steps`` then count the mixed-in samples too.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

import storage
from osvp.architectures import ARCHITECTURES, DEFAULT_ARCHITECTURE, Architecture, architecture
from osvp.checkpoint import VERSION as CHECKPOINT_VERSION
from osvp.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from osvp.covers import CoverBank
from osvp.curves import FIT, draw_curves, write_metrics_csv
from osvp.data import (
    Batch,
    DataError,
    SampleBank,
    Split,
    check_sample_fraction,
    require_covers,
    split_rows,
    training_subset,
)
from osvp.decoding import PAPER_THRESHOLD, Decoding
from osvp.loss import TARGET_REGISTRY, is_next_view, target_loss, targets
from osvp.metrics import decoded_metrics, tune_threshold
from osvp.mixing import MIX_STREAM, Mixture, check_fraction, check_mixable, mixed_batches
from osvp.stream import (
    MEMORY_LIMIT_GB,
    VAL_CAP,
    StreamedRows,
    cap_rows,
    choose_streaming,
    index_bank,
    open_dataset,
    rows_bank,
)

RECIPE_LAMBDA = 2.0
"""The lambda ``osvp train`` uses unless told: the recipe's, measured with ``osvp sweep-lambda``."""

LEARNING_RATES = {"paper": 1e-4, "small": 1e-3}
"""Default AdamW learning rate per preset (the authors' 1e-4 for the paper's network; the small
network trains for minutes, not days, and takes a larger step)."""

VALIDATION_EPOCH = 2**32 - 1
"""Validation clouds are resampled from this stream index, the same every epoch."""

LAST, BEST = "last.pt", "best.pt"

EPOCH_DECODINGS = {"": Decoding("threshold", PAPER_THRESHOLD), "size_": Decoding("size")}
"""The decodings validated every epoch, by the prefix of their columns."""


@dataclass(frozen=True)
class TrainOptions:
    data: str
    out: Path
    preset: str = "small"
    network: str = DEFAULT_ARCHITECTURE
    """The architecture (`osvp.architectures.ARCHITECTURES`): ``osvp``, ``nbvnet`` or ``scvp``."""
    lambda_: float = RECIPE_LAMBDA
    """SCLoss's weight of a label's 1s: 2, measured best on our sparser labels (osvp/recipe/RESULTS.md
    section 4; the paper's 1.25 is `osvp.loss.DEFAULT_LAMBDA`)."""
    epochs: int = 30
    batch_size: int = 32
    learning_rate: float | None = None
    weight_decay: float = 5e-4
    lr_step: int = 20
    """Halve the learning rate every this many epochs (the authors' StepLR)."""
    device: str = "cpu"
    seed: int = 0
    split: Split = "samples"
    val_fraction: float = 0.2
    source: Literal["points", "observed"] = "points"
    resume: bool = False
    target: str = ""
    """The loss (`osvp.loss.TARGETS`); empty: the network's default (`Architecture.default_target`,
    ``mincover`` for ``osvp``), filled in on construction. All but ``label`` need a version-2
    dataset, ``gain`` and ``best_view`` a version-3 one."""
    max_objects: int | None = None
    """Train on this many of the training side's objects (a seeded, nested draw); None: all."""
    sample_fraction: float = 1.0
    """Train on this seeded, nested fraction of the (remaining) training samples."""
    steps: int | None = None
    """Train for about this many gradient steps instead of `epochs` (see `for_samples`)."""
    stream: bool | None = None
    """Stream the training samples (True), hold them in memory (False), or choose by `memory_limit_gb`."""
    memory_limit_gb: float = MEMORY_LIMIT_GB
    """Stream when a `SampleBank` of the dataset would need more (`osvp.stream.memory_estimate`)."""
    workers: int = 2
    """DataLoader workers reading shards when streaming (the order depends on their number)."""
    shuffle_buffer: int = 4096
    """Samples the stream mixes at once."""
    val_cap: int = VAL_CAP
    """When streaming: validate on at most this many of the validation rows (a seeded draw; 0: all)."""
    fit_rows: int = 0
    """Also score this many training rows (a seeded draw) every epoch, the ``fit_`` columns: how well
    the network fits what it trains on, beside the held-out figures (0: none)."""
    val_data: str | None = None
    """Validate on every sample of this dataset (held-out objects made apart, e.g. a split's
    validation objects) instead of a split of ``data``, which is then trained on whole."""
    init: Path | None = None
    """Start from this checkpoint's weights (the same network, preset and view count): fine-tuning
    a pre-trained planner. The optimiser starts afresh."""
    case_balance: float = 0.0
    """Draw each epoch's training samples with probability proportional to count(case size)^-p
    (with replacement; as many as there are): 0 takes every sample once (the default), 1 weighs every
    case size alike. The long-tail cases hold few large cases, so a next-best-view planner sees few of
    the situations it meets after its first views."""
    mix_data: str | None = None
    """Draw ``mix_fraction`` of every epoch's training samples from this dataset (`osvp.mixing`):
    synthetic objects beside real ones, say. Validation stays on the run's own validation rows."""
    mix_fraction: float = 0.0
    """The mixed-in share of an epoch's samples, in (0, 1), with ``mix_data``."""

    def for_samples(self, train_samples: int) -> TrainOptions:
        """The options for a training set of ``train_samples``: with `steps`, as many epochs as give
        that many gradient steps, the learning rate halved once after 80 % of them (as the recipe's 20
        of 25 epochs), so runs on more or fewer samples get the same optimisation, only other data."""
        if self.steps is None:
            return self
        epochs = max(1, math.ceil(self.steps * self.batch_size / max(train_samples, 1)))
        return replace(self, epochs=epochs, lr_step=max(1, math.ceil(0.8 * epochs)))

    @property
    def architecture(self) -> Architecture:
        return architecture(self.network)

    @property
    def reads_covers(self) -> bool:
        """Whether the target's batches carry the listed minimum covers (`osvp.loss.Target.reads`)."""
        return TARGET_REGISTRY[self.target].reads_covers

    @property
    def num_points(self) -> int:
        """Points per cloud in a batch (one for a grid network, which reads none)."""
        return self.architecture.preset(self.preset).num_points

    def __post_init__(self) -> None:
        if not self.target and self.network in ARCHITECTURES:
            object.__setattr__(self, "target", self.architecture.default_target)

    def check(self) -> None:
        if self.network not in ARCHITECTURES:
            raise DataError(f"unknown network {self.network!r}; choose {', '.join(sorted(ARCHITECTURES))}")
        presets = self.architecture.presets
        if self.preset not in presets:
            raise DataError(f"unknown preset {self.preset!r}; choose {', '.join(sorted(presets))}")
        if self.target and self.target not in TARGET_REGISTRY:
            raise DataError(f"unknown target {self.target!r}; choose {', '.join(targets())}")
        if self.max_objects is not None and self.max_objects < 1:
            raise DataError(f"max objects {self.max_objects} must be >= 1")
        check_sample_fraction(self.sample_fraction)
        if self.steps is not None and self.steps < 1:
            raise DataError(f"steps {self.steps} must be >= 1")
        for name, value in (("epochs", self.epochs), ("batch size", self.batch_size), ("lr step", self.lr_step)):
            if value < 1:
                raise DataError(f"{name} {value} must be >= 1")
        if not (self.lambda_ > 0 and math.isfinite(self.lambda_)):
            raise DataError(f"lambda {self.lambda_} must be a positive number")
        if self.learning_rate is not None and not self.learning_rate > 0:
            raise DataError(f"learning rate {self.learning_rate} must be positive")
        if not self.memory_limit_gb > 0:
            raise DataError(f"memory limit {self.memory_limit_gb} GB must be positive")
        for name, value, least in (("workers", self.workers, 0), ("shuffle buffer", self.shuffle_buffer, 1)):
            if value < least:
                raise DataError(f"{name} {value} must be >= {least}")
        if self.fit_rows < 0:
            raise DataError(f"fit rows {self.fit_rows} must be >= 0 (0: none)")
        if self.val_cap < 0:
            raise DataError(f"validation cap {self.val_cap} must be >= 0 (0: every validation sample)")
        if not 0.0 <= self.case_balance <= 1.0:
            raise DataError(f"--case-balance {self.case_balance}: give a power from 0 (every sample once) to 1")
        if self.case_balance and self.stream:
            raise DataError("--case-balance draws samples from memory; train without --stream")
        if self.mix_data is not None:
            check_fraction(self.mix_fraction)
            if self.stream:
                raise DataError("--mix-data draws samples from memory; train without --stream")
        elif self.mix_fraction:
            raise DataError(f"--mix-fraction {self.mix_fraction} needs --mix-data: the dataset to draw that share from")
        if self.init is not None and self.resume:
            raise DataError("--init starts a new run from a checkpoint's weights; --resume continues one: give one")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise DataError(f"device {self.device!r}: CUDA is not available here; use --device cpu")

    @property
    def lr(self) -> float:
        return self.learning_rate if self.learning_rate is not None else LEARNING_RATES.get(self.preset, 1e-4)

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the run it continues."""
        data = asdict(self)
        if self.network == DEFAULT_ARCHITECTURE:  # what runs before architectures existed recorded
            data.pop("network")
        for free in ("out", "resume", "epochs", "device", "memory_limit_gb", "fit_rows"):
            data.pop(free)
        for added, unset in (
            ("val_data", None),
            ("init", None),
            ("case_balance", 0.0),
            ("mix_data", None),
            ("mix_fraction", 0.0),
        ):
            if data[added] == unset:  # what runs before these options existed recorded
                data.pop(added)
        if self.init is not None:  # the weights it started from, by content: a moved file resumes alike
            data["init"] = file_sha256(self.init)
        if not self.stream:  # in memory: what runs before streaming existed recorded
            for unused in ("stream", "workers", "shuffle_buffer", "val_cap"):
                data.pop(unused)
        data["learning_rate"] = self.lr
        return data


@dataclass(frozen=True)
class EpochReport:
    epoch: int
    epochs: int
    row: dict[str, float]
    best: bool


@dataclass(frozen=True)
class TrainOutcome:
    out: Path
    best_score: float
    """The best validation value of ``best_metric``."""
    best_metric: str
    """``cover_f1`` (nearest minimum cover, threshold 0.5) with covers, else ``f1`` (label bits)."""
    best_epoch: int
    epochs: int
    history: list[dict[str, float]]


def covers_needed(target: str) -> str | None:
    """What needs the minimum covers when training or scoring ``target``: None for ``label``."""
    found = TARGET_REGISTRY.get(target)
    return f"target {target!r}" if found is not None and found.needs_ties else None


def selection_metric(bank: SampleBank, target: str = "label") -> str:
    """The validation figure ``best.pt`` maximises: for a next-view target, how often the largest
    predicted gain is the best next view; else F1."""
    found = TARGET_REGISTRY.get(target)
    if found is not None and found.selected_by is not None:
        return found.selected_by
    if is_next_view(target):
        return "best_view_accuracy"
    return "size_cover_f1" if bank.covers is not None else "f1"


def run_rows(bank: SampleBank, options: TrainOptions) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(training rows, validation rows) of a run: the split, then the training subset
    (``max_objects``, ``sample_fraction``); validation never depends on the subset. With
    ``val_data`` every row of ``bank`` is on the training side and none validates."""
    if options.val_data is not None:
        train_side, val_rows = np.arange(len(bank), dtype=np.int64), np.zeros(0, dtype=np.int64)
    else:
        train_side, val_rows = split_rows(bank, options.split, options.val_fraction, options.seed)
    subset = training_subset(bank, train_side, options.max_objects, options.sample_fraction, options.seed)
    return subset, val_rows


@dataclass(frozen=True)
class RunRecord:
    """What a checkpoint says about the run beside its weights."""

    epoch: int
    """Epochs completed."""
    history: list[dict[str, float]]
    best_epoch: int
    best_metric: str
    tuned_threshold: float
    train_samples: int
    val_samples: int
    train_objects: int


@contextmanager
def seeded_torch(seed: int, device: str) -> Iterator[None]:
    """torch's RNG seeded inside a fork: draws are reproducible and the caller's RNG is untouched."""
    devices = [torch.device(device).index or 0] if device.startswith("cuda") else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        yield


def stream_seed(*parts: int) -> int:
    return int(np.random.SeedSequence(list(parts)).generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def train(
    options: TrainOptions,
    on_epoch: Callable[[EpochReport], None] | None = None,
    on_batch: Callable[[int, int, float], None] | None = None,
    bank: SampleBank | None = None,
) -> TrainOutcome:
    """Train (or resume) into ``options.out``: last.pt, best.pt, metrics.csv, curves.png."""
    options.check()
    needs = covers_needed(options.target)
    fields = case_fields(options.architecture)
    require_next_view_data(options, bank.schema_version if bank is not None else None)
    streamed: StreamedRows | None = None
    dataset: storage.Dataset | None = None
    streaming = options.stream if bank is None or options.stream else False
    if streaming is None:
        streaming = choose_streaming(options.data, None, options.memory_limit_gb, options.source, fields)[0]
    options = replace(options, stream=streaming)
    if streaming and options.case_balance:
        raise DataError("--case-balance draws samples from memory, but this dataset is streamed; raise --memory-limit")
    if streaming and options.mix_data is not None:
        raise DataError("--mix-data draws samples from memory, but this dataset is streamed; raise --memory-limit")
    if streaming:
        dataset = open_dataset(options.data, needs)
        bank = index_bank(dataset, options.source)
        train_rows, val_rows = run_rows(bank, options)
        val_dataset = dataset
        if options.val_data is not None:
            val_dataset = open_dataset(options.val_data, needs)
            val_rows = np.arange(len(val_dataset), dtype=np.int64)
        # Validation in memory: its rows only (a bank of their own, position p = row val_rows[p]).
        val_bank = rows_bank(val_dataset, cap_rows(val_rows, options.val_cap, options.seed), options.source, fields)
        val_rows = np.arange(len(val_bank), dtype=np.int64)
        streamed = StreamedRows(
            dataset,
            train_rows,
            options.num_points,
            options.batch_size,
            options.seed,
            options.source,
            covers=options.reads_covers,
            workers=options.workers,
            shuffle_buffer=options.shuffle_buffer,
            pin_memory=options.device.startswith("cuda"),
            fields=fields,
        )
    else:
        bank = val_bank = bank or SampleBank.load(options.data, options.source, covers_for=needs, fields=fields)
        if options.val_data is not None:
            val_bank = SampleBank.load(options.val_data, options.source, covers_for=needs, fields=fields)
    if val_bank.num_views != bank.num_views:
        raise DataError(
            f"{options.val_data}: has {val_bank.num_views} views, the training data {bank.num_views}; "
            "validate on a dataset of the same view space"
        )
    if needs is not None:
        require_covers(val_bank, needs)
    if streamed is None:
        train_rows, val_rows = run_rows(bank, options)
        if options.val_data is not None:
            val_rows = np.arange(len(val_bank), dtype=np.int64)
    mixture = _mixture(options, bank, needs, fields)
    epoch_samples = len(train_rows) + (mixture.count(len(train_rows)) if mixture is not None else 0)
    options = options.for_samples(epoch_samples)
    fit = fit_probe(dataset, bank, train_rows, options, fields)
    train_objects = len({bank.object_ids[i] for i in train_rows.tolist()})
    val_covers = val_bank.covers.take(val_rows) if val_bank.covers is not None else None
    network, optimiser, scheduler, start, history, best = _start(options, bank, options.num_points)
    generation = training_config(options.data)
    metric = selection_metric(val_bank, options.target)
    best_score = max((row[metric] for row in history), default=-1.0)
    for epoch in range(start, options.epochs):
        started = time.perf_counter()
        if streamed is not None:
            batches = streamed.epoch(epoch)
        else:
            batches = _bank_batches(bank, train_rows, options, epoch, mixture)
        train_loss, loading = _train_epoch(network, optimiser, batches, epoch_samples, options, epoch, on_batch)
        scheduler.step()
        spent = time.perf_counter() - started
        val_loss, probabilities = predict_rows(network, val_bank, val_rows, options.num_points, options)
        figures, tuned = validation_figures(val_bank, val_rows, probabilities, val_covers, options.target)
        if fit is not None:
            figures |= fit_figures(network, fit, options)
        row = {
            "epoch": epoch + 1,
            "train_loss": train_loss,
            "val_loss": val_loss,
            **figures,
            "seconds": spent,
            "train_samples_per_s": epoch_samples / spent,
            "loader_samples_per_s": epoch_samples / loading if loading > 0 else float("inf"),
        }
        history.append(row)
        improved = row[metric] > best_score
        if improved:
            best_score, best = row[metric], epoch + 1
        record = RunRecord(epoch + 1, history, best, metric, tuned, len(train_rows), len(val_rows), train_objects)
        state = _state(options, bank, network, optimiser, scheduler, record) | {"generation_config": generation}
        if improved:
            save_checkpoint(options.out / BEST, state)
        save_checkpoint(options.out / LAST, state)
        write_metrics_csv(options.out / "metrics.csv", history)
        title = f"{options.network} {options.preset}, target {options.target}, lambda {options.lambda_}"
        draw_curves(options.out / "curves.png", history, title)
        if on_epoch:
            on_epoch(EpochReport(epoch + 1, options.epochs, row, improved))
    return TrainOutcome(options.out, best_score, metric, best, options.epochs, history)


@dataclass(frozen=True)
class FitProbe:
    """The training rows a run also scores every epoch (``fit_rows``), in a bank of their own."""

    bank: SampleBank
    rows: npt.NDArray[np.int64]
    covers: CoverBank | None


def fit_probe(
    dataset: storage.Dataset | None,
    bank: SampleBank,
    train_rows: npt.NDArray[np.int64],
    options: TrainOptions,
    fields: Sequence[str],
) -> FitProbe | None:
    """A seeded draw of ``fit_rows`` training rows (None when 0); read apart when streaming (``dataset``)."""
    if options.fit_rows <= 0:
        return None
    chosen = cap_rows(train_rows, options.fit_rows, options.seed + 1)
    if dataset is not None:
        held = rows_bank(dataset, chosen, options.source, fields)
        chosen = np.arange(len(held), dtype=np.int64)
    else:
        held = bank
    return FitProbe(held, chosen, held.covers.take(chosen) if held.covers is not None else None)


def fit_figures(network: nn.Module, fit: FitProbe, options: TrainOptions) -> dict[str, float]:
    """The `osvp.curves.FIT` figures of the network on the probe's training rows, ``fit_`` prefixed."""
    _, probabilities = predict_rows(network, fit.bank, fit.rows, options.num_points, options)
    figures, _ = validation_figures(fit.bank, fit.rows, probabilities, fit.covers, options.target)
    return {f"fit_{key}": figures[key] for key in FIT if key in figures}


def validation_figures(
    bank: SampleBank,
    rows: npt.NDArray[np.int64],
    probabilities: npt.NDArray[np.float32],
    covers: CoverBank | None,
    target: str = "label",
) -> tuple[dict[str, float], float]:
    """One epoch's validation columns (each of `EPOCH_DECODINGS`, the tuned threshold and its F1;
    for a next-view target also `next_view_figures`) and the tuned threshold; ``covers``: those of
    ``rows``, in order."""
    state, labels = bank.view_state[rows], bank.labels[rows]
    figures: dict[str, float] = {}
    if is_next_view(target):
        figures = next_view_figures(bank, rows, probabilities, target)
    for prefix, decoding in EPOCH_DECODINGS.items():
        scores = decoded_metrics(probabilities, state, labels, decoding, covers).as_dict()
        figures |= {f"{prefix}{key}": value for key, value in scores.items()}
    tuned, tuned_f1 = tune_threshold(probabilities, state, labels, covers)
    return figures | {"tuned_threshold": tuned, "tuned_f1": tuned_f1}, tuned


def next_view_figures(
    bank: SampleBank, rows: npt.NDArray[np.int64], predicted: npt.NDArray[np.float32], target: str = "gain"
) -> dict[str, float]:
    """``best_view_accuracy``: the share of samples with a next view whose largest predicted score
    (among the open views, lowest index first) is the stored best next view; for the ``gain``
    target also ``gain_mae``: the mean absolute error of the predicted gain shares."""
    fields = bank.samples.fields
    gains, best = fields["view_gain"][rows], fields["best_view"][rows]
    open_views = bank.view_state[rows] < 0.5
    chosen = np.argmax(np.where(open_views, predicted, -np.inf), axis=1)
    has_next = best >= 0
    accuracy = float(np.mean(chosen[has_next] == best[has_next])) if has_next.any() else float("nan")
    figures = {"best_view_accuracy": accuracy}
    best_gain = gains[np.arange(len(rows)), np.maximum(best, 0)]
    seen_more = has_next & (best_gain > 0)
    if seen_more.any():  # what the chosen view sees of what the best one would: 1 for a view as good as the best
        taken = gains[np.arange(len(rows)), chosen]
        figures["chosen_gain_ratio"] = float(np.mean(taken[seen_more] / best_gain[seen_more]))
    if "gain_mae" in TARGET_REGISTRY[target].figures:  # a regression of the gains
        figures["gain_mae"] = float(np.mean(np.abs(predicted - gains)))
    return figures


def predict_rows(
    network: nn.Module,
    bank: SampleBank,
    rows: npt.NDArray[np.int64],
    num_points: int,
    options: TrainOptions,
    seed: int | None = None,
) -> tuple[float, npt.NDArray[np.float32]]:
    """Mean target loss of the network on ``rows`` and its probabilities (len(rows), n), with a
    fixed resampling in eval mode."""
    network.eval()
    found: list[npt.NDArray[np.float32]] = []
    total, count = 0.0, 0
    with torch.no_grad():
        for start in range(0, len(rows), options.batch_size):
            chosen = rows[start : start + options.batch_size]
            batch = bank.batch(
                chosen,
                num_points,
                options.seed if seed is None else seed,
                VALIDATION_EPOCH,
                with_covers=options.reads_covers,
            )
            logits = forward(network, options.architecture, batch, options.device).cpu()
            total += float(target_loss(options.target, logits, batch, options.lambda_)) * len(chosen)
            count += len(chosen)
            found.append(torch.sigmoid(logits).numpy())
    probabilities = np.concatenate(found) if found else np.zeros((0, bank.num_views), dtype=np.float32)
    return (total / count if count else float("nan")), probabilities


def require_next_view_data(options: TrainOptions, schema_version: int | None = None) -> None:
    """Refuse, before any sample is read, a next-view target or a grid network on a dataset before
    version 3 (``schema_version`` None: read from the dataset's record), naming the relabel."""
    needs = f"target {options.target!r}" if is_next_view(options.target) else ""
    needs = needs or (f"network {options.network!r}" if case_fields(options.architecture) else "")
    if not needs:
        return
    version = storage.open_dataset(options.data).info.schema_version if schema_version is None else schema_version
    if version < 3:
        raise DataError(
            f"{needs} needs every case's next-view labels and occupancy grid, which a version-{version} dataset "
            f"lacks; add them with `datagen shards relabel {options.data} --out NEW_URL` (no re-imaging)"
        )


def case_fields(family: Architecture) -> tuple[str, ...]:
    """The optional sample fields a network of ``family`` reads (the grid), beside the contract's own."""
    return ("grid",) if family.reads == "grid" else ()


def forward(network: nn.Module, family: Architecture, batch: Batch, device: str) -> torch.Tensor:
    """The network's logits for a batch: its cloud or its grid, as the family reads, and the view state."""
    case = batch.grid if family.reads == "grid" else batch.points
    if case is None:
        raise DataError(f"network {family.name!r} reads each case's {family.reads}, which the batch lacks")
    logits: torch.Tensor = network(case.to(device), batch.view_state.to(device))
    return logits


def epoch_order(
    rows: npt.NDArray[np.int64], case_sizes: npt.NDArray[np.int64], rng: np.random.Generator, case_balance: float
) -> npt.NDArray[np.int64]:
    """An epoch's rows: a permutation, or with ``case_balance`` p > 0 as many rows drawn with
    replacement, each with probability proportional to count(its case size)^-p (1: every size alike)."""
    if not case_balance:
        return rng.permutation(rows)
    counts = np.bincount(case_sizes)
    weights = counts[case_sizes].astype(np.float64) ** -case_balance
    return rng.choice(rows, size=len(rows), replace=True, p=weights / weights.sum())


def _bank_batches(
    bank: SampleBank, rows: npt.NDArray[np.int64], options: TrainOptions, epoch: int, mixture: Mixture | None = None
) -> Iterator[Batch]:
    """An epoch's batches from memory: the rows in a permutation drawn from (seed, epoch, 1), or with
    ``case_balance`` as many rows drawn with replacement, weighted by their case size's rarity; with a
    ``mixture``, its rows placed among them (`osvp.mixing`)."""
    sizes = bank.view_state[rows].sum(axis=1).astype(np.int64)
    order = epoch_order(
        rows, sizes, np.random.default_rng(np.random.SeedSequence([options.seed, epoch, 1])), options.case_balance
    )
    num_points = options.num_points
    if mixture is not None:
        rng = np.random.default_rng(np.random.SeedSequence([options.seed, epoch, MIX_STREAM]))
        yield from mixed_batches(
            bank, order, mixture, rng, options.batch_size, num_points, options.seed, epoch, options.reads_covers
        )
        return
    for start in range(0, len(order), options.batch_size):
        rows_now = order[start : start + options.batch_size]
        yield bank.batch(rows_now, num_points, options.seed, epoch, with_covers=options.reads_covers)


def _train_epoch(
    network: nn.Module,
    optimiser: torch.optim.Optimizer,
    batches: Iterator[Batch],
    samples: int,
    options: TrainOptions,
    epoch: int,
    on_batch: Callable[[int, int, float], None] | None,
) -> tuple[float, float]:
    """One pass over an epoch's batches (``samples`` in all); (mean loss, seconds spent waiting for them)."""
    network.train()
    total, loading, seen = 0.0, 0.0, 0
    with seeded_torch(stream_seed(options.seed, epoch, 2), options.device):
        while True:
            clock = time.perf_counter()
            batch = next(batches, None)
            loading += time.perf_counter() - clock
            if batch is None:
                break
            logits = forward(network, options.architecture, batch, options.device)
            loss = target_loss(options.target, logits, batch, options.lambda_)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            size = int(batch.label.shape[0])
            total += float(loss.detach()) * size
            seen += size
            if on_batch:
                on_batch(seen, samples, total / seen)
    return total / max(seen, 1), loading


def _mixture(options: TrainOptions, bank: SampleBank, needs: str | None, fields: Sequence[str]) -> Mixture | None:
    """The mixed-in dataset of ``options.mix_data`` in memory, refused in one line when its samples
    do not match the training data's."""
    if options.mix_data is None:
        return None
    mixed = SampleBank.load(options.mix_data, options.source, covers_for=needs, fields=fields)
    check_mixable(bank, mixed)
    return Mixture(mixed, options.mix_fraction)


def _start(
    options: TrainOptions, bank: SampleBank, num_points: int
) -> tuple[nn.Module, torch.optim.Optimizer, Any, int, list[dict[str, float]], int]:
    """A fresh network, or the state of ``last.pt`` when resuming."""
    last = options.out / LAST
    if last.exists() and not options.resume:
        raise DataError(
            f"{options.out}: already holds a training run; pass --resume to continue it or pick another --out"
        )
    if options.resume and not last.exists():
        raise DataError(f"{options.out}: nothing to resume (no {LAST}); start without --resume")
    if options.resume:
        checkpoint = load_checkpoint(last)
        if checkpoint.version < CHECKPOINT_VERSION:
            raise CheckpointError(
                f"{last}: written by an older osvp (checkpoint version {checkpoint.version}); start a new --out"
            )
        checkpoint.require(bank.num_views, num_points)
        stored = checkpoint.training
        if stored.get("options") != options.identity() or stored.get("config_hash") != bank.config_hash:
            raise CheckpointError(
                f"{last}: was trained with other options or data; resume with the same --data, --network, --preset, "
                "--lambda, --target, --batch-size, --seed, --split, --max-objects, --sample-fraction and --mix-data / "
                "--mix-fraction, streaming "
                "as it did (with the same --workers, --shuffle-buffer and --val-cap), or start a new --out"
            )
        network = checkpoint.network(options.device).train()
        optimiser, scheduler = _optimiser(network, options)
        optimiser.load_state_dict(checkpoint.data["optimiser"])
        scheduler.load_state_dict(checkpoint.data["scheduler"])
        return network, optimiser, scheduler, checkpoint.epoch, list(stored["history"]), int(stored["best_epoch"])
    with seeded_torch(stream_seed(options.seed, 0, 0), "cpu"):
        family = options.architecture
        network = family.build(family.preset(options.preset), bank.num_views)
    if options.init is not None:
        network.load_state_dict(_initial_weights(options, bank.num_views))
    network = network.to(options.device)
    optimiser, scheduler = _optimiser(network, options)
    return network, optimiser, scheduler, 0, [], 0


def _initial_weights(options: TrainOptions, num_views: int) -> dict[str, torch.Tensor]:
    """The weights of ``options.init``, refused in one line when they are another network's."""
    assert options.init is not None
    start = load_checkpoint(options.init)
    start.require(num_views, what="the training data")
    family = options.architecture
    if start.architecture.name != family.name or start.preset != family.preset(options.preset):
        raise CheckpointError(
            f"{options.init}: holds a {start.architecture.name} network of another size than --network "
            f"{family.name} --preset {options.preset}; give a checkpoint of the same network to start from"
        )
    model: dict[str, torch.Tensor] = start.data["model"]
    return model


def training_config(url: str) -> dict[str, Any]:
    """The generation config of the dataset at ``url`` (its ``dataset.json``) as plain data: what a
    checkpoint records so that ``datagen evaluate`` images the objects as its training data was."""
    config: dict[str, Any] = storage.open_dataset(url).info.config.model_dump(mode="json")
    return config


def file_sha256(path: Path) -> str:
    """The sha256 of a file's bytes (a checkpoint started from, a shipped planner)."""
    with Path(path).open("rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()


def _optimiser(network: nn.Module, options: TrainOptions) -> tuple[torch.optim.Optimizer, Any]:
    optimiser = torch.optim.AdamW(network.parameters(), lr=options.lr, weight_decay=options.weight_decay)
    scheduler = torch.optim.lr_scheduler.StepLR(optimiser, step_size=options.lr_step, gamma=0.5)
    return optimiser, scheduler


def _state(
    options: TrainOptions,
    bank: SampleBank,
    network: nn.Module,
    optimiser: torch.optim.Optimizer,
    scheduler: Any,
    record: RunRecord,
) -> dict[str, Any]:
    preset = options.architecture.preset(options.preset)
    return {
        "architecture": options.network,
        "preset": preset.as_dict(),
        "num_views": bank.num_views,
        "num_points": preset.num_points,
        "source": options.source,
        "epoch": record.epoch,
        "decoding": "tuned",
        "tuned_threshold": record.tuned_threshold,
        "model": {k: v.detach().cpu() for k, v in network.state_dict().items()},
        "optimiser": optimiser.state_dict(),
        "scheduler": scheduler.state_dict(),
        "training": {
            "options": options.identity(),
            "config_hash": bank.config_hash,
            "data": bank.url,
            "samples": len(bank),
            "train_samples": record.train_samples,
            "val_samples": record.val_samples,
            "train_objects": record.train_objects,
            "history": record.history,
            "best_epoch": record.best_epoch,
            "best_metric": record.best_metric,
        },
    }
