"""What the POCO network sees, shared by the refiner and by training (`datagen.training`).

- **Inputs** (`observation_inputs`): the centres of keys(O), clean, each with the unit direction to
  the camera of the first observed point in its key (used by the ``*_sv`` presets).
- **Input points** (`choose_inputs`): exactly the preset's ``num_input_points``: a random subset when
  there are more, else all of them plus random repeats, so the point density matches training.
- **Frame** (`normalise`): centred on the mean of the chosen input points and divided by
  ``TRAINING_SCALE`` metres; `network_tensors` builds the (1, 3, n) tensors of one observation.
- **Queries** (`query_keys`): the band keys of O minus keys(O) minus the keys some view saw empty.
- **Running the network**: `forward_logits` (the differentiable forward used by training and
  test-time fine-tuning) and `predict_probs` (p(inside) of each query, chunked, without gradients).

Everything here is inference-side: it imports the pipeline and torch, never training code or trimesh.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from datagen.pipeline.imaging import Observation
from datagen.pipeline.keys import key_centres, points_to_packed, unpack_keys
from datagen.pipeline.refine.base import ViewBands, band_keys
from datagen.pipeline.refine.freespace import DepthBuffers, sensor_empty
from datagen.pipeline.refine.poco.network import PocoModel
from datagen.pipeline.refine.poco.spatial import KnnBackend
from schemas.config import GenerationConfig

TRAINING_SCALE = 0.05
"""Metres per network unit: inputs are centred on their mean and divided by this."""
DECODE_CHUNK = 8192
"""Queries decoded at once by `predict_probs` (bounds memory on large bands). The fast path keeps this
chunking where it decides bits (`PocoModel.decode_inference`) and decodes cache-sized sub-chunks."""


def observation_inputs(
    observation: Observation, voxel_size: float, grid_offset: tuple[float, float, float]
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Centres of keys(O) and, per key, the unit direction to the camera of the first point in it."""
    keys = observation.keys
    centres = key_centres(unpack_keys(keys), voxel_size, grid_offset)
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
    """Points (metres) in the network frame around ``centre``."""
    return ((points - centre) / TRAINING_SCALE).astype(np.float32)


def query_keys(
    observation: Observation,
    config: GenerationConfig,
    buffers: DepthBuffers | None = None,
    bands: ViewBands | None = None,
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64], npt.NDArray[np.bool_]]:
    """(unknown, queries, empty): band minus keys(O); those not sensor-empty; the sensor-empty mask.

    ``buffers`` keeps views' depth buffers between calls (`freespace.DepthBuffers`), ``bands`` their
    bands (`base.ViewBands`, for ``config.band_keys_sq``); the result is the same with or without.
    """
    if bands is not None and bands.radius_sq == config.band_keys_sq:
        band = bands.band(observation)
    else:
        band = band_keys(observation.keys, config.band_keys_sq)
    unknown = np.setdiff1d(band, observation.keys, assume_unique=True)
    empty = sensor_empty(unknown, observation, config.camera, config.voxel_size, config.grid_offset, buffers)
    return unknown, unknown[~empty], empty


def network_tensors(
    chosen: npt.NDArray[Any], directions: npt.NDArray[Any], queries: npt.NDArray[Any]
) -> tuple[Tensor, Tensor, Tensor]:
    """(points, directions, queries) of one observation as (1, 3, n) CPU tensors in the network frame.

    ``chosen`` are the input points picked by `choose_inputs` (metres), ``directions`` theirs; the
    frame is centred on the mean of ``chosen``.
    """
    chosen = chosen.astype(np.float64)
    centre = chosen.mean(axis=0)
    points = torch.from_numpy(normalise(chosen, centre).T.copy())[None]
    dirs = torch.from_numpy(np.ascontiguousarray(directions.T, dtype=np.float32))[None]
    q = torch.from_numpy(normalise(queries.astype(np.float64), centre).T.copy())[None]
    return points, dirs, q


def place_on_device(
    model: PocoModel,
    points: Tensor,
    directions: Tensor,
    queries: Tensor,
    generator: torch.Generator,
    device: torch.device | str,
    knn_backend: KnnBackend = "auto",
) -> tuple[Tensor, Tensor, dict[str, Tensor], Tensor]:
    """(points, features, tables, queries) on ``device``. The sampling runs on the CPU; with
    ``knn_backend`` "ordered" (``poco_version`` 3) every neighbour table is `spatial.knn_ordered`'s,
    searched on ``device``; otherwise on the CPU, the encoder's by scipy's cKDTree, the decoder's
    (``proj_indices``) by ``knn_backend`` ("auto" is cKDTree there too; "pykdtree" for version 2)."""
    if knn_backend == "ordered":
        tables = model.tables(points.cpu(), generator, queries.cpu(), backend="ordered", knn_device=device)
    else:
        tables = model.tables(points.cpu(), generator)
        tables["proj_indices"] = model.query_knn(points.cpu(), queries.cpu(), backend=knn_backend)
    tables = {k: v.to(device) for k, v in tables.items()}
    points, directions, queries = points.to(device), directions.to(device), queries.to(device)
    features = model.features(points, directions if model.preset.uses_directions else None)
    return points, features, tables, queries


def forward_logits(
    model: PocoModel,
    points: Tensor,
    directions: Tensor,
    queries: Tensor,
    generator: torch.Generator,
    device: torch.device | str,
    knn_backend: KnnBackend = "auto",
    fast: bool = True,
) -> Tensor:
    """Logits (B, 2, M) of the queries in one differentiable forward (training, test-time fine-tuning;
    ``fast=False``: the encoder's original operations, `PocoModel.encode`)."""
    with exact_float32(device):
        points, features, tables, queries = place_on_device(
            model, points, directions, queries, generator, device, knn_backend
        )
        logits: Tensor = model(points, features, tables, queries, tables["proj_indices"], fast=fast)
    return logits


@contextmanager
def exact_float32(device: torch.device | str) -> Iterator[None]:
    """TF32 off while a CUDA device runs the network (a no-op elsewhere). cuDNN's convolutions use TF32
    by default, which moved 0.03-0.4 % of R(O)'s keys and 2 of 327 labels away from the CPU's on an
    H200; with it off, every R(O) and label equalled the CPU's
    (benchmarks/generation/results/gpu-check.md). The flags are restored on the way out."""
    if torch.device(device).type != "cuda":
        yield
        return
    cudnn = torch.backends.cudnn
    matmul = torch.backends.cuda.matmul
    with cudnn.flags(
        enabled=cudnn.enabled, benchmark=cudnn.benchmark, deterministic=cudnn.deterministic, allow_tf32=False
    ):
        before = matmul.allow_tf32
        matmul.allow_tf32 = False
        try:
            yield
        finally:
            matmul.allow_tf32 = before


def predict_probs(
    model: PocoModel,
    inputs: npt.NDArray[Any],
    directions: npt.NDArray[Any],
    queries: npt.NDArray[Any],
    rng: np.random.Generator,
    generator: torch.Generator,
    device: torch.device | str,
    *,
    fast: bool = True,
    knn_backend: KnnBackend = "auto",
) -> npt.NDArray[np.float32]:
    """p(inside) of each query (metres) given the observed key centres (metres), one observation.

    ``fast`` (the default) runs under ``torch.inference_mode`` with `PocoModel.decode_inference`;
    ``fast=False`` is the original execution (``no_grad``, `PocoModel.decode` in chunks of
    `DECODE_CHUNK`). Both give bit-identical probabilities (tests/pipeline/test_refine_speed.py).
    ``knn_backend`` builds the neighbour tables (`place_on_device`).
    """
    if queries.shape[0] == 0:
        return np.zeros(0, dtype=np.float32)
    pick = choose_inputs(inputs.shape[0], model.preset.num_input_points, rng)
    points, dirs, q = network_tensors(inputs[pick], directions[pick], queries)
    with torch.inference_mode() if fast else torch.no_grad(), exact_float32(device):
        points, features, tables, q = place_on_device(model, points, dirs, q, generator, device, knn_backend)
        latents = model.encode(points, features, tables, fast)
        return decode_probs(model, latents, points, q, tables["proj_indices"], fast)


def decode_probs(
    model: PocoModel, latents: Tensor, points: Tensor, queries: Tensor, knn: Tensor, fast: bool = True
) -> npt.NDArray[np.float32]:
    """p(inside) of one observation's queries from its latents (1, L, n): `PocoModel.decode_inference`
    when ``fast``, else `PocoModel.decode` in chunks of `DECODE_CHUNK` (the same bits)."""
    if fast:
        logits = model.decode_inference(latents, points, queries, knn, DECODE_CHUNK)
    else:
        logits = model.decode(latents, points, queries, knn, chunk_size=DECODE_CHUNK)
    prob = torch.softmax(logits.float(), dim=1)[0, 1]
    return prob.cpu().numpy().astype(np.float32)
