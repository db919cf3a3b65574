"""The seeded streams of an export: a sample's draw of input points and a task's draw of ground-truth
points, from the export's seed and the sample's or task's id (part of its documented format).
"""

from __future__ import annotations

import hashlib

import numpy as np
import numpy.typing as npt


def _digest(name: str) -> int:
    return int.from_bytes(hashlib.sha256(name.encode()).digest()[:8], "little")


def sample_rng(seed: int, sample_id: str) -> np.random.Generator:
    """The stream that draws one sample's cloud: fixed by the seed and the sample id alone (the export's
    own, part of its documented format: not the (seed, epoch, index) streams of `storage.samples.resampling`,
    which depend on a dataset's order)."""
    return np.random.default_rng(np.random.SeedSequence([seed, _digest(sample_id)]))


GROUND_TRUTH_STREAM = 1
"""Appended to a task's stream so that its ground-truth draw never shares a sample's."""


def task_rng(seed: int, task_id: str) -> np.random.Generator:
    """The stream that draws a task's ground-truth cloud (one draw per task, shared by its samples)."""
    return np.random.default_rng(np.random.SeedSequence([seed, _digest(task_id), GROUND_TRUTH_STREAM]))


def draw(rng: np.random.Generator, count: int, size: int) -> tuple[npt.NDArray[np.int64], bool]:
    """``size`` of ``count`` indices, without replacement unless there are fewer; (indices, drawn with
    replacement)."""
    replace_ = count < size
    return rng.choice(count, size=size, replace=replace_), replace_
