"""Write a small real dataset for the osvp tests with datagen's pipeline.

Run as a script by conftest.py in a subprocess, so that the osvp test process itself never imports
datagen: capsule, cone and torus at 2 rotations, refiner none (seconds, no Ray). With V1_OUT, the
same tasks are also written in schema version 1 (no minimum covers), as an older datagen wrote them.
`main` also takes another refiner, objects and rotation count (the light-install test makes a POCO
dataset with it).

    python make_dataset.py OUT [V1_OUT]
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from datagen.engine.shard_payload import task_payload
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine.factory import make_refiner
from datagen.pipeline.task import run_task
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig
from schemas.dataset import DatasetInfo
from schemas.version import SCHEMA_VERSION
from storage import finalise, init_dataset, open_location, write_task

OBJECTS = ("builtin:capsule", "builtin:cone", "builtin:torus")


def main(
    out: str, v1_out: str | None = None, refiner: str = "none", objects: tuple[str, ...] = OBJECTS, rotations: int = 2
) -> None:
    config = GenerationConfig(refiner=refiner, rotations=rotations)
    view_space = build_view_space(config.view_space)
    targets = [(open_location(out), SCHEMA_VERSION)] + ([(open_location(v1_out), 1)] if v1_out else [])
    for location, version in targets:
        init_dataset(
            location,
            DatasetInfo(
                schema_version=version,
                config=config,
                config_hash=config.config_hash(),
                view_positions=[tuple(p) for p in view_space.positions.tolist()],
                versions={},
                created="2026-01-01T00:00:00",
            ),
        )
    refiner = make_refiner(config)
    with tempfile.TemporaryDirectory() as folder:
        listing = Path(folder) / "objects.txt"
        listing.write_text("".join(f"{source}\n" for source in objects))
        specs = read_objects_file(listing).objects
    for spec in specs:
        prepared = prepare_object(spec, config)
        for rotation in range(config.rotations):
            result = run_task(prepared, rotation, config, view_space, refiner)
            for location, version in targets:
                write_task(location, task_payload(result, config, version), "a1")
    for location, _ in targets:
        finalise(location)


if __name__ == "__main__":
    main(*sys.argv[1:3])
