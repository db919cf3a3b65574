"""View masks as bits: bit ``v`` of a stored uint64 mask is candidate view ``v``.

How a view state, a label, a support or a listed minimum cover reaches a network: 0/1 rows of the
views (`bit_rows`), and a sample's listed covers padded to its batch's longest listing
(`padded_covers`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt


def bit_rows(masks: int | npt.ArrayLike, width: int) -> npt.NDArray[np.float32]:
    """0/1 float32 rows (..., width) of masks: how a view state, label or support reaches a network."""
    return mask_bits(masks, width).astype(np.float32)


def padded_covers(
    listed: Sequence[npt.NDArray[np.uint64]], width: int
) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.bool_]]:
    """(covers (B, C, n) float32 0/1, valid (B, C) bool) of each sample's listed covers (masks), padded
    with empty rows to the longest listing (C)."""
    most = max((found.size for found in listed), default=0)
    covers = np.zeros((len(listed), most, width), dtype=np.float32)
    valid = np.zeros((len(listed), most), dtype=bool)
    for slot, found in enumerate(listed):
        covers[slot, : found.size] = mask_bits(found, width)
        valid[slot, : found.size] = True
    return covers, valid


def bools_mask(bits: npt.ArrayLike) -> int:
    """The mask of one bool per view (bit v = view v): `mask_bits`' inverse, for one view set."""
    return sum(1 << int(v) for v in np.flatnonzero(np.asarray(bits, dtype=bool).reshape(-1)))


def mask_bits(masks: int | npt.ArrayLike, width: int) -> npt.NDArray[np.bool_]:
    """One bool per view (bit v = view v) of a mask, or rows of them for an array of masks."""
    values = np.asarray(masks, dtype=np.uint64)
    bits = np.arange(width, dtype=np.uint64)
    return ((values[..., None] >> bits) & np.uint64(1)).astype(bool)
