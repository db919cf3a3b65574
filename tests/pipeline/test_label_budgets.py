"""Labels decided by work budgets, never by the clock (issue 52, finding 11).

- A case past HiGHS's node budget is left out and recorded, the same on every machine.
- A solve past the wall-clock safety net fails the whole task, naming the case: never a case quietly
  left out because the machine was busy.
- The same task run alone and beside CPU-starving competitors makes the same samples.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import time
from pathlib import Path

import numpy as np
import pytest

from datagen.pipeline import setcover
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.objects.prepare import prepare_object
from datagen.pipeline.refine.factory import make_refiner
from datagen.pipeline.setcover import LabelError, SolverTimeLimit, TaskCover
from datagen.pipeline.task import label_cases, run_task
from datagen.pipeline.viewspace import build_view_space
from schemas.config import GenerationConfig


def hard_rows() -> np.ndarray:
    """Rows no shortcut settles (each key seen by three of 24 views, seeded): HiGHS decides the size."""
    rng = np.random.default_rng(7)
    rows = [sum(1 << int(v) for v in rng.choice(24, size=3, replace=False)) for _ in range(400)]
    return np.array(rows, dtype=np.uint64)


@pytest.fixture
def highs_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """The search gives up at once, so every size comes from HiGHS."""
    monkeypatch.setattr(setcover, "SEARCH_NODE_BUDGET", 0)


def test_a_case_past_the_node_budget_is_left_out_and_recorded_alike(
    highs_only: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(setcover, "HIGHS_NODE_LIMIT", 1)
    cover = TaskCover(hard_rows(), 24)
    labels, failures = label_cases(cover, [1, 2])
    assert not labels and [f.case for f in failures] == [1, 2]
    assert all("within its work budget" in f.message and "1 nodes" in f.message for f in failures)
    with pytest.raises(LabelError):  # the same decision again: a count, not a time
        cover.label(1)


def test_a_solve_past_the_safety_net_fails_the_task_naming_the_case(
    highs_only: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(setcover, "SAFETY_NET_SECONDS", 1e-9)
    cover = TaskCover(hard_rows(), 24, time_limit=1e-9)
    with pytest.raises(SolverTimeLimit, match=r"case 0000000000000005 \(views 0, 2\): HiGHS ran past the wall-clock"):
        label_cases(cover, [5])


def _spin(stop: float) -> None:
    while time.time() < stop:
        pass


def _digest(result) -> str:  # type: ignore[no-untyped-def]
    digest = hashlib.sha256()
    for sample in result.samples:
        digest.update(repr((sample.case, sample.label, sample.cover.proof, sample.cover.objective)).encode())
    digest.update(repr([(f.case, f.message) for f in result.failures]).encode())
    return digest.hexdigest()


@pytest.mark.slow
def test_a_task_beside_cpu_starving_competitors_makes_the_same_samples(tmp_path: Path, highs_only: None) -> None:
    """Every size from HiGHS (the search gives up at once) under a clock of 20 ms a solve, as the config
    may say: before the budgets decided, the crowded run lost the cases whose solves the competitors
    slowed past the clock; now the clock is only a safety net and both runs make the same samples."""
    objects = tmp_path / "objects.txt"
    objects.write_text("builtin:cone\n")
    config = GenerationConfig(refiner="none", rotations=1, solver_time_limit=0.02)
    prepared = prepare_object(read_objects_file(objects).objects[0], config)
    view_space = build_view_space(config.view_space)

    def once() -> str:
        return _digest(run_task(prepared, 0, config, view_space, make_refiner(config)))

    alone = once()
    stop = time.time() + 600
    hogs = [multiprocessing.get_context("spawn").Process(target=_spin, args=(stop,)) for _ in range(6)]
    for hog in hogs:
        hog.start()
    try:
        crowded = once()
    finally:
        for hog in hogs:
            hog.terminate()
            hog.join()
    assert crowded == alone
