"""Train / held-out splits of a dataset's samples, the same for every reader and trainer.

A split by object holds out ``round(fraction * objects)`` objects (at least one when the fraction is
positive) drawn by a permutation seeded with ``(seed, number of objects)``, so every sample of an
object lands on one side; a split by sample permutes the rows with ``(seed, number of samples)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from schemas.errors import DatagenError


class SplitError(DatagenError, ValueError):
    """A split cannot be made as asked (a fraction out of range, too few samples or objects)."""


def held_out_objects(objects: Sequence[str], fraction: float, seed: int) -> set[str]:
    """The objects a split by object holds out; ``objects`` are the distinct ids, sorted."""
    if not 0.0 <= fraction <= 1.0:
        raise SplitError(f"validation fraction {fraction} must lie in [0, 1]")
    count = round(fraction * len(objects))
    if fraction > 0:
        count = max(1, count)
    order = np.random.default_rng(np.random.SeedSequence([seed, len(objects)])).permutation(len(objects))
    return {objects[i] for i in order[:count].tolist()}


def split_by_object(
    object_ids: Sequence[str], fraction: float, seed: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(train, validation) rows of samples whose objects are ``object_ids``: no object on both sides."""
    held = held_out_objects(sorted(set(object_ids)), fraction, seed)
    in_val = np.fromiter((o in held for o in object_ids), dtype=bool, count=len(object_ids))
    return np.flatnonzero(~in_val), np.flatnonzero(in_val)


def split_by_sample(total: int, fraction: float, seed: int) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(train, validation) rows, sorted, of a seeded split of ``total`` samples (the paper's 80/20)."""
    if not 0.0 < fraction < 1.0:
        raise SplitError(f"validation fraction {fraction} must lie strictly between 0 and 1")
    order = np.random.default_rng(np.random.SeedSequence([seed, total])).permutation(total)
    cut = max(1, round(fraction * total))
    if cut >= total:
        raise SplitError(f"{total} samples are too few to split; generate more")
    return np.sort(order[cut:]), np.sort(order[:cut])
