"""One engine-written dataset shared by the `datagen shards` tests, and a copy of it in fsspec's
memory filesystem (Ray workers cannot write there, so the copy is made file by file).

The job: capsule, cone and torus at 2 rotations (refiner none, so it takes seconds) plus a corrupt
mesh, whose 2 tasks fail with a message; so listings show both committed and failed tasks.
"""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from pathlib import Path

import fsspec
import pytest

from datagen import api
from datagen.settings import RunSettings
from jobs.ledger import FAILED
from support.engine import builtin_lines, start_local_ray, stop_local_ray, write_config, write_objects

BUILTINS = ("capsule", "cone", "torus")
ROTATIONS = 2


@dataclass(frozen=True)
class EngineDataset:
    url: str
    """Local path of the dataset the engine wrote."""
    memory_url: str
    """The same files under memory://."""
    objects_file: Path
    config_file: Path
    committed_tasks: int
    failed_tasks: int


def copy_to_memory(local: Path) -> str:
    url = f"memory://shards-{uuid.uuid4().hex[:8]}"
    fs = fsspec.filesystem("memory")
    root = url.removeprefix("memory://")
    for path in sorted(local.rglob("*")):
        if path.is_file():
            fs.pipe(f"{root}/{path.relative_to(local).as_posix()}", path.read_bytes())
    return url


@pytest.fixture(scope="session")
def engine_dataset(tmp_path_factory: pytest.TempPathFactory) -> EngineDataset:
    folder = tmp_path_factory.mktemp("shards-dataset")
    config = write_config(folder / "config.toml", rotations=ROTATIONS)
    (folder / "broken.obj").write_bytes(b"v 0 0 0\nv 1 0 0\nf 1 2 9\n" + bytes(range(256)) * 4)
    objects = write_objects(folder / "objects.txt", [*builtin_lines(BUILTINS), str(folder / "broken.obj")])
    start_local_ray(2)
    try:
        job = api.submit(objects, config, RunSettings(home=folder / "home", num_workers=2, ray_address=None))
    finally:
        stop_local_ray()
    assert job.state == FAILED and job.summary["done"] == len(BUILTINS) * ROTATIONS, job.summary
    failed = len(job.summary.get("failures", []))
    return EngineDataset(
        url=job.out,
        memory_url=copy_to_memory(Path(job.out)),
        objects_file=objects,
        config_file=config,
        committed_tasks=len(BUILTINS) * ROTATIONS,
        failed_tasks=failed,
    )
