"""Every sample's minimum covers in memory, for the ambiguity-aware targets and metrics.

A label is one arbitrary minimum cover among many equally good ones (schema version 2 stores them
all, up to a cap). `CoverBank` keeps, per sample, the listed covers and U's set-cover rows packed
as uint64 masks with offsets (bit v = view v), the support and per-view marginals as bit rows, so
a batch target or a judgement of a prediction needs no reader. Judging goes through
`storage.samples.covers` (`nearest_cover`, `covers_universe`): osvp never re-implements the cover rules.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from storage import LabelAmbiguity
from storage.readers import PackedCovers
from storage.samples import cover_marginals, covers_universe, mask_bits, nearest_cover, padded_covers

MaskArray = npt.NDArray[np.uint64]
FloatArray = npt.NDArray[np.float32]
BoolArray = npt.NDArray[np.bool_]


def bits_to_masks(bits: npt.ArrayLike) -> MaskArray:
    """(S, n) 0/1 rows -> (S,) uint64 masks (bit v = column v)."""
    rows = np.asarray(bits) > 0.5
    if rows.ndim != 2 or rows.shape[1] > 64:
        raise ValueError(f"bit rows must be (samples, views <= 64), got {rows.shape}")
    weights = np.left_shift(np.uint64(1), np.arange(rows.shape[1], dtype=np.uint64))
    return np.bitwise_or.reduce(np.where(rows, weights[None, :], np.uint64(0)), axis=1).astype(np.uint64)


def masks_to_bits(masks: npt.ArrayLike, num_views: int) -> BoolArray:
    """(K,) uint64 masks -> (K, n) bool rows."""
    return mask_bits(np.asarray(masks, dtype=np.uint64).reshape(-1), num_views)


def _pack(pieces: Sequence[MaskArray]) -> tuple[MaskArray, npt.NDArray[np.int64]]:
    offsets = np.zeros(len(pieces) + 1, dtype=np.int64)
    np.cumsum([piece.size for piece in pieces], out=offsets[1:])
    packed = np.concatenate(pieces).astype(np.uint64) if offsets[-1] else np.zeros(0, dtype=np.uint64)
    return packed, offsets


@dataclass(frozen=True)
class CoverBank:
    """Per sample: the listed minimum covers, U's rows, support, marginals, count and exactness."""

    num_views: int
    covers: MaskArray
    cover_offsets: npt.NDArray[np.int64]
    """Sample i's covers are ``covers[cover_offsets[i]:cover_offsets[i + 1]]`` (the label among them)."""
    universe: MaskArray
    universe_offsets: npt.NDArray[np.int64]
    """Sample i's U rows (the view state's already left out): a view set covers U when it meets each."""
    view_states: MaskArray
    support: FloatArray
    """(S, n) 0/1: views in any minimum cover (exact even when the listing is capped)."""
    marginals: FloatArray
    """(S, n): the fraction of the listed covers holding each view."""
    counts: npt.NDArray[np.int64]
    """How many minimum covers exist (a lower bound where not ``exact``)."""
    exact: BoolArray

    @classmethod
    def build(cls, ambiguities: Sequence[LabelAmbiguity], view_states: Sequence[int], num_views: int) -> CoverBank:
        """Pack what `storage.Dataset.ambiguity` says for each sample, in sample order."""
        covers, cover_offsets = _pack([np.asarray(a.covers, dtype=np.uint64) for a in ambiguities])
        universe, universe_offsets = _pack([np.asarray(a.universe_rows, dtype=np.uint64) for a in ambiguities])
        supports = np.asarray([a.support for a in ambiguities], dtype=np.uint64).reshape(-1)
        marginals = [cover_marginals(a.covers, num_views) for a in ambiguities]
        return cls(
            num_views=num_views,
            covers=covers,
            cover_offsets=cover_offsets,
            universe=universe,
            universe_offsets=universe_offsets,
            view_states=np.asarray(view_states, dtype=np.uint64).reshape(-1),
            support=masks_to_bits(supports, num_views).astype(np.float32),
            marginals=(np.stack(marginals) if marginals else np.zeros((0, num_views))).astype(np.float32),
            counts=np.asarray([a.count for a in ambiguities], dtype=np.int64),
            exact=np.asarray([a.exact for a in ambiguities], dtype=bool),
        )

    @classmethod
    def from_packed(
        cls,
        packed: PackedCovers,
        view_states: npt.ArrayLike,
        num_views: int,
        marginals: npt.NDArray[np.float32] | None = None,
    ) -> CoverBank:
        """What `storage.readers.load_memory` read (every sample's covers and U rows as masks with
        offsets), with the marginals `build` would compute (``marginals``: the ones the load already
        holds, the `storage.samples.sample_fields` field), without reading the dataset again."""
        if marginals is None:
            marginals = cls._marginals(packed, num_views)
        return cls(
            num_views=num_views,
            covers=packed.covers,
            cover_offsets=packed.cover_offsets,
            universe=packed.universe,
            universe_offsets=packed.universe_offsets,
            view_states=np.asarray(view_states, dtype=np.uint64).reshape(-1),
            support=masks_to_bits(packed.support, num_views).astype(np.float32),
            marginals=marginals.astype(np.float32, copy=False),
            counts=packed.counts,
            exact=packed.exact,
        )

    @staticmethod
    def _marginals(packed: PackedCovers, num_views: int) -> npt.NDArray[np.float32]:
        """Each sample's share of its listed covers holding each view, from the packed masks."""
        sizes = np.diff(packed.cover_offsets)
        listed = sizes > 0
        starts = packed.cover_offsets[:-1][listed]
        held = np.zeros((sizes.size, num_views), dtype=np.int64)
        for view in range(num_views):  # one view at a time: a byte per listed cover, not a row
            column = ((packed.covers >> np.uint64(view)) & np.uint64(1)).astype(np.uint8)
            if starts.size:
                held[listed, view] = np.add.reduceat(column, starts, dtype=np.int64)
        # sums of 0/1 are exact, so held / size is `cover_marginals`' mean to the last bit
        marginals = np.divide(held, sizes[:, None], out=np.zeros(held.shape), where=sizes[:, None] > 0)
        return marginals.astype(np.float32)

    def __len__(self) -> int:
        return int(self.view_states.size)

    def covers_of(self, i: int) -> MaskArray:
        return self.covers[self.cover_offsets[i] : self.cover_offsets[i + 1]]

    def universe_of(self, i: int) -> MaskArray:
        return self.universe[self.universe_offsets[i] : self.universe_offsets[i + 1]]

    def nearest(self, i: int, views: int) -> int:
        """The listed cover of sample i sharing most views with ``views`` (`storage.nearest_cover`)."""
        return nearest_cover(self.covers_of(i), views)

    def covers_universe(self, i: int, views: int) -> bool:
        """Whether ``views`` together with sample i's view state cover its U (`storage.covers_universe`)."""
        return covers_universe(self.universe_of(i), int(self.view_states[i]), views)

    def take(self, rows: npt.ArrayLike) -> CoverBank:
        """The samples ``rows`` only, in that order (metrics then index 0..len(rows)-1)."""
        index = np.asarray(rows, dtype=np.int64).reshape(-1)
        covers, cover_offsets = _pack([self.covers_of(int(i)) for i in index])
        universe, universe_offsets = _pack([self.universe_of(int(i)) for i in index])
        return CoverBank(
            num_views=self.num_views,
            covers=covers,
            cover_offsets=cover_offsets,
            universe=universe,
            universe_offsets=universe_offsets,
            view_states=self.view_states[index],
            support=self.support[index],
            marginals=self.marginals[index],
            counts=self.counts[index],
            exact=self.exact[index],
        )

    def padded(self, rows: npt.ArrayLike) -> tuple[FloatArray, BoolArray]:
        """The covers of ``rows`` as bit rows (B, C, n) padded to the batch's largest listing, and
        (B, C) True where a cover is real (`storage.samples.padded_covers`): what
        `osvp.loss.mincover_loss` takes."""
        index = np.asarray(rows, dtype=np.int64).reshape(-1)
        return padded_covers([self.covers_of(i) for i in index.tolist()], self.num_views)
