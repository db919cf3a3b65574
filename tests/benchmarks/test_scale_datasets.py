"""The storage side of the scale benchmark in small: `benchmarks.scale.datasets` writes a real
dataset's tasks again as new objects through the real writer, and the result is a dataset
`storage.validate` accepts (every task, object and sample id distinct, each version-4-or-later cloud
in its new object's seeded order); the probe measures an operation on it in a process of its own."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from support import storage as fx

from benchmarks.scale import datasets
from benchmarks.scale.probe import PROBES
from storage import open_dataset, validate
from storage.dataset import pack_dataset


@pytest.fixture(scope="module")
def replicated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("scale")
    fx.build_dataset(str(folder / "source"), finalise_index=True)
    datasets.replicate(str(folder / "source"), str(folder / "many"), tasks=7, processes=1)
    return folder / "many"


def test_replicas_are_a_valid_dataset_of_distinct_tasks(replicated: Path) -> None:
    dataset = open_dataset(str(replicated))
    tasks = dataset.column("task_id").to_pylist()
    assert len(set(tasks)) == 7 and len(set(dataset.column("object_id").to_pylist())) == 7
    assert len(set(dataset.column("sample_id").to_pylist())) == len(dataset)
    assert validate(str(replicated), full=True) == []  # the clouds in each new object's order included
    packed = replicated.with_name("packed")
    pack_dataset(str(replicated), str(packed), target_bytes=300_000)
    assert validate(str(packed), full=True) == []


def test_the_probe_reports_its_own_seconds(replicated: Path, tmp_path: Path) -> None:
    report = tmp_path / "report.json"
    probe = Path(datasets.__file__).with_name("probe.py")
    for operation in ("open", "sample", "ls", "stats"):
        assert operation in PROBES
        done = subprocess.run(
            [sys.executable, str(probe), operation, str(replicated), str(report)], check=True, capture_output=True
        )
        found = json.loads(report.read_text())
        assert found["seconds"] > 0 and found["requests"] == 0
        if operation == "ls":  # the command ran in the probe's process: its table is the output
            assert b"committed" in done.stdout
