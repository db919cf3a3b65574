"""The training loop of our own POCO weights (the ``poco`` refiner's network).

`train` builds (or reuses) the run folder's sample pool (`poco_samples`), holds out whole shapes for
validation, then takes Adam steps on batches drawn from the pool with a random yaw about the vertical
axis as augmentation. Every ``checkpoint_every`` steps it measures the held-out shapes
(`poco_validation`), writes ``last.pt`` and ``best.pt`` (`poco_checkpoints`) and a line of ``log.jsonl``.
Batches use exactly the refiner's view of a sample (`datagen.pipeline.refine.poco.inputs`).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from datagen.errors import ConfigError
from datagen.pipeline.refine.poco.inputs import choose_inputs, forward_logits, normalise
from datagen.pipeline.refine.poco.network import PocoModel
from datagen.pipeline.refine.poco.presets import PocoPreset, get_preset
from datagen.pipeline.thread_limits import single_threaded_blas
from datagen.training.poco_checkpoints import save_training_state
from datagen.training.poco_samples import (
    Sample,
    generate_pool,
    load_pool,
    objects_file_specs,
    save_pool,
    split_pool,
    training_specs,
)
from datagen.training.poco_validation import evaluate_pool, threshold_metrics, tune_threshold

# --------------------------------------------------------------------------------------------------
# Batches


def yaw_matrix(angle: float) -> npt.NDArray[np.float64]:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_batch(
    samples: Sequence[Sample], preset: PocoPreset, rng: np.random.Generator, augment: bool = True
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """points (B,3,N), directions (B,3,N), queries (B,3,M), labels (B,M) in the normalised frame."""
    pts, dirs, qs, ls = [], [], [], []
    for sample in samples:
        pick = choose_inputs(sample.inputs.shape[0], preset.num_input_points, rng)
        inputs = sample.inputs[pick].astype(np.float64)
        centre = inputs.mean(axis=0)
        m = sample.queries.shape[0]
        chosen = rng.choice(m, size=preset.num_queries, replace=m < preset.num_queries)
        rotation = yaw_matrix(float(rng.uniform(0, 2 * math.pi))) if augment else np.eye(3)
        pts.append(normalise(inputs, centre) @ rotation.T.astype(np.float32))
        dirs.append(sample.directions[pick] @ rotation.T.astype(np.float32))
        qs.append(normalise(sample.queries[chosen].astype(np.float64), centre) @ rotation.T.astype(np.float32))
        ls.append(sample.labels[chosen])

    def stack(arrays: list[npt.NDArray[Any]]) -> Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.stack(arrays).transpose(0, 2, 1), dtype=np.float32))

    return stack(pts), stack(dirs), stack(qs), torch.from_numpy(np.stack(ls).astype(np.int64))


def forward_batch(
    model: PocoModel, batch: tuple[Tensor, Tensor, Tensor, Tensor], generator: torch.Generator, device: torch.device
) -> tuple[Tensor, Tensor]:
    """Logits of a `make_batch` batch and its labels, on ``device``."""
    points, directions, queries, labels = batch
    return forward_logits(model, points, directions, queries, generator, device), labels.to(device)


def iou_occupied(pred: Tensor, labels: Tensor) -> float:
    inter = int((pred & labels).sum())
    union = int((pred | labels).sum())
    return inter / union if union else 1.0


# --------------------------------------------------------------------------------------------------
# The loop


@dataclass
class TrainOptions:
    out: Path
    steps: int = 1000
    preset: str = "small_sv"
    seed: int = 0
    batch: int = 4
    lr: float = 1e-3
    tasks: int = 120
    samples_per_task: int = 4
    synth: int = 40
    """Synthetic shapes (objects synth) added to the 22 built-ins."""
    objects: Path | None = None
    """An objects file whose watertight meshes join the training shapes (e.g. real scans)."""
    val_fraction: float = 0.1
    checkpoint_every: int = 50
    threads: int = 1
    resume: bool = False
    init: Path | None = None
    """Weights file or checkpoint to start from (a fresh optimiser; steps continue from its step)."""
    max_seconds: float | None = None
    device: str | None = None


def build_pool(options: TrainOptions, log: Callable[[str], None] = print) -> list[Sample]:
    pool_path = options.out / "pool.npz"
    if pool_path.exists():
        return load_pool(pool_path)
    synth_list = None
    if options.synth > 0:
        from datagen.shapes.synthetic import synthesize

        synth_list = synthesize(options.synth, options.seed, options.out / "synth")
    shapes = training_specs(synth_list)
    if options.objects is not None:
        listed = objects_file_specs(options.objects)
        for reason in listed.left_out:
            log(f"pool: left out {reason}")
        log(f"pool: {len(listed.kept)} shapes of {options.objects} join {len(shapes)} built-in and synthetic ones")
        shapes.extend(listed.kept)
    started = time.perf_counter()

    def report(done: int, total: int, name: str) -> None:
        if done % 10 == 0 or done == total:
            log(f"pool: task {done}/{total} ({name}) {time.perf_counter() - started:.0f} s")

    pool = generate_pool(shapes, options.tasks, options.samples_per_task, options.seed, progress=report)
    save_pool(pool, pool_path)
    return pool


def train(options: TrainOptions, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Train (or resume) a POCO model; writes ``last.pt``, ``best.pt`` and ``log.jsonl`` under ``out``."""
    if (options.out / "last.pt").exists() and not (options.resume and options.init is None):
        raise ConfigError(
            f"{options.out} already holds a training run (last.pt); pass --resume (without --init) to continue "
            "it, or choose another --out"
        )
    if options.init is not None and not options.init.is_file():
        raise ConfigError(f"{options.init}: --init weights file not found")
    torch.set_num_threads(options.threads)
    options.out.mkdir(parents=True, exist_ok=True)
    device = torch.device(options.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    preset = get_preset(options.preset)
    pool = build_pool(options, log)
    train_set, val_set = split_pool(pool, options.val_fraction, options.seed)
    log(
        f"pool: {len(pool)} samples ({len(train_set)} train, {len(val_set)} validation), preset {preset.name}, {device}"
    )

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(options.seed)
        model = PocoModel(preset).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=options.lr)
    step = 0
    best = {"val_miou": -1.0}
    last_path, best_path = options.out / "last.pt", options.out / "best.pt"
    if options.init is not None:
        payload = torch.load(options.init, map_location=device, weights_only=True)
        state = payload.get("state_dict", payload) if isinstance(payload, dict) else payload
        model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
        step = int(payload.get("step", 0)) if isinstance(payload, dict) else 0
        log(f"initialised from {options.init} (step {step}; new optimiser)")
    elif options.resume and last_path.exists():
        payload = torch.load(last_path, map_location=device, weights_only=True)
        model.load_state_dict(payload["state_dict"])
        optimizer.load_state_dict(payload["optimizer"])
        step = int(payload["step"])
        best = json.loads(payload.get("extra", "{}")).get("best", best)
        log(f"resumed at step {step}")
    rng = np.random.default_rng(np.random.SeedSequence([options.seed, 0x57E9, step]))
    generator = torch.Generator().manual_seed(options.seed * 1_000_003 + step)
    started = time.perf_counter()
    losses: list[float] = []
    ious: list[float] = []
    history = []
    with single_threaded_blas(), open(options.out / "log.jsonl", "a") as journal:
        while step < options.steps:
            model.train()
            picks = rng.integers(0, len(train_set), size=options.batch)
            batch = make_batch([train_set[int(i)] for i in picks], preset, rng)
            logits, labels = forward_batch(model, batch, generator, device)
            loss = torch.nn.functional.cross_entropy(logits, labels)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            step += 1
            losses.append(float(loss.detach()))
            ious.append(iou_occupied(logits.argmax(1).bool(), labels.bool()))
            elapsed = time.perf_counter() - started
            final = step >= options.steps or (options.max_seconds is not None and elapsed >= options.max_seconds)
            if step % options.checkpoint_every == 0 or final:
                record: dict[str, Any] = {
                    "step": step,
                    "seconds": round(elapsed, 1),
                    "loss": float(np.mean(losses[-options.checkpoint_every :])),
                    "train_iou": float(np.mean(ious[-options.checkpoint_every :])),
                }
                if val_set:
                    ev = evaluate_pool(model, val_set[: min(len(val_set), 24)], options.seed, device)
                    tuned = tune_threshold(ev["prob"], ev["label"], ev["is_gt"])
                    record.update({f"val_{k}": v for k, v in tuned.items()})
                    record["val_majority_miou"] = threshold_metrics(ev["prob"], ev["label"], ev["is_gt"], -1.0)["miou"]
                    if record["val_miou"] > best["val_miou"]:
                        best = {"val_miou": record["val_miou"], "step": step, "threshold": tuned["threshold"]}
                        save_training_state(
                            best_path, model, optimizer, step, {"best": best, "threshold": tuned["threshold"]}
                        )
                save_training_state(last_path, model, optimizer, step, {"best": best})
                journal.write(json.dumps(record) + "\n")
                journal.flush()
                history.append(record)
                log(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in record.items()))
            if final:
                break
    return {"step": step, "best": best, "history": history, "losses": losses, "ious": ious}
