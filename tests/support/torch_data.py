"""Small real datasets for the storage/torch, export and training-signal tests.

Datasets are built from built-in shapes through the real pipeline (`datagen.pipeline.task.run_task` ->
`datagen.engine.shard_payload.task_payload` -> `storage.dataset.write_task`, then
`storage.dataset.finalise`), once per test session (`cached_dataset`). Alongside the URL a build keeps
what the pipeline produced for every sample (packed keys of ``points`` and ``observed``, case and label
masks), so tests can check what the readers return against the pipeline's own output rather than
against the reader itself.

``shift`` builds use `ShiftRefiner`, a deterministic stand-in refiner that adds every observed key moved
by +1 voxel along x (inside the band), so a sample's ``points`` differ from its ``observed`` keys (with
the real ``none`` refiner both are identical).
"""

from __future__ import annotations

import datetime
import multiprocessing
import os
import tempfile
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np
import numpy.typing as npt

from datagen.engine.shard_payload import task_payload
from datagen.pipeline.keys import pack_keys, unpack_keys
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine import make_refiner
from datagen.pipeline.refine.base import Refiner, RefineRequest
from datagen.pipeline.task import TaskResult, run_task
from datagen.pipeline.thread_limits import single_threaded_blas
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig
from schemas.dataset import DatasetInfo
from schemas.version import SCHEMA_VERSION
from storage.dataset import finalise, init_dataset, write_task
from storage.store import open_location

# Cheap built-ins (each task well under a second); the torus knots take 10-60 s to label, avoid them.
SMALL_OBJECTS = ("capsule", "l_bracket", "chair")
TRAINING_OBJECTS = (
    "box_with_hole",
    "box_with_two_holes",
    "capsule",
    "chair",
    "cone",
    "cylinder_and_ball",
    "dumbbell",
    "gear",
    "hex_nut",
    "l_bracket",
    "mushroom",
    "stacked_cylinders",
)


class ShiftRefiner:
    """R(O) = keys(O) moved by +1 voxel along x: deterministic, inside the band, never empty."""

    name = "test-shift"
    weights_id = ""

    def refine(self, requests: Sequence[RefineRequest]) -> list[npt.NDArray[np.int64]]:
        out = []
        for request in requests:
            keys = unpack_keys(request.observation.keys)
            out.append(np.unique(pack_keys(keys + np.array([1, 0, 0]))))
        return out


@dataclass(frozen=True)
class ExpectedSample:
    """What the pipeline produced for one sample (independent of the readers under test)."""

    object_id: str
    object_name: str
    rotation: int
    case: int
    label: int
    points: npt.NDArray[np.int64]
    """Packed keys of P(O_S), sorted."""
    observed: npt.NDArray[np.int64]
    """Packed keys of keys(O_S), sorted."""


@dataclass(frozen=True)
class Built:
    url: str
    config: GenerationConfig
    samples: dict[str, ExpectedSample]
    """By sample id."""

    @property
    def objects(self) -> set[str]:
        return {s.object_id for s in self.samples.values()}


def objects_file(folder: Path, names: Sequence[str], rename: dict[str, str] | None = None) -> Path:
    """An objects file listing built-ins (``rename`` gives some of them a ``name=``)."""
    rename = rename or {}
    path = folder / "objects.txt"
    lines = [f"builtin:{n}" + (f" name={rename[n]}" if n in rename else "") for n in names]
    path.write_text("\n".join(lines) + "\n")
    return path


def dataset_info(config: GenerationConfig) -> DatasetInfo:
    view_space = build_view_space(config.view_space)
    return DatasetInfo(
        schema_version=SCHEMA_VERSION,
        config=config,
        config_hash=config.config_hash(),
        view_positions=[tuple(p) for p in view_space.positions.tolist()],
        versions={},
        created=datetime.datetime(2024, 1, 1).isoformat(),
    )


def expected_of(result: TaskResult) -> dict[str, ExpectedSample]:
    return {
        s.sample_id: ExpectedSample(
            object_id=result.object_id,
            object_name=result.object_name,
            rotation=result.rotation,
            case=s.case,
            label=s.label,
            points=np.asarray(s.points),
            observed=np.asarray(s.observed),
        )
        for s in result.samples
    }


def build_dataset(
    url: str,
    names: Sequence[str],
    config: GenerationConfig,
    refiner: Refiner | None = None,
    rotations: Sequence[int] | None = None,
    rename: dict[str, str] | None = None,
    finalise_index: bool = True,
    processes: int = 1,
) -> Built:
    """Run every task (object x rotation) and write it to the dataset at ``url`` (``processes`` > 1:
    tasks run and commit in forked worker processes, as concurrent jobs would).

    Writing into an existing dataset of the same config adds tasks (as a second job would).
    """
    chosen = list(rotations) if rotations is not None else list(range(config.rotations))
    location = open_location(url)
    init_dataset(location, dataset_info(config))
    expected: dict[str, ExpectedSample] = {}
    with tempfile.TemporaryDirectory() as folder:
        listing = objects_file(Path(folder), names, rename)
        count = len(read_objects_file(listing).objects)
        jobs = [(str(listing), i, r, config, refiner, url) for i in range(count) for r in chosen]
        if processes > 1:
            context = multiprocessing.get_context("fork")
            with ProcessPoolExecutor(processes, mp_context=context) as pool:
                for part in pool.map(_run_and_write, jobs):
                    expected.update(part)
        else:
            for job in jobs:
                expected.update(_run_and_write(job))
    if finalise_index:
        finalise(location)
    return Built(url=url, config=config, samples=expected)


def _run_and_write(
    job: tuple[str, int, int, GenerationConfig, Refiner | None, str],
) -> dict[str, ExpectedSample]:
    listing, index, rotation, config, refiner, url = job
    spec = read_objects_file(listing).objects[index]
    with single_threaded_blas():
        prepared = prepare_object(spec, config)
        view_space = build_view_space(config.view_space)
        result = run_task(prepared, rotation, config, view_space, refiner or make_refiner(config))
        write_task(open_location(url), task_payload(result, config), "a0")
    return expected_of(result)


_CACHE: dict[str, Built] = {}


def cached_dataset(kind: str, root: Path) -> Built:
    """A dataset built once per session (``root`` is a session-scoped temporary folder).

    kinds: ``small`` (3 cheap objects x 2 rotations, ShiftRefiner: points != observed),
    ``training`` (`TRAINING_OBJECTS` x 4 rotations, refiner none).
    """
    if kind not in _CACHE:
        path = root / kind
        if kind == "small":
            config = GenerationConfig(rotations=2, refiner="none")
            built = build_dataset(str(path), SMALL_OBJECTS, config, refiner=ShiftRefiner())
        elif kind == "training":
            config = GenerationConfig(rotations=4, refiner="none")
            built = build_dataset(str(path), TRAINING_OBJECTS, config, processes=2)
        else:
            raise KeyError(kind)
        _CACHE[kind] = built
    return _CACHE[kind]


def keys_of_points(points: npt.ArrayLike, config: GenerationConfig) -> tuple[npt.NDArray[np.int64], float]:
    """Packed keys of voxel centres and the largest distance of a point from its key's centre (m)."""
    p = np.asarray(points, dtype=np.float64)
    offset = np.asarray(config.grid_offset, dtype=np.float64)
    keys = np.floor(p / config.voxel_size + offset).astype(np.int64)
    centres = (keys + 0.5 - offset) * config.voxel_size
    return pack_keys(keys), float(np.abs(p - centres).max()) if p.size else 0.0


def bits(mask: int, width: int) -> npt.NDArray[np.float32]:
    return np.array([(mask >> v) & 1 for v in range(width)], dtype=np.float32)
