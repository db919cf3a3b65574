"""The default refiner version's labels on built-in objects, as recorded when it became the default.

`recorded/default-version-labels.json` holds, for two tasks of ``builtin:capsule`` under the default
config (`schemas.config.LATEST_POCO_VERSION`), every sample's case, label and refined-cloud size. A
fresh run must give them again: the recorded run and this one are two runs; worker counts are
`tests/engine/test_engine.py`'s (one and two worker CPUs give identical samples).

Within one machine the pipeline is exact, so the record matches exactly (it did on the machine that
wrote it). Another CPU may round a float kernel of the network differently (their docstrings,
`PocoModel.decode_inference`), which can move a key across the threshold; so a cloud's size may move
by 0.5 % and one label of a task may differ, and no more. ``python tests/pipeline/test_default_version_record.py
--record`` writes the record again: only for a new default version, judged first
(`studies/labels/version_labels.py`).
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest

from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine import make_refiner
from datagen.pipeline.refine.poco.refiner import BUILTIN_WEIGHTS
from datagen.pipeline.task import TaskResult, run_task
from datagen.pipeline.thread_limits import fixed_torch_threads, single_threaded_blas
from datagen.pipeline.viewspace import build_view_space
from schemas.config import LATEST_POCO_VERSION, GenerationConfig

RECORDED = Path(__file__).parent / "recorded" / "default-version-labels.json"
OBJECT = "builtin:capsule"
ROTATIONS = (0, 3)
SIZE_TOLERANCE = 0.005
"""The most a refined cloud's size may move on another CPU (a fraction of the recorded size)."""

pytestmark = pytest.mark.skipif(not BUILTIN_WEIGHTS.is_file(), reason="no shipped POCO weights")


def run(rotation: int) -> TaskResult:
    """One task of `OBJECT` under the default config, as a worker runs it."""
    config = GenerationConfig()
    with tempfile.TemporaryDirectory() as folder:
        listing = Path(folder) / "objects.txt"
        listing.write_text(OBJECT + "\n", encoding="utf-8")
        (spec,) = read_objects_file(listing).objects
    with single_threaded_blas(), fixed_torch_threads():
        prepared = prepare_object(spec, config)
        return run_task(prepared, rotation, config, build_view_space(config.view_space), make_refiner(config))


def summary(result: TaskResult) -> dict[str, list[Any]]:
    """A task's samples as recorded: case and label masks (hex) and refined-cloud sizes, in row order."""
    return {
        "cases": [f"{s.case:08x}" for s in result.samples],
        "labels": [f"{s.label:08x}" for s in result.samples],
        "points": [int(s.points.size) for s in result.samples],
    }


def record() -> None:
    config = GenerationConfig()
    tasks = {str(rotation): summary(run(rotation)) for rotation in ROTATIONS}
    head = {"object": OBJECT, "poco_version": config.poco_version, "config_hash": config.config_hash()}
    lines = [f" {json.dumps(key)}: {json.dumps(value)}," for key, value in head.items()]
    rows = [f"  {json.dumps(rotation)}: {json.dumps(task)}" for rotation, task in tasks.items()]
    RECORDED.write_text("{\n" + "\n".join(lines) + '\n "tasks": {\n' + ",\n".join(rows) + "\n }\n}\n", encoding="utf-8")


def test_the_record_is_of_the_default_version() -> None:
    """A new default version needs a new record (and a judgement first)."""
    recorded = json.loads(RECORDED.read_text(encoding="utf-8"))
    assert recorded["poco_version"] == GenerationConfig().poco_version == LATEST_POCO_VERSION
    assert recorded["config_hash"] == GenerationConfig().config_hash()


@pytest.mark.parametrize("rotation", ROTATIONS)
def test_the_default_version_gives_the_recorded_labels(rotation: int) -> None:
    expected = json.loads(RECORDED.read_text(encoding="utf-8"))["tasks"][str(rotation)]
    found = summary(run(rotation))
    assert len(expected["cases"]) > 20
    labels = dict(zip(found["cases"], found["labels"], strict=True))
    recorded_labels = dict(zip(expected["cases"], expected["labels"], strict=True))
    differing = sorted(c for c in labels.keys() | recorded_labels.keys() if labels.get(c) != recorded_labels.get(c))
    assert len(differing) <= 1, differing
    sizes = dict(zip(found["cases"], found["points"], strict=True))
    for case, recorded_size in zip(expected["cases"], expected["points"], strict=True):
        if case in sizes:
            assert abs(sizes[case] - recorded_size) <= SIZE_TOLERANCE * recorded_size, case


if __name__ == "__main__":
    if sys.argv[1:] != ["--record"]:
        raise SystemExit(f"usage: python {sys.argv[0]} --record")
    record()
