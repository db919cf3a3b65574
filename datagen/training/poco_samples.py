"""Training examples of our own POCO weights.

Shapes: the built-ins, ``objects synth`` meshes and, optionally, the watertight meshes of an objects
file (`objects_file_specs`: real scans; an open mesh has no inside, so no labels, and is left out).
A sample is built exactly as the refiner sees a case at inference (`datagen.pipeline.refine.poco.inputs`):

- a random shape prepared at a random size in [0.05, 0.15] m, a random task rotation, ``scan_task``
  once per (shape, rotation); 1-3 random views combined with `Observation.combine`;
- **inputs** = centres of keys(O), clean (no noise: the refiner feeds clean key centres too), each
  with the unit direction to the camera of the first point that saw it (``*_sv`` presets);
- **queries** = band keys of O minus keys(O) minus sensor-empty keys (the refiner's query set),
  labelled by ``mesh.contains`` on the key centre (all shapes are watertight), plus a few uniform
  points in the band's box (``BOX_FRACTION`` of the labelled queries);
- each query also records whether it is a P_gt key (for the hidden-key recall metric).

Samples are kept in metres; the network frame is applied when batching. They are generated once into
a pool (``pool.npz`` in the run folder, reused on resume); `split_pool` holds out whole shapes.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import trimesh

from datagen.pipeline.imaging import Observation
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.objects.spec import BUILTIN_PREFIX, ObjectOptions, ObjectSpec, builtin_object_id, file_object_id
from datagen.pipeline.refine.poco.inputs import observation_inputs, query_keys
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.thread_limits import single_threaded_blas
from datagen.pipeline.viewspace import build_view_space
from datagen.shapes import builtins
from schemas.config import GenerationConfig

BOX_FRACTION = 0.1
"""Share of labelled training queries drawn uniformly in the band's box (not just the query set)."""
SIZE_RANGE = (0.05, 0.15)


ShapeSource = tuple[str, str, bytes | None]
"""(name, source, mesh bytes or None for a built-in) of one training shape."""


def training_specs(synth_objects: Path | None = None) -> list[ShapeSource]:
    """The built-ins, then the synthetic listing's meshes (`objects_file_specs` adds an objects file's)."""
    shapes: list[ShapeSource] = [(n, BUILTIN_PREFIX + n, None) for n in builtins.builtin_names()]
    if synth_objects is not None:
        folder = synth_objects.parent
        for line in synth_objects.read_text().splitlines():
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            path = (folder / line.split()[0]).resolve()
            shapes.append((path.stem, str(path), path.read_bytes()))
    return shapes


@dataclass(frozen=True)
class ListedShapes:
    """The shapes of an objects file that can be labelled, and why each other line cannot."""

    kept: list[ShapeSource]
    left_out: list[str]
    """One line each: an unreadable line, a built-in (already in the pool) or an open mesh."""


def objects_file_specs(objects: Path, config: GenerationConfig | None = None) -> ListedShapes:
    """The watertight meshes of an objects file, by their listed names (real scans for training).

    Labels are ``mesh.contains`` of query centres, defined only inside a closed surface, so an open
    mesh is left out rather than labelled by a guess; each one is named in ``left_out``.
    """
    from datagen.errors import ObjectError
    from datagen.pipeline.objects.objects_file import ObjectLineError, read_objects_file

    config = config or GenerationConfig()
    kept: list[ShapeSource] = []
    left_out: list[str] = []
    with single_threaded_blas():
        for entry in read_objects_file(objects).entries:
            if isinstance(entry, ObjectLineError):
                left_out.append(str(entry))
                continue
            if entry.is_builtin:
                left_out.append(f"{entry.name}: a built-in, already a training shape")
                continue
            try:
                watertight = prepare_object(entry, config).watertight
            except ObjectError as error:  # a corrupt or empty mesh: its one line, the rest go on
                left_out.append(str(error))
                continue
            if watertight:
                kept.append((entry.name, entry.source, Path(entry.source).read_bytes()))
            else:
                left_out.append(f"{entry.name}: open mesh (not watertight), no inside to label")
    return ListedShapes(kept, left_out)


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


def split_pool(pool: Sequence[Sample], val_fraction: float, seed: int) -> tuple[list[Sample], list[Sample]]:
    """Hold out whole shapes (by name) for validation, so validation measures unseen shapes."""
    names = sorted({s.shape for s in pool})
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7A1]))
    held = set(rng.choice(names, size=max(1, round(val_fraction * len(names))), replace=False).tolist())
    return [s for s in pool if s.shape not in held], [s for s in pool if s.shape in held]
