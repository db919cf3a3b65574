"""The large datasets of the storage-side scale benchmark, made without hours of imaging.

    python -m benchmarks.scale.datasets source --out /tmp/datagen-scale/source
    python -m benchmarks.scale.datasets replicate --source /tmp/datagen-scale/source --tasks 100000 \\
        --out /tmp/datagen-scale/tasks-100000 [--processes 2]

``source`` runs a real job (`datagen submit`): 12 synthetic objects (``objects synth --seed 1``) at
2 rotations, refiner ``none`` and 12 mm voxels, so that a task holds about 60 samples in about
300 KB (the paper's 2 mm voxels and POCO make 1-5 MB).

``replicate`` writes N tasks through the real writer and commit path (`storage.write_task`, then
`storage.finalise`): task k is source task ``k % S`` committed as a new object, copy ``k // S`` of
it, whose object id is the SHA-256 of the source's id and the copy number, so every task, object and
sample id is distinct, and the points of each version-4-or-later cloud are put in the new object's
seeded order (`schemas.shard.point_order`). Every array is a real task's, so the dataset is one that
`datagen shards validate` accepts, at whatever size: 100,000 tasks are about 6 million samples.

The functions use only the storage API that every version of this code has (`open_dataset`,
`ShardReader`, `write_task`, `finalise`), so an older checkout run with its own tree first on
``PYTHONPATH`` makes its own layout of the same dataset, for a baseline measured beside it.
"""

from __future__ import annotations

import argparse
import hashlib
import multiprocessing
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

SOURCE_CONFIG = 'rotations = 2\nrefiner = "none"\nvoxel_size = 0.012\n'
SOURCE_OBJECTS = 12
SOURCE_SEED = 1
ATTEMPT = "a1-scale"


def make_source(out: Path) -> None:
    """A real job's dataset at ``out`` (skipped when it is there): see the module's docstring."""
    if (out / "dataset.json").exists():
        print(f"{out}: there already", file=sys.stderr)
        return
    inputs = out.parent / f"{out.name}-inputs"
    inputs.mkdir(parents=True, exist_ok=True)
    (inputs / "config.toml").write_text(SOURCE_CONFIG)
    datagen = [sys.executable, "-m", "datagen.cli.main"]
    synth = ["objects", "synth", "--count", str(SOURCE_OBJECTS), "--seed", str(SOURCE_SEED), "--out", str(inputs)]
    subprocess.run([*datagen, *synth], check=True)
    submit = ["submit", "--objects", str(inputs / "objects.txt"), "--config", str(inputs / "config.toml")]
    env = {**os.environ, "DATAGEN_HOME": str(inputs / "home")}
    subprocess.run([*datagen, *submit, "--out", str(out)], check=True, env=env)


@dataclass(frozen=True)
class Template:
    """One source task, as `storage.write_task` takes it."""

    attributes: Any
    arrays: dict[str, npt.NDArray[Any]]
    rows: dict[str, list[Any]]
    seed: int


def templates(source: str) -> list[Template]:
    """Every committed task of the source dataset, in task id order."""
    import pyarrow.compute as pc

    import storage
    from schemas.shard import array_names
    from storage import ShardReader

    found = storage.open_dataset(source)
    index = found.index
    out = []
    for record in storage.committed_tasks(found.location):
        reader = ShardReader(found.location, record.shard)
        arrays = {name: np.asarray(reader.array(name)) for name in array_names(reader.attributes.schema_version)}
        rows = index.filter(pc.equal(index["shard"], record.shard)).sort_by("row")
        columns = {c: rows.column(c).to_pylist() for c in rows.column_names if c not in ("shard", "row", "attempt_id")}
        out.append(Template(reader.attributes, arrays, columns, int(found.info.config.seed)))
    return out


def copy_of(template: Template, copy: int) -> Any:
    """Copy ``copy`` of a source task as a new object (copy 0: the task itself), its payload."""
    from schemas.shard import ordered_points
    from storage import ShardPayload

    source = template.attributes
    if copy == 0:
        return ShardPayload(source, template.arrays, template.rows)
    object_id = hashlib.sha256(f"{source.object_id}:{copy}".encode()).hexdigest()
    task_id = f"{object_id[:16]}-r{source.rotation}"
    name = f"{source.object_name}-c{copy}"
    arrays = dict(template.arrays)
    if ordered_points(source.schema_version, "points"):
        arrays["points_keys"] = _reordered(template, object_id)
    rows = dict(template.rows)
    count = source.num_samples
    rows["task_id"] = [task_id] * count
    rows["object_id"] = [object_id] * count
    rows["object_name"] = [name] * count
    rows["sample_id"] = [f"{task_id}-{sample.rsplit('-', 1)[1]}" for sample in template.rows["sample_id"]]
    attributes = source.model_copy(update={"task_id": task_id, "object_id": object_id, "object_name": name})
    return ShardPayload(attributes, arrays, rows)


def _reordered(template: Template, object_id: str) -> npt.NDArray[Any]:
    """The source's stored clouds put back in sorted order, then in the new object's seeded order."""
    from schemas.shard import VIEW_STATE_COLUMN, point_order

    source = template.attributes
    keys, offsets = template.arrays["points_keys"], template.arrays["points_offsets"]
    cases = template.arrays["masks"][:, VIEW_STATE_COLUMN]
    out = np.empty_like(keys)
    for i, case in enumerate(cases.tolist()):
        start, stop = int(offsets[i]), int(offsets[i + 1])
        count = stop - start
        old = point_order(template.seed, source.object_id, source.rotation, int(case), count)
        new = point_order(template.seed, object_id, source.rotation, int(case), count)
        ordered = np.empty_like(keys[start:stop])
        ordered[old] = keys[start:stop]
        out[start:stop] = ordered[new]
    return out


_TEMPLATES: list[Template] = []


def _write_range(job: tuple[str, int, int]) -> int:
    """Write tasks ``start`` to ``stop`` (a worker process's share); returns the samples written."""
    from storage import open_location, write_task

    out, start, stop = job
    location = open_location(out)
    samples = 0
    for k in range(start, stop):
        template = _TEMPLATES[k % len(_TEMPLATES)]
        payload = copy_of(template, k // len(_TEMPLATES))
        write_task(location, payload, ATTEMPT)
        samples += payload.attributes.num_samples
    return samples


def replicate(source: str, out: str, tasks: int, processes: int) -> None:
    """Write ``tasks`` tasks at ``out`` (see the module's docstring), then finalise its index."""
    import storage
    from storage import finalise, init_dataset, open_location

    started = time.perf_counter()
    _TEMPLATES[:] = templates(source)
    location = open_location(out)
    init_dataset(location, storage.open_dataset(source).info)
    step = 2000
    jobs = [(out, a, min(a + step, tasks)) for a in range(0, tasks, step)]
    written = 0
    context = multiprocessing.get_context("fork")
    with context.Pool(processes) as pool:
        for samples in pool.imap(_write_range, jobs):
            written += samples
            print(f"{written} samples, {time.perf_counter() - started:.0f} s", file=sys.stderr, flush=True)
    wrote = time.perf_counter() - started
    finalise(location)
    print(
        f"{out}: {tasks} tasks, {written} samples; written in {wrote:.0f} s, finalised in "
        f"{time.perf_counter() - started - wrote:.0f} s",
        file=sys.stderr,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    source = commands.add_parser("source", help="run the real job whose tasks are replicated")
    source.add_argument("--out", type=Path, required=True)
    many = commands.add_parser("replicate", help="write N tasks from the source's")
    many.add_argument("--source", required=True)
    many.add_argument("--out", required=True)
    many.add_argument("--tasks", type=int, required=True)
    many.add_argument("--processes", type=int, default=2)
    args = parser.parse_args()
    if args.command == "source":
        make_source(args.out)
    else:
        replicate(args.source, args.out, args.tasks, args.processes)


if __name__ == "__main__":
    main()
