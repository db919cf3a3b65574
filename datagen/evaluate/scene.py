"""The simulated world of one evaluation: an object at one rotation and what each candidate view sees.

A view's observation is computed once, by the generator's own imaging (`scan_task`), so "visiting" a
view in the simulated online run returns exactly the keys V_i the generator labelled with. The
reference count is the authors' (docs/authors-code.md section 8.1): the distinct keys visible
from all candidate views together; coverage against every key of P_gt is reported beside it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from datagen.pipeline.imaging import TaskImaging
from datagen.pipeline.keys import union_keys
from datagen.pipeline.objects.prepare import PreparedObject
from datagen.pipeline.scanning import scan_task
from datagen.pipeline.viewspace import ViewSpace
from schemas.config import GenerationConfig

OBSTACLE_SCALE = math.sqrt(2.0) * 17.0 / 16.0
"""Obstacle radius / bounding radius. The authors take r = ps·sqrt(2) with ps = 17/16 of the object's
largest distance from its centre (docs/authors-code.md sections 2.10 and 8.2)."""


@dataclass(frozen=True)
class Scene:
    """One object at one rotation in the task frame (object centre at the origin, views around it)."""

    prepared: PreparedObject
    rotation: int
    scan: TaskImaging
    positions: npt.NDArray[np.float64]
    """Camera centre of each candidate view, metres."""
    obstacle_radius: float
    """Radius of the sphere about the origin that camera moves skirt (`datagen.evaluate.path`)."""
    reference: npt.NDArray[np.int64]
    """Sorted packed keys visible from all candidate views together: the coverage denominator."""
    view_columns: tuple[npt.NDArray[np.int64], ...]
    """For each view, the positions of its keys V_i in `reference` (so unions are boolean ORs)."""

    @property
    def object_name(self) -> str:
        return self.prepared.spec.name

    @property
    def object_id(self) -> str:
        return self.prepared.spec.object_id

    @property
    def num_views(self) -> int:
        return len(self.view_columns)

    @property
    def ground_truth_size(self) -> int:
        return len(self.scan.ground_truth)

    def seen(self, views: Iterable[int]) -> npt.NDArray[np.bool_]:
        """Which reference keys the given views observe together."""
        covered = np.zeros(self.reference.size, dtype=bool)
        for view in views:
            covered[self.view_columns[view]] = True
        return covered

    def observed_points(self, views: Iterable[int]) -> npt.NDArray[np.float32]:
        """The accumulated cloud: every surface point the given views hit, metres."""
        clouds = [self.scan.observations[v].points for v in sorted(set(views))]
        return np.concatenate(clouds) if clouds else np.empty((0, 3), dtype=np.float32)


def obstacle_radius(prepared: PreparedObject, view_radius: float) -> float:
    """The authors' obstacle sphere, never larger than the sphere the views sit on (a camera inside the
    obstacle would have no defined local path)."""
    return min(OBSTACLE_SCALE * prepared.bounding_radius, view_radius)


def build_scene(prepared: PreparedObject, rotation: int, config: GenerationConfig, view_space: ViewSpace) -> Scene:
    """Image the object at ``rotation`` from every candidate view, exactly as the generator does."""
    scan = scan_task(prepared, rotation, config, view_space)
    visible = [o.keys for o in scan.observations]
    reference = union_keys(*visible)
    columns = tuple(np.searchsorted(reference, keys) for keys in visible)
    return Scene(
        prepared=prepared,
        rotation=rotation,
        scan=scan,
        positions=np.asarray(view_space.positions, dtype=np.float64),
        obstacle_radius=obstacle_radius(prepared, config.view_space.radius),
        reference=reference,
        view_columns=columns,
    )
