"""What a planner is asked at the start of one simulated run, built lazily and once.

`RefinedScene` refines the scene's single views with one refiner, exactly as generation does
(`datagen.pipeline.task.refine_views` and `case_inputs`), so a planner's input is the sample input a
dataset would hold for that case, and the oracle's answer is the label it would hold. `Situation` is
one initial view of a refined scene: trained planners read only `request()`; the baselines may also
read the truth (the scene, the generator's label, a seeded stream).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import numpy.typing as npt

from datagen.evaluate.scene import Scene
from datagen.pipeline.coverage import Coverage, coverage_table
from datagen.pipeline.keys import key_centres, unpack_keys
from datagen.pipeline.objectives import CaseLabeller, task_labeller
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.refine.base import Refiner
from datagen.pipeline.setcover import CoverResult, LabelError
from datagen.pipeline.task import RefinedViews, case_inputs, refine_views
from schemas.config import GenerationConfig

LABEL_FIELDS = ("alpha", "label_objective", "label_budget", "label_tau", "label_tie_break")
"""The config fields a label depends on beyond the scene and its refinement."""


def needs_refinement(config: GenerationConfig) -> bool:
    """Whether labels under ``config`` read the refined views (the paper's cover objective does; the
    visibility objectives read only what each view sees)."""
    return config.objective.needs_refinement


@dataclass(frozen=True)
class PlanRequest:
    """A trained planner's whole input: the sample a dataset would hold for this case, minus its label."""

    initial_view: int
    num_views: int
    view_state: npt.NDArray[np.float32]
    """(n,) 0/1: the views already taken."""
    points: npt.NDArray[np.float32]
    """(N, 3) key centres of P(O_S), the refined cloud (a shard's ``points``), metres, task frame."""
    observed: npt.NDArray[np.float32]
    """(M, 3) key centres of what the input views saw (a shard's ``observed``)."""


class RefinedScene:
    """A scene with every single view refined by one refiner; the coverage table built on demand."""

    def __init__(self, scene: Scene, refiner: Refiner, config: GenerationConfig) -> None:
        self.scene = scene
        self.refiner = refiner
        self.config = config
        self.refine_seconds = 0.0
        self._labellers: dict[tuple[object, ...], CaseLabeller] = {}

    @cached_property
    def views(self) -> RefinedViews:
        started = time.perf_counter()
        views = refine_views(self.scene.scan, self.refiner, self.config, self.scene.object_id, self.scene.rotation)
        self.refine_seconds = time.perf_counter() - started
        return views

    @cached_property
    def coverage(self) -> Coverage:
        """P_full and its coverage masks for the config's alpha."""
        return coverage_table(self.views.sets.refined, self.config.alpha)

    def labeller(self, config: GenerationConfig | None = None) -> CaseLabeller:
        """The generator's labeller of this scene under ``config`` (default: the scene's own), built once
        per label setting; the paper's objective refines the views first, the visibility ones never do."""
        config = self.config if config is None else config
        key = tuple(getattr(config, name) for name in LABEL_FIELDS)
        labellers = self._labellers
        if key not in labellers:
            coverage = None
            if needs_refinement(config):
                same = config.alpha == self.config.alpha
                coverage = self.coverage if same else coverage_table(self.views.sets.refined, config.alpha)
            visible = tuple(o.keys for o in self.scene.scan.observations)
            labellers[key] = task_labeller(visible, coverage, config, list_covers=False)
        return labellers[key]

    def relabelled(self, config: GenerationConfig) -> RefinedScene:
        """The same refined views labelled under another config (another alpha): no new refinement."""
        other = RefinedScene(self.scene, self.refiner, config)
        other.__dict__["views"] = self.views  # seeds the cached property
        other.refine_seconds = self.refine_seconds
        return other

    def request(self, initial_view: int) -> PlanRequest:
        case = 1 << initial_view
        points, observed = case_inputs(
            self.views, [case], self.refiner, self.config, self.scene.object_id, self.scene.rotation
        )[case]
        state = np.zeros(self.scene.num_views, dtype=np.float32)
        state[initial_view] = 1.0
        return PlanRequest(
            initial_view=initial_view,
            num_views=self.scene.num_views,
            view_state=state,
            points=self._centres(points),
            observed=self._centres(observed),
        )

    def label(self, initial_view: int, config: GenerationConfig | None = None) -> CoverResult:
        """The label generation computes for the single-view case ``initial_view`` (under ``config``'s
        label settings; default: the scene's)."""
        return self.labeller(config).label(1 << initial_view)

    def _centres(self, packed: npt.NDArray[np.int64]) -> npt.NDArray[np.float32]:
        return key_centres(unpack_keys(packed), self.config.voxel_size, self.config.grid_offset).astype(np.float32)


class Situation:
    """One initial view of a refined scene: the question every planner answers."""

    def __init__(self, refined: RefinedScene, initial_view: int) -> None:
        if not (0 <= initial_view < refined.scene.num_views):
            raise ValueError(f"initial view {initial_view} is outside 0..{refined.scene.num_views - 1}")
        self.refined = refined
        self.initial_view = initial_view
        self._labels: dict[int, CoverResult] = {}

    @property
    def scene(self) -> Scene:
        return self.refined.scene

    @property
    def config(self) -> GenerationConfig:
        return self.refined.config

    @cached_property
    def _request(self) -> PlanRequest:
        return self.refined.request(self.initial_view)

    def prepare(self) -> None:
        """Do the generator's share now (refine every view, build the coverage table and this case's
        input) so that a planner's timed call measures planning alone."""
        if needs_refinement(self.config):
            self.refined.labeller()
        self._request  # noqa: B018

    @property
    def input_seconds(self) -> float:
        """Time to refine one view of this scene (the scene's single-view refinement time / n): what the
        one-shot pipeline spends on its input before the planner runs."""
        return self.refined.refine_seconds / self.scene.num_views

    def request(self) -> PlanRequest:
        """The sample input for this case (refines the scene's views on first use)."""
        return self._request

    def oracle_label(self, config: GenerationConfig | None = None) -> CoverResult:
        """The generator's exact label for this case, under ``config``'s label settings (default: the
        scene's); raises `LabelError` if the solver gives up. Computed once per label setting."""
        labeller = self.refined.labeller(config)
        if id(labeller) not in self._labels:  # the scene keeps every labeller it built: ids stay unique
            self._labels[id(labeller)] = labeller.label(1 << self.initial_view)
        return self._labels[id(labeller)]

    def rng(self) -> np.random.Generator:
        """A fresh seeded stream for this (object, rotation, initial view), independent of all others."""
        scene, case = self.scene, 1 << self.initial_view
        return stream(self.config.seed, scene.object_id, scene.rotation, Purpose.EVALUATION, mask=case)


__all__ = ["LabelError", "PlanRequest", "RefinedScene", "Situation"]
