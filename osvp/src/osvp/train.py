"""Training: the OSVP network on a dataset's samples with SCLoss, validated every epoch.

Deterministic on CPU for a fixed seed and thread count: the network is initialised inside a forked
torch RNG seeded from ``seed`` (never the global one), each epoch's dropout draws come from a fork
seeded by (seed, epoch), the batch order from a numpy stream (seed, epoch), and each sample's points
from `SampleBank.batch`'s own stream. So a run resumed from ``last.pt`` (written after every epoch)
continues with exactly the weights an uninterrupted run would have. ``best.pt`` is the epoch with
the best validation F1 (the authors' selection reset every epoch; ours does not).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
import torch

from osvp.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from osvp.curves import draw_curves, write_metrics_csv
from osvp.data import DataError, SampleBank, Split, split_rows
from osvp.loss import DEFAULT_LAMBDA, sc_loss
from osvp.metrics import SetMetrics
from osvp.network import PRESETS, OSVPNetwork, build_network

LEARNING_RATES = {"paper": 1e-4, "small": 1e-3}
"""Default AdamW learning rate per preset (the authors' 1e-4 for the paper's network; the small
network trains for minutes, not days, and takes a larger step)."""

VALIDATION_EPOCH = 2**32 - 1
"""Validation clouds are resampled from this stream index, the same every epoch."""

LAST, BEST = "last.pt", "best.pt"


@dataclass(frozen=True)
class TrainOptions:
    data: str
    out: Path
    preset: str = "small"
    lambda_: float = DEFAULT_LAMBDA
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

    def check(self) -> None:
        if self.preset not in PRESETS:
            raise DataError(f"unknown preset {self.preset!r}; choose {', '.join(sorted(PRESETS))}")
        for name, value in (("epochs", self.epochs), ("batch size", self.batch_size), ("lr step", self.lr_step)):
            if value < 1:
                raise DataError(f"{name} {value} must be >= 1")
        if not (self.lambda_ > 0 and math.isfinite(self.lambda_)):
            raise DataError(f"lambda {self.lambda_} must be a positive number")
        if self.learning_rate is not None and not self.learning_rate > 0:
            raise DataError(f"learning rate {self.learning_rate} must be positive")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise DataError(f"device {self.device!r}: CUDA is not available here; use --device cpu")

    @property
    def lr(self) -> float:
        return self.learning_rate if self.learning_rate is not None else LEARNING_RATES.get(self.preset, 1e-4)

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the run it continues."""
        data = asdict(self)
        for free in ("out", "resume", "epochs", "device"):
            data.pop(free)
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
    best_f1: float
    best_epoch: int
    epochs: int
    history: list[dict[str, float]]


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
    bank = bank or SampleBank.load(options.data, options.source)
    train_rows, val_rows = split_rows(bank, options.split, options.val_fraction, options.seed)
    preset = PRESETS[options.preset]
    network, optimiser, scheduler, start, history, best = _start(options, bank, preset.num_points)
    best_f1 = max((row["f1"] for row in history), default=-1.0)
    for epoch in range(start, options.epochs):
        started = time.perf_counter()
        train_loss, loading = _train_epoch(network, optimiser, bank, train_rows, options, epoch, on_batch)
        scheduler.step()
        spent = time.perf_counter() - started
        val_loss, metrics = evaluate_rows(network, bank, val_rows, preset.num_points, options)
        row = {
            "epoch": epoch + 1,
            "train_loss": train_loss,
            "val_loss": val_loss,
            **metrics.as_dict(),
            "seconds": spent,
            "train_samples_per_s": len(train_rows) / spent,
            "loader_samples_per_s": len(train_rows) / loading if loading > 0 else float("inf"),
        }
        history.append(row)
        improved = row["f1"] > best_f1
        if improved:
            best_f1, best = row["f1"], epoch + 1
        state = _state(options, bank, network, optimiser, scheduler, epoch + 1, history, best)
        if improved:
            save_checkpoint(options.out / BEST, state)
        save_checkpoint(options.out / LAST, state)
        write_metrics_csv(options.out / "metrics.csv", history)
        draw_curves(options.out / "curves.png", history, f"osvp {options.preset}, lambda {options.lambda_}")
        if on_epoch:
            on_epoch(EpochReport(epoch + 1, options.epochs, row, improved))
    return TrainOutcome(options.out, best_f1, best, options.epochs, history)


def evaluate_rows(
    network: OSVPNetwork,
    bank: SampleBank,
    rows: npt.NDArray[np.int64],
    num_points: int,
    options: TrainOptions,
    seed: int | None = None,
) -> tuple[float, SetMetrics]:
    """Mean SCLoss and set metrics of the network on ``rows`` (fixed resampling, eval mode)."""
    network.eval()
    metrics, total, count = SetMetrics(), 0.0, 0
    with torch.no_grad():
        for start in range(0, len(rows), options.batch_size):
            chosen = rows[start : start + options.batch_size]
            batch = bank.batch(chosen, num_points, options.seed if seed is None else seed, VALIDATION_EPOCH)
            logits = network(batch.points.to(options.device), batch.view_state.to(options.device)).cpu()
            total += float(sc_loss(logits, batch.labels, options.lambda_)) * len(chosen)
            count += len(chosen)
            metrics.add(torch.sigmoid(logits), batch.labels)
    return (total / count if count else float("nan")), metrics


def _train_epoch(
    network: OSVPNetwork,
    optimiser: torch.optim.Optimizer,
    bank: SampleBank,
    rows: npt.NDArray[np.int64],
    options: TrainOptions,
    epoch: int,
    on_batch: Callable[[int, int, float], None] | None,
) -> tuple[float, float]:
    """One pass over the training rows; (mean loss, seconds spent building batches)."""
    network.train()
    order = np.random.default_rng(np.random.SeedSequence([options.seed, epoch, 1])).permutation(rows)
    num_points = PRESETS[options.preset].num_points
    total, loading, seen = 0.0, 0.0, 0
    with seeded_torch(stream_seed(options.seed, epoch, 2), options.device):
        for start in range(0, len(order), options.batch_size):
            clock = time.perf_counter()
            batch = bank.batch(order[start : start + options.batch_size], num_points, options.seed, epoch)
            loading += time.perf_counter() - clock
            logits = network(batch.points.to(options.device), batch.view_state.to(options.device))
            loss = sc_loss(logits, batch.labels.to(options.device), options.lambda_)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            size = int(batch.labels.shape[0])
            total += float(loss.detach()) * size
            seen += size
            if on_batch:
                on_batch(seen, len(order), total / seen)
    return total / max(seen, 1), loading


def _start(
    options: TrainOptions, bank: SampleBank, num_points: int
) -> tuple[OSVPNetwork, torch.optim.Optimizer, Any, int, list[dict[str, float]], int]:
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
        checkpoint.require(bank.num_views, num_points)
        stored = checkpoint.training
        if stored.get("options") != options.identity() or stored.get("config_hash") != bank.config_hash:
            raise CheckpointError(
                f"{last}: was trained with other options or data; resume with the same --data, --preset, --lambda, "
                "--batch-size, --seed and --split, or start a new --out"
            )
        network = checkpoint.network(options.device).train()
        optimiser, scheduler = _optimiser(network, options)
        optimiser.load_state_dict(checkpoint.data["optimiser"])
        scheduler.load_state_dict(checkpoint.data["scheduler"])
        return network, optimiser, scheduler, checkpoint.epoch, list(stored["history"]), int(stored["best_epoch"])
    with seeded_torch(stream_seed(options.seed, 0, 0), "cpu"):
        network = build_network(options.preset, bank.num_views)
    network = network.to(options.device)
    optimiser, scheduler = _optimiser(network, options)
    return network, optimiser, scheduler, 0, [], 0


def _optimiser(network: OSVPNetwork, options: TrainOptions) -> tuple[torch.optim.Optimizer, Any]:
    optimiser = torch.optim.AdamW(network.parameters(), lr=options.lr, weight_decay=options.weight_decay)
    scheduler = torch.optim.lr_scheduler.StepLR(optimiser, step_size=options.lr_step, gamma=0.5)
    return optimiser, scheduler


def _state(
    options: TrainOptions,
    bank: SampleBank,
    network: OSVPNetwork,
    optimiser: torch.optim.Optimizer,
    scheduler: Any,
    epoch: int,
    history: list[dict[str, float]],
    best_epoch: int,
) -> dict[str, Any]:
    preset = PRESETS[options.preset]
    return {
        "preset": preset.as_dict(),
        "num_views": bank.num_views,
        "num_points": preset.num_points,
        "source": options.source,
        "epoch": epoch,
        "model": {k: v.detach().cpu() for k, v in network.state_dict().items()},
        "optimiser": optimiser.state_dict(),
        "scheduler": scheduler.state_dict(),
        "training": {
            "options": options.identity(),
            "config_hash": bank.config_hash,
            "data": bank.url,
            "samples": len(bank),
            "history": history,
            "best_epoch": best_epoch,
        },
    }
