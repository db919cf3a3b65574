"""Scan one task: the mesh in the task frame, its ground truth P_gt and the n views' observations.

Steps 1.6-3 of docs/pipeline.md composed; pure, no files, no Ray.
"""

from __future__ import annotations

from datagen.pipeline.ground_truth import sample_ground_truth
from datagen.pipeline.imaging import TaskImaging, image_task
from datagen.pipeline.objects.prepare import PreparedObject
from datagen.pipeline.random_streams import Purpose, stream
from datagen.pipeline.step_timing import StepClock, timed
from datagen.pipeline.viewspace import ViewSpace
from schemas.config import GenerationConfig


def scan_task(
    prepared: PreparedObject,
    rotation: int,
    config: GenerationConfig,
    view_space: ViewSpace,
    clock: StepClock | None = None,
) -> TaskImaging:
    """P_gt and every view's observation for task (object, rotation); ``clock`` times the two steps."""
    if not (0 <= rotation < config.rotations):
        raise ValueError(f"rotation {rotation} is outside 0..{config.rotations - 1}")
    vertices = prepared.task_vertices(rotation, config.rotations)
    rng = stream(config.seed, prepared.spec.object_id, rotation, Purpose.GROUND_TRUTH)
    with timed(clock, "ground_truth"):
        ground_truth = sample_ground_truth(
            vertices, prepared.faces, config.voxel_size, config.grid_offset, config.gt_density, rng
        )
    with timed(clock, "imaging"):
        return image_task(vertices, prepared.faces, ground_truth, view_space, config)
