"""What a stored sample means to a consumer, in one place.

A shard keeps integer voxel keys and uint64 view masks; every consumer (the PyTorch datasets, the
in-memory and streaming read paths, osvp, the authors'-layout export, inspection) turns them into
the same things through these functions:

- a key is the centre of its voxel, in metres: ``(key + 0.5 - grid_offset) * voxel_size``;
- bit ``v`` of a mask is candidate view ``v``;
- a cloud is resampled to a fixed point count from its own stream ``(seed, epoch, index)``, with
  replacement only when it holds fewer points, so a tensor never depends on batch size, worker
  count or read order; an empty cloud becomes ``num_points`` zero keys;
- a split by object holds out ``round(fraction * objects)`` objects (at least one when the fraction
  is positive) drawn by a permutation seeded with ``(seed, number of objects)``, so every sample of an
  object lands on one side; a split by sample permutes the rows with ``(seed, number of samples)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from schemas.errors import DatagenError

KeyArray = npt.NDArray[np.int16]


class SplitError(DatagenError, ValueError):
    """A split cannot be made as asked (a fraction out of range, too few samples or objects)."""


def key_centres(
    keys: npt.NDArray[np.integer], voxel_size: float, grid_offset: Sequence[float] | npt.NDArray[np.floating]
) -> npt.NDArray[np.float32]:
    """Voxel centres in metres (float32, same leading shape) of integer keys (..., 3)."""
    offset = np.asarray(grid_offset, dtype=np.float64)
    return ((np.asarray(keys).astype(np.float64) + 0.5 - offset) * float(voxel_size)).astype(np.float32)


def mask_bits(masks: int | npt.ArrayLike, width: int) -> npt.NDArray[np.bool_]:
    """One bool per view (bit v = view v) of a mask, or rows of them for an array of masks."""
    values = np.asarray(masks, dtype=np.uint64)
    bits = np.arange(width, dtype=np.uint64)
    return ((values[..., None] >> bits) & np.uint64(1)).astype(bool)


def resample_indices(count: int, num_points: int, seed: int, epoch: int, index: int) -> npt.NDArray[np.int64]:
    """Which of ``count`` points make the ``num_points`` of sample ``index`` in ``epoch``."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, epoch, index]))
    # shuffle=False: the order of a point set carries nothing, and it is ~40 % cheaper.
    return rng.choice(count, size=num_points, replace=count < num_points, shuffle=False)


def resample_keys(keys: KeyArray, num_points: int, seed: int, epoch: int, index: int) -> KeyArray:
    """``num_points`` keys of a cloud (K, 3), drawn from stream (seed, epoch, index); zeros when empty."""
    if keys.shape[0] == 0:
        return np.zeros((num_points, 3), dtype=np.int16)
    # np.take: the same rows as keys[...], gathered about 4x faster (it matters at thousands of clouds/s).
    return np.take(keys, resample_indices(keys.shape[0], num_points, seed, epoch, index), axis=0)


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
