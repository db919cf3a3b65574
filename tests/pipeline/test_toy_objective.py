"""A label objective added from this test module alone (issue 42): one `register_objective` call with
its labeller and its judge, no other file touched. The config takes it by name, a dataset made with it
validates (its judge checks every label), its judge names a wrong label, and an unknown objective is
refused by name.

The toy objective ``first_new_view``: the label is the lowest-index view outside the case that sees a
key the case has not seen (empty when none does), judged on what each view sees.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from datagen.engine.driver import dataset_info
from datagen.engine.job_plan import object_ref
from datagen.engine.worker import execute_task
from datagen.pipeline.coverage import Coverage
from datagen.pipeline.maxcover import visibility_masks
from datagen.pipeline.objectives import task_labeller
from datagen.pipeline.objects.objects_file import read_objects_file
from datagen.pipeline.setcover import CoverAmbiguity, CoverResult
from schemas.config import GenerationConfig
from schemas.jobs import TaskSpec
from schemas.objectives import OBJECTIVES, Objective, UnknownObjective, objective_named, register_objective
from storage import finalise, init_dataset, open_dataset, open_location, validate
from storage.samples import JudgedTask, VisibilityJudge, task_judge

NAME = "first_new_view"


class FirstNewView:
    """The toy labeller of one task."""

    def __init__(self, visible: tuple[np.ndarray, ...], config: GenerationConfig) -> None:
        self.masks, _ = visibility_masks(visible)
        self.num_views = config.num_views

    def label(self, case: int, threads: int = 1) -> CoverResult:
        unseen = self.masks[(self.masks & np.uint64(case)) == 0]
        every = int(np.bitwise_or.reduce(unseen)) if unseen.size else 0
        label = every & -every  # the lowest set bit: the first view seeing something new
        return CoverResult(
            label=label,
            status="optimal" if label else "empty",
            objective=label.bit_count(),
            rows_before=int(unseen.size),
            rows_after=int(unseen.size),
            seconds=0.0,
            proof="search" if label else "none",
            ambiguity=CoverAmbiguity(covers=(label,), count=1, exact=True, support=label),
        )


def first_new_view_labeller(
    visible: tuple[np.ndarray, ...], coverage: Coverage | None, config: GenerationConfig, list_covers: bool
) -> FirstNewView:
    return FirstNewView(visible, config)


class FirstNewViewJudge(VisibilityJudge):
    def label_problem(self, case: int, label: int) -> str | None:
        for view in range(self.config.num_views):
            bit = 1 << view
            if not case & bit and self.seen(case | bit) > self.seen(case):
                return None if label == bit else f"label is not view {view}, the first that sees a new key"
        return None if label == 0 else "label is not empty, though no view sees a new key"


@pytest.fixture(scope="module", autouse=True)
def toy_objective():
    register_objective(
        Objective(
            name=NAME,
            judged_on="visible",
            labeller=first_new_view_labeller,
            judge=FirstNewViewJudge,
            oracle_settings={},
        )
    )
    yield
    del OBJECTIVES[NAME]


SMALL = {"rotations": 1, "voxel_size": 0.004, "alpha": 3, "refiner": "none"}


def test_the_config_takes_a_registered_objective_and_refuses_an_unknown_one_by_name() -> None:
    config = GenerationConfig(label_objective=NAME)
    assert config.objective is objective_named(NAME) and not config.objective.needs_refinement
    assert config.objective_text() == NAME
    with pytest.raises(
        ValidationError, match=r"unknown label objective 'nothing'; choose one of cover, .*first_new_view"
    ):
        GenerationConfig(label_objective="nothing")
    with pytest.raises(UnknownObjective, match="unknown label objective 'nothing'"):
        objective_named("nothing")


def test_a_dataset_made_with_the_toy_objective_validates(tmp_path: Path) -> None:
    config = GenerationConfig(label_objective=NAME, **SMALL)
    listing = tmp_path / "objects.txt"
    listing.write_text("builtin:capsule\nbuiltin:cone\n")
    out = str(tmp_path / "data")
    location = open_location(out)
    info = init_dataset(location, dataset_info(config))
    for spec in read_objects_file(listing).objects:
        task = TaskSpec(task_id=spec.task_id(0), object=object_ref(spec), rotation=0)
        outcome = execute_task(task, config, out, f"toy-{time.monotonic_ns()}", config_hash=info.config_hash)
        assert outcome.ok, outcome.message
    finalise(location)
    assert validate(out, full=True) == []
    dataset = open_dataset(out)
    assert dataset.info.config.label_objective == NAME and len(dataset) > 0
    labels = dataset.index.column("label").to_pylist()
    assert all(int(label).bit_count() <= 1 for label in labels) and any(labels)


def test_the_toy_judge_names_a_wrong_label() -> None:
    config = GenerationConfig(label_objective=NAME, **SMALL)
    visible = (np.array([1, 2]), np.array([2, 3]), np.array([1]), np.array([4]))
    labeller = task_labeller(visible, None, config)
    judge = task_judge(JudgedTask(np.empty(0, dtype=np.uint64), lambda: visible, config))
    assert labeller.label(0b0001).label == 0b0010  # view 1 sees key 3, new to view 0
    assert judge.label_problem(0b0001, 0b0010) is None
    assert judge.label_problem(0b0001, 0b1000) == "label is not view 1, the first that sees a new key"
    assert labeller.label(0b1011).label == 0  # nothing new is left for view 2
