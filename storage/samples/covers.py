"""Set-cover facts a reader needs without a solver (schema version 2).

A sample stores its minimum covers and its task stores ``cover_rows``, the undominated masks of
P_full: U(S)'s rows are the ``cover_rows`` that miss S (a subset of a mask that misses S misses S
too), and a view set covers U exactly when it meets every one of them. That is enough to judge any
prediction: does it cover U, and how close is it to the nearest minimum cover. Masks are uint64
bit masks over the views (bit i = view i).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt

MaskArray = npt.NDArray[np.uint64]


def undominated(masks: npt.ArrayLike) -> MaskArray:
    """Distinct masks that contain no other mask, sorted: a view set meeting each of these meets
    every mask."""
    distinct = np.unique(np.asarray(masks, dtype=np.uint64))
    keep = np.ones(distinct.size, dtype=bool)
    for start in range(0, distinct.size, 512):
        block = distinct[start : start + 512]
        subset = (block[:, None] & distinct[None, :]) == distinct[None, :]  # distinct[j] within block[i]
        subset[np.arange(block.size), np.arange(start, start + block.size)] = False
        keep[start : start + block.size] = ~subset.any(axis=1)
    return distinct[keep]


def universe_rows(cover_rows: MaskArray, view_state: int) -> MaskArray:
    """The set-cover rows of U(S): the task's undominated rows that the input views S miss."""
    return cover_rows[(cover_rows & np.uint64(view_state)) == 0]


def covers_universe(cover_rows: MaskArray, view_state: int, views: int) -> bool:
    """Whether ``views`` (with the input views) cover every key of U(S)."""
    rows = universe_rows(cover_rows, view_state)
    return bool(((rows & np.uint64(views)) != 0).all())


def cover_marginals(covers: Sequence[int] | MaskArray, num_views: int) -> npt.NDArray[np.float64]:
    """For each view, the fraction of ``covers`` holding it (zeros when there are none)."""
    masks = np.asarray(covers, dtype=np.uint64).reshape(-1)
    if masks.size == 0:
        return np.zeros(num_views, dtype=np.float64)
    bits = (masks[:, None] >> np.arange(num_views, dtype=np.uint64)[None, :]) & np.uint64(1)
    return bits.mean(axis=0, dtype=np.float64)


def listed_marginals(
    covers: MaskArray, offsets: npt.NDArray[np.integer], rows: npt.NDArray[np.integer], num_views: int
) -> npt.NDArray[np.float64]:
    """`cover_marginals` of many samples of one shard at once, (len(rows), num_views): sample ``r``
    lists ``covers[offsets[r]:offsets[r + 1]]``. The same values bit for bit: each count of covers
    holding a view is an exact integer, divided by the listing's size as ``mean`` does; in a few array
    passes instead of a few small numpy calls per sample (a streaming reader's cost per sample)."""
    masks = np.asarray(covers, dtype="<u8").reshape(-1)
    where = np.asarray(offsets, dtype=np.int64).reshape(-1)
    local = np.asarray(rows, dtype=np.int64).reshape(-1)
    if where.size == 0 or where[0] != 0 or where[-1] > masks.size or (np.diff(where) < 0).any():
        # Not one listing after another: each sample on its own.
        return np.stack([cover_marginals(masks[where[r] : where[r + 1]], num_views) for r in local.tolist()])
    sizes = np.diff(where)
    counts = np.zeros((sizes.size, num_views), dtype=np.float64)
    listed = np.flatnonzero(sizes)
    if listed.size:
        # Bit v of each mask as one byte (little-endian bytes, least significant bit first); the
        # listings are back to back, so one sum per non-empty listing, from its start to the next one's.
        as_bytes = masks[: where[-1]].view(np.uint8).reshape(-1, 8)
        bits = np.unpackbits(as_bytes, axis=1, count=num_views, bitorder="little")
        counts[listed] = np.add.reduceat(bits, where[listed], axis=0, dtype=np.int64)
        counts[listed] /= sizes[listed, None]
    return counts[local]


def nearest_cover(covers: MaskArray, views: int) -> int:
    """The cover sharing most views with ``views`` (minimum covers all have one size, so this is
    also the one of best F1 against it); ties go to the first listed."""
    masks = np.asarray(covers, dtype=np.uint64).reshape(-1)
    if masks.size == 0:
        raise ValueError("no covers to choose from")
    shared = np.bitwise_count(masks & np.uint64(views))
    return int(masks[int(np.argmax(shared))])


def mask_views(mask: int) -> tuple[int, ...]:
    """The views of a mask, ascending (the sort key of stored covers)."""
    return tuple(v for v in range(mask.bit_length()) if mask >> v & 1)


def listed_problem(
    listed: MaskArray, case: int, label: int, noun: tuple[str, str], as_good: Callable[[MaskArray], str | None]
) -> str | None:
    """What is wrong with the view sets a sample lists beside its label (its minimum covers, or its ties
    under another objective), or None: the label must be among them, each the label's size, none sharing a
    view with the case, each as good as the label (``as_good`` says why not), sorted as tuples of views and
    distinct. ``noun``: what they are, singular and plural."""
    one, many = noun
    if label not in listed.tolist():
        return f"label {mask_views(label)} is not among its {listed.size} listed {many}"
    if (np.bitwise_count(listed) != label.bit_count()).any():
        return f"listed {many} differ in size from the label"
    if ((listed & np.uint64(case)) != 0).any():
        return f"a listed {one} shares views with the input case"
    problem = as_good(listed)
    if problem:
        return problem
    ordered = [mask_views(int(c)) for c in listed]
    if any(a >= b for a, b in itertools.pairwise(ordered)):
        return f"listed {many} are not sorted and distinct"
    return None
