"""Training data and the training loop of our own POCO weights (the ``poco`` refiner's network).

Data comes only from the project's own shapes (built-ins and ``objects synth`` meshes). A sample is
built exactly as the refiner sees a case at inference:

- a random shape prepared at a random size in [0.05, 0.15] m, a random task rotation, ``scan_task``
  once per (shape, rotation); 1-3 random views combined with `Observation.combine`;
- **inputs** = centres of keys(O), clean (no noise: the refiner feeds clean key centres too), each
  with the unit direction to the camera of the first point that saw it (``*_sv`` presets);
- **queries** = band keys of O minus keys(O) minus sensor-empty keys (the refiner's query set),
  labelled by ``mesh.contains`` on the key centre (all shapes are watertight), plus a few uniform
  points in the band's box (``BOX_FRACTION`` of the labelled queries);
- each query also records whether it is a P_gt key (for the hidden-key recall metric).

The network works in a normalised frame: `normalise` centres on the mean of the chosen input points
and divides by ``TRAINING_SCALE`` metres. Input points are chosen by `choose_inputs`: a random subset
of ``num_input_points`` when there are more, else all of them plus random repeats to fill exactly
``num_input_points`` (the same rule at inference, so the point density matches training).

Samples are generated once into a pool (``pool.npz`` in the run folder, reused on resume), then the
loop draws batches from it with a random yaw about the vertical axis as augmentation.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
import trimesh
from torch import Tensor

from datagen.errors import ConfigError
from datagen.pipeline.imaging import Observation
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.objects.spec import BUILTIN_PREFIX, ObjectOptions, ObjectSpec, builtin_object_id, file_object_id
from datagen.pipeline.refine.base import band_keys
from datagen.pipeline.refine.freespace import sensor_empty
from datagen.pipeline.refine.poco.network import PocoModel
from datagen.pipeline.refine.poco.presets import PocoPreset, get_preset
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.thread_limits import single_threaded_blas
from datagen.pipeline.viewspace import build_view_space
from datagen.shapes import builtins
from schemas.config import GenerationConfig

TRAINING_SCALE = 0.05
"""Metres per network unit: inputs are centred on their mean and divided by this."""
BOX_FRACTION = 0.1
"""Share of labelled training queries drawn uniformly in the band's box (not just the query set)."""
SIZE_RANGE = (0.05, 0.15)


# --------------------------------------------------------------------------------------------------
# What the network sees (shared by training and the refiner)


def observation_inputs(
    observation: Observation, voxel_size: float, grid_offset: tuple[float, float, float]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Centres of keys(O) and, per key, the unit direction to the camera of the first point in it."""
    keys = observation.keys
    centres = key_centres(unpack_keys(keys), voxel_size, grid_offset)
    from datagen.pipeline.keys import points_to_packed

    point_keys = points_to_packed(observation.points.astype(np.float64), voxel_size, grid_offset)
    origins = observation.point_origins()
    index = np.searchsorted(keys, point_keys)
    index = np.clip(index, 0, max(keys.size - 1, 0))
    found = keys[index] == point_keys if keys.size else np.zeros(0, dtype=bool)
    origin_of = np.full((keys.size, 3), np.nan)
    rows = np.flatnonzero(found)[::-1]  # reversed so the first point of each key is written last
    origin_of[index[rows]] = origins[rows]
    missing = np.isnan(origin_of[:, 0])
    if missing.any():  # a key with no hit point in it (should not happen): its nearest view's origin
        origin_of[missing] = observation.origins[0]
    directions = np.asarray(origin_of - centres, dtype=np.float64)
    directions /= np.maximum(np.linalg.norm(directions, axis=1, keepdims=True), 1e-12)
    return np.asarray(centres, dtype=np.float64), directions


def choose_inputs(count: int, n: int, rng: np.random.Generator) -> npt.NDArray[np.int64]:
    """Exactly ``n`` row indices of ``count`` points: a subset when more, all plus repeats when fewer."""
    if count >= n:
        return np.sort(rng.choice(count, size=n, replace=False))
    extra = rng.integers(0, count, size=n - count)
    return np.concatenate([np.arange(count), np.sort(extra)])


def normalise(points: npt.NDArray[np.float64], centre: npt.NDArray[np.float64]) -> npt.NDArray[np.float32]:
    return ((points - centre) / TRAINING_SCALE).astype(np.float32)


def query_keys(
    observation: Observation, config: GenerationConfig
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """(unknown, queries, empty): band minus keys(O); those not sensor-empty; the sensor-empty mask."""
    band = band_keys(observation.keys, config.band_keys_sq)
    unknown = np.setdiff1d(band, observation.keys, assume_unique=True)
    empty = sensor_empty(unknown, observation, config.camera, config.voxel_size, config.grid_offset)
    return unknown, unknown[~empty], empty


# --------------------------------------------------------------------------------------------------
# Training shapes and samples


def training_specs(synth_objects: Path | None = None) -> list[tuple[str, str, bytes | None]]:
    """(name, source, mesh bytes or None for built-ins) of every training shape."""
    shapes: list[tuple[str, str, bytes | None]] = [(n, BUILTIN_PREFIX + n, None) for n in builtins.builtin_names()]
    if synth_objects is not None:
        folder = synth_objects.parent
        for line in synth_objects.read_text().splitlines():
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            path = (folder / line.split()[0]).resolve()
            shapes.append((path.stem, str(path), path.read_bytes()))
    return shapes


def sized_spec(name: str, source: str, data: bytes | None, size: float) -> ObjectSpec:
    options = ObjectOptions(size=float(size))
    if data is None:
        identity = builtins.builtin_generator_identity(source[len(BUILTIN_PREFIX) :])
        object_id = builtin_object_id(identity, options)
        return ObjectSpec(source=source, name=name, options=options, object_id=object_id, generator=identity)
    return ObjectSpec(source=source, name=name, options=options, object_id=file_object_id(data, options))


@dataclass
class Sample:
    """One training sample, in metres (normalisation happens when batching)."""

    inputs: npt.NDArray[np.float32]  # (n, 3) key centres of O
    directions: npt.NDArray[np.float32]  # (n, 3) unit, towards the camera
    queries: npt.NDArray[np.float32]  # (m, 3) query key centres, then box points
    labels: npt.NDArray[np.bool_]  # (m,) inside
    is_gt: npt.NDArray[np.bool_]  # (m,) query is a P_gt key (False for box points)
    is_box: npt.NDArray[np.bool_]  # (m,) uniform box point, not a query key
    shape: str


def samples_of_task(
    prepared_vertices: npt.NDArray[np.float64],
    faces: npt.NDArray[np.int64],
    imaging: Any,
    config: GenerationConfig,
    rng: np.random.Generator,
    count: int,
    shape: str,
    max_views: int = 3,
) -> list[Sample]:
    """``count`` samples of one scanned task, each of 1..max_views random views."""
    mesh = trimesh.Trimesh(vertices=prepared_vertices, faces=faces, process=False)
    gt_keys = imaging.ground_truth.keys
    samples = []
    n_views = len(imaging.observations)
    for _ in range(count):
        k = int(rng.integers(1, max_views + 1))
        views = rng.choice(n_views, size=k, replace=False)
        parts = [imaging.observations[int(v)] for v in views]
        parts = [p for p in parts if p.keys.size]
        if not parts:
            continue
        observation = Observation.combine(parts)
        inputs, directions = observation_inputs(observation, config.voxel_size, config.grid_offset)
        _, queries, _ = query_keys(observation, config)
        centres = key_centres(unpack_keys(queries), config.voxel_size, config.grid_offset)
        n_box = max(1, int(BOX_FRACTION * centres.shape[0]))
        low = inputs.min(axis=0) - config.band
        high = inputs.max(axis=0) + config.band
        box = low + rng.random((n_box, 3)) * (high - low)
        points = np.concatenate([centres, box])
        labels = mesh.contains(points) if points.size else np.zeros(0, dtype=bool)
        is_gt = np.concatenate([np.isin(queries, gt_keys, assume_unique=True), np.zeros(n_box, dtype=bool)])
        is_box = np.concatenate([np.zeros(centres.shape[0], dtype=bool), np.ones(n_box, dtype=bool)])
        samples.append(
            Sample(
                inputs.astype(np.float32),
                directions.astype(np.float32),
                points.astype(np.float32),
                np.asarray(labels, dtype=bool),
                is_gt,
                is_box,
                shape,
            )
        )
    return samples


def generate_pool(
    shapes: Sequence[tuple[str, str, bytes | None]],
    tasks: int,
    samples_per_task: int,
    seed: int,
    config: GenerationConfig | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> list[Sample]:
    """Scan ``tasks`` random (shape, size, rotation) tasks and cut ``samples_per_task`` samples from each."""
    config = config or GenerationConfig()
    view_space = build_view_space(config.view_space)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x9C0]))
    pool: list[Sample] = []
    with single_threaded_blas():
        for task in range(tasks):
            name, source, data = (
                shapes[task % len(shapes)] if task < len(shapes) else shapes[int(rng.integers(len(shapes)))]
            )
            size = float(rng.uniform(*SIZE_RANGE))
            prepared = prepare_object(sized_spec(name, source, data, size), config)
            rotation = int(rng.integers(config.rotations))
            imaging = scan_task(prepared, rotation, config, view_space)
            vertices = prepared.task_vertices(rotation, config.rotations)
            pool.extend(samples_of_task(vertices, prepared.faces, imaging, config, rng, samples_per_task, name))
            if progress is not None:
                progress(task + 1, tasks, name)
    return pool


def save_pool(pool: Sequence[Sample], path: Path) -> None:
    arrays: dict[str, Any] = {}
    for field in ("inputs", "directions", "queries", "labels", "is_gt", "is_box"):
        values = [getattr(s, field) for s in pool]
        arrays[field] = np.concatenate(values)
        arrays[field + "_len"] = np.array([len(v) for v in values], dtype=np.int64)
    arrays["shape"] = np.array([s.shape for s in pool])
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def load_pool(path: Path) -> list[Sample]:
    data = np.load(path)
    split: dict[str, list[Any]] = {}
    for field in ("inputs", "directions", "queries", "labels", "is_gt", "is_box"):
        split[field] = np.split(data[field], np.cumsum(data[field + "_len"])[:-1])
    return [
        Sample(
            inputs=split["inputs"][i],
            directions=split["directions"][i],
            queries=split["queries"][i],
            labels=split["labels"][i],
            is_gt=split["is_gt"][i],
            is_box=split["is_box"][i],
            shape=str(name),
        )
        for i, name in enumerate(data["shape"])
    ]


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
    points, directions, queries, labels = batch
    tables = model.tables(points, generator, queries=queries)
    points, directions, queries, labels = (t.to(device) for t in (points, directions, queries, labels))
    tables = {k: v.to(device) for k, v in tables.items()}
    features = model.features(points, directions if model.preset.uses_directions else None)
    logits = model(points, features, tables, queries, tables["proj_indices"])
    return logits, labels


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
    started = time.perf_counter()

    def report(done: int, total: int, name: str) -> None:
        if done % 10 == 0 or done == total:
            log(f"pool: task {done}/{total} ({name}) {time.perf_counter() - started:.0f} s")

    pool = generate_pool(shapes, options.tasks, options.samples_per_task, options.seed, progress=report)
    save_pool(pool, pool_path)
    return pool


def split_pool(pool: Sequence[Sample], val_fraction: float, seed: int) -> tuple[list[Sample], list[Sample]]:
    """Hold out whole shapes (by name) for validation, so validation measures unseen shapes."""
    names = sorted({s.shape for s in pool})
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7A1]))
    held = set(rng.choice(names, size=max(1, round(val_fraction * len(names))), replace=False).tolist())
    return [s for s in pool if s.shape not in held], [s for s in pool if s.shape in held]


def evaluate_pool(
    model: PocoModel, samples: Sequence[Sample], seed: int, device: torch.device
) -> dict[str, npt.NDArray[Any]]:
    """Per query (box points excluded): p(inside), label, is_gt, over every query of every sample."""
    model.eval()
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0xE7A]))
    generator = torch.Generator().manual_seed(seed)
    probs, labels, gts = [], [], []
    with torch.no_grad():
        for sample in samples:
            keep = ~sample.is_box
            probs.append(
                predict_probs(model, sample.inputs, sample.directions, sample.queries[keep], rng, generator, device)
            )
            labels.append(sample.labels[keep])
            gts.append(sample.is_gt[keep])
    return {"prob": np.concatenate(probs), "label": np.concatenate(labels), "is_gt": np.concatenate(gts)}


def predict_probs(
    model: PocoModel,
    inputs: npt.NDArray[Any],
    directions: npt.NDArray[Any],
    queries: npt.NDArray[Any],
    rng: np.random.Generator,
    generator: torch.Generator,
    device: torch.device,
) -> npt.NDArray[np.float32]:
    """p(inside) of each query (metres) given the observed key centres (metres), one observation."""
    if queries.shape[0] == 0:
        return np.zeros(0, dtype=np.float32)
    pick = choose_inputs(inputs.shape[0], model.preset.num_input_points, rng)
    chosen = inputs[pick].astype(np.float64)
    centre = chosen.mean(axis=0)
    points = torch.from_numpy(normalise(chosen, centre).T.copy())[None]
    dirs = torch.from_numpy(np.ascontiguousarray(directions[pick].T, dtype=np.float32))[None]
    q = torch.from_numpy(normalise(queries.astype(np.float64), centre).T.copy())[None]
    with torch.no_grad():
        tables = model.tables(points, generator, queries=q)
        tables = {k: v.to(device) for k, v in tables.items()}
        points, dirs, q = points.to(device), dirs.to(device), q.to(device)
        features = model.features(points, dirs if model.preset.uses_directions else None)
        latents = model.encode(points, features, tables)
        logits = model.decode(latents, points, q, tables["proj_indices"], chunk_size=8192)
        prob = torch.softmax(logits.float(), dim=1)[0, 1]
    return prob.cpu().numpy().astype(np.float32)


def threshold_metrics(
    prob: npt.NDArray[Any], label: npt.NDArray[Any], is_gt: npt.NDArray[Any], t: float
) -> dict[str, float]:
    pred = prob > t
    tp = float((pred & label).sum())
    precision = tp / max(1.0, float(pred.sum()))
    recall = tp / max(1.0, float(label.sum()))
    iou1 = tp / max(1.0, float((pred | label).sum()))
    iou0 = float((~pred & ~label).sum()) / max(1.0, float((~pred | ~label).sum()))
    hidden = float(pred[is_gt].mean()) if is_gt.any() else 0.0
    return {
        "threshold": t,
        "precision": precision,
        "recall": recall,
        "iou": iou1,
        "miou": (iou0 + iou1) / 2,
        "hidden_recall": hidden,
    }


def tune_threshold(
    prob: npt.NDArray[Any], label: npt.NDArray[Any], is_gt: npt.NDArray[Any], min_hidden_recall: float = 0.35
) -> dict[str, float]:
    """The highest threshold (most precise R) that still keeps ``min_hidden_recall`` of the hidden
    P_gt keys; if none does, the threshold of the best mean IoU over both classes."""
    grid = [round(float(t), 3) for t in np.arange(0.05, 0.96, 0.025)]
    rows = [threshold_metrics(prob, label, is_gt, t) for t in grid]
    good = [r for r in rows if r["hidden_recall"] >= min_hidden_recall]
    if good:
        return max(good, key=lambda r: r["threshold"])
    return max(rows, key=lambda r: r["miou"])


def save_training_state(
    path: Path, model: PocoModel, optimizer: torch.optim.Optimizer, step: int, extra: dict[str, Any]
) -> None:
    payload = {
        "state_dict": model.state_dict(),
        "optimizer": optimizer.state_dict(),
        "preset": dataclasses.asdict(model.preset),
        "step": int(step),
        "extra": json.dumps(extra),
    }
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    os.close(fd)
    torch.save(payload, tmp)
    os.replace(tmp, path)


def export_weights(checkpoint: Path, out: Path, threshold: float | None = None, half: bool = True) -> None:
    """Write the shipped weights file (fp16 storage by default) from a training checkpoint."""
    payload = torch.load(checkpoint, map_location="cpu", weights_only=True)
    state = payload["state_dict"]
    if half:
        state = {k: (v.half() if v.is_floating_point() else v) for k, v in state.items()}
    extra = json.loads(payload.get("extra", "{}"))
    if threshold is not None:
        extra["threshold"] = threshold
    torch.save(
        {
            "state_dict": state,
            "preset": payload["preset"],
            "step": payload.get("step", 0),
            "training_scale": TRAINING_SCALE,
            "extra": json.dumps(extra),
        },
        out,
    )


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
