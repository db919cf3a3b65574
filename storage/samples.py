"""What a stored sample means to a consumer, in one place.

A shard keeps integer voxel keys and uint64 view masks; every consumer (the PyTorch datasets, the
in-memory and streaming read paths, osvp, the authors'-layout export, inspection) turns them into
the same things through these functions:

- a key is the centre of its voxel, in metres: ``(key + 0.5 - grid_offset) * voxel_size``;
- bit ``v`` of a mask is candidate view ``v``;
- a cloud is resampled to a fixed point count from its own stream ``(seed, epoch, index)``, with
  replacement only when it holds fewer points, so a tensor never depends on batch size, worker
  count or read order; an empty cloud becomes ``num_points`` zero keys. A cloud stored in
  `schemas.shard.point_order` (version 4's refined clouds) larger than the count gives instead one
  window of its stored order, from a start drawn from that stream (wrapping past the end): a uniform
  random subset that a reader gets by decoding one or two chunks (`cloud_positions`);
- a batch of samples is one `SampleBatch` whatever read it (`storage.memory`, `storage.stream`,
  `storage.torch`, osvp): its numpy arrays, or the same as torch tensors (`SampleBatch.tensors`); the
  listed minimum covers are padded to the batch's longest listing by `padded_covers`;
- the rows a reader holds are chosen once, by `storage.reader.Dataset.chosen_rows`;
- a view's gain reaches a network normalised by its task's denominator, and the best next view is
  the largest visibility gain outside the case, lowest index first (`best_views`); a case's occupancy
  grid is built from the task's per-view ray cells (`storage.occupancy`) only when asked for;
- a split by object holds out ``round(fraction * objects)`` objects (at least one when the fraction
  is positive) drawn by a permutation seeded with ``(seed, number of objects)``, so every sample of an
  object lands on one side; a split by sample permutes the rows with ``(seed, number of samples)``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar

import numpy as np
import numpy.typing as npt

from schemas.errors import DatagenError
from schemas.shard import (
    COVERAGE_GAINS,
    GAIN_TOTALS,
    GRID_HITS,
    GRID_MISSES,
    MASKS,
    VIEW_GAINS,
    VIEW_STATE_COLUMN,
    offsets_array,
    ordered_points,
)
from storage.occupancy import case_grid
from storage.seeding import StreamGenerator, pcg64_states

if TYPE_CHECKING:
    import torch

KeyArray = npt.NDArray[np.int16]
Source = Literal["points", "observed"]
"""Which cloud a reader gives: the refined one P(O_S) (``points``) or what the input views saw."""
SOURCES: tuple[Source, ...] = ("points", "observed")

ArrayT = TypeVar("ArrayT")
OtherT = TypeVar("OtherT")


class SplitError(DatagenError, ValueError):
    """A split cannot be made as asked (a fraction out of range, too few samples or objects)."""


def check_source(source: str) -> Source:
    """``source`` itself, or the one `ValueError` every reader gives for another word."""
    if source not in SOURCES:
        raise ValueError(f"source = {source!r}: use 'points' (refined) or 'observed'")
    return source


@dataclass(frozen=True)
class SampleBatch(Generic[ArrayT]):
    """Samples as one batch: what every reader gives and every trainer takes.

    ``SampleBatch[np.ndarray]`` as read; `tensors` gives the same arrays as torch tensors (no copy), and
    `to` moves them to a device. The optional fields are there when the dataset keeps minimum covers
    (``marginals``, ``support``) and when the covers themselves were asked for (``covers``,
    ``cover_mask``). A DataLoader pins it (`pin_memory`) and passes it through untouched.
    """

    points: ArrayT
    """(B, N, 3) float32 key centres, metres."""
    view_state: ArrayT
    """(B, n) float32 0/1: the views the case already has."""
    label: ArrayT
    """(B, n) float32 0/1: the label's views."""
    index: ArrayT
    """(B,) int64: each sample's dataset row (its resampling stream)."""
    marginals: ArrayT | None = None
    """(B, n) float32: the fraction of the listed minimum covers holding each view."""
    support: ArrayT | None = None
    """(B, n) float32 0/1: the views in any minimum cover."""
    covers: ArrayT | None = None
    """(B, C, n) float32 0/1: the listed minimum covers, padded to the batch's longest listing."""
    cover_mask: ArrayT | None = None
    """(B, C) bool: True where ``covers`` holds a real cover."""
    cloud_size: ArrayT | None = None
    """(B,) int64: points in the stored cloud ``points`` was drawn from (fewer than N: drawn with
    repeats). A `SampleField`: the in-memory and streaming readers fill it."""
    view_gain: ArrayT | None = None
    """(B, n) float32 (version 3): each view's new keys of the visibility sets over all keys any view
    sees (MA-SCVP's PCNBV target)."""
    coverage_gain: ArrayT | None = None
    """(B, n) float32 (version 3): each view's new keys of P_full over |P_full|."""
    best_view: ArrayT | None = None
    """(B,) int64 (version 3): the best next view (NBVNet's class), -1 when the case has every view."""
    grid: ArrayT | None = None
    """(B, 32, 32, 32) float32 (version 3, read only when asked for): the case's occupancy
    probabilities indexed [x, y, z], 0.5 unknown (`storage.occupancy`)."""

    def __len__(self) -> int:
        return len(self.index)  # type: ignore[arg-type]

    def as_dict(self) -> dict[str, ArrayT]:
        """The fields that are present, by name."""
        found = ((field.name, getattr(self, field.name)) for field in fields(self))
        return {name: value for name, value in found if value is not None}

    def map(self, convert: Callable[[ArrayT], OtherT]) -> SampleBatch[OtherT]:
        """Every present field through ``convert`` (absent ones stay None)."""
        return SampleBatch(**{name: convert(value) for name, value in self.as_dict().items()})

    def tensors(self: SampleBatch[npt.NDArray[Any]]) -> SampleBatch[torch.Tensor]:
        """The same arrays as CPU tensors, sharing their memory."""
        import torch

        return self.map(torch.from_numpy)

    def to(self: SampleBatch[torch.Tensor], device: Any, non_blocking: bool = False) -> SampleBatch[torch.Tensor]:
        """Every tensor on ``device``."""
        return self.map(lambda tensor: tensor.to(device, non_blocking=non_blocking))

    def pin_memory(self: SampleBatch[torch.Tensor]) -> SampleBatch[torch.Tensor]:
        """Every tensor in pinned memory (what a DataLoader with ``pin_memory=True`` calls)."""
        return self.map(lambda tensor: tensor.pin_memory())


@dataclass(frozen=True)
class ShardRows:
    """Some samples of one shard, as a reader has them: what a `SampleField` reads from."""

    source: Source
    local: npt.NDArray[np.int64]
    """The samples' rows within the shard."""
    array: Callable[[str], npt.NDArray[Any]]
    """The shard's array of that name, whole (`schemas.shard`'s names)."""


@dataclass(frozen=True)
class SampleField:
    """A per-sample `SampleBatch` field read from a shard's arrays, the same way by every batch reader.

    ``read`` gives the values of ``rows.local`` stacked, (S, ...) with a fixed trailing shape, for a
    dataset of schema version ``since`` or later. A new field of a sample is its `SampleBatch`
    attribute and one `register_field` here: `storage.memory` and `storage.stream` read and batch
    every registered field without naming it.
    """

    name: str
    since: int
    read: Callable[[ShardRows], npt.NDArray[Any]]
    optional: bool = False
    """Read only when a reader is asked for it by name (large, or costly to build)."""


SAMPLE_FIELDS: dict[str, SampleField] = {}
"""Every registered per-sample field, by `SampleBatch` attribute."""


def register_field(
    name: str, since: int = 1, optional: bool = False
) -> Callable[[Callable[[ShardRows], npt.NDArray[Any]]], Callable[[ShardRows], npt.NDArray[Any]]]:
    """Register the decorated reader as field ``name`` (a `SampleBatch` attribute) of datasets of
    schema version ``since`` or later; an ``optional`` one is read only when asked for."""
    if name not in {field.name for field in fields(SampleBatch)}:
        raise ValueError(f"{name!r} is no SampleBatch field; declare it on SampleBatch first")

    def register(read: Callable[[ShardRows], npt.NDArray[Any]]) -> Callable[[ShardRows], npt.NDArray[Any]]:
        if name in SAMPLE_FIELDS:
            raise ValueError(f"sample field {name!r} is registered twice")
        SAMPLE_FIELDS[name] = SampleField(name, since, read, optional)
        return read

    return register


def fields_for(schema_version: int, asked: Sequence[str] = ()) -> list[SampleField]:
    """The registered fields a reader of a dataset of ``schema_version`` reads, sorted by name: every
    one the version has, the optional ones only when ``asked`` names them. Naming a field that is not
    registered, or that the version lacks, is a `ValueError`."""
    for name in asked:
        found = SAMPLE_FIELDS.get(name)
        if found is None:
            known = ", ".join(sorted(SAMPLE_FIELDS))
            raise ValueError(f"fields: {name!r} is no sample field; the fields are {known}")
        if found.since > schema_version:
            raise ValueError(
                f"fields: {name!r} needs a dataset of schema version {found.since}; this one is version "
                f"{schema_version} (add it with `datagen shards relabel`)"
            )
    return [
        field
        for name, field in sorted(SAMPLE_FIELDS.items())
        if field.since <= schema_version and (not field.optional or name in asked)
    ]


@register_field("cloud_size")
def _cloud_size(rows: ShardRows) -> npt.NDArray[np.int64]:
    offsets = np.asarray(rows.array(offsets_array(rows.source)), dtype=np.int64)
    return offsets[rows.local + 1] - offsets[rows.local]


def _cases(rows: ShardRows) -> npt.NDArray[np.uint64]:
    return np.asarray(rows.array(MASKS), dtype=np.uint64)[rows.local, VIEW_STATE_COLUMN]


@register_field("view_gain", since=3)
def _view_gain(rows: ShardRows) -> npt.NDArray[np.float32]:
    gains = np.asarray(rows.array(VIEW_GAINS))[rows.local]
    return _normalised(gains, int(rows.array(GAIN_TOTALS)[0]))


@register_field("coverage_gain", since=3)
def _coverage_gain(rows: ShardRows) -> npt.NDArray[np.float32]:
    gains = np.asarray(rows.array(COVERAGE_GAINS))[rows.local]
    return _normalised(gains, int(rows.array(GAIN_TOTALS)[1]))


@register_field("best_view", since=3)
def _best_view(rows: ShardRows) -> npt.NDArray[np.int64]:
    gains = np.asarray(rows.array(VIEW_GAINS))[rows.local]
    return best_views(gains, _cases(rows), gains.shape[1])[0]


@register_field("grid", since=3, optional=True)
def _grid(rows: ShardRows) -> npt.NDArray[np.float32]:
    hits, misses = rows.array(GRID_HITS), rows.array(GRID_MISSES)
    grids = [case_grid(hits, misses, case) for case in _cases(rows).tolist()]
    return np.stack(grids) if grids else np.zeros((0, 32, 32, 32), dtype=np.float32)


def _normalised(gains: npt.NDArray[Any], total: int) -> npt.NDArray[np.float32]:
    """Gains over their denominator, in float64 then float32 (0 when nothing is counted)."""
    return (gains.astype(np.float64) / total if total else np.zeros(gains.shape)).astype(np.float32)


def best_views(
    gains: npt.ArrayLike, cases: npt.ArrayLike, width: int
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]:
    """(best view, views sharing its gain) of each row of ``gains`` (S, width) for the ``cases`` (S,)
    masks: the largest gain outside the case, lowest index first (the authors' first-maximum loop);
    (-1, 0) for a case of every view. The generator and every reader pick it here."""
    values = np.asarray(gains, dtype=np.int64).reshape(-1, width)
    outside = ~mask_bits(np.asarray(cases, dtype=np.uint64).reshape(-1), width)
    candidates = np.where(outside, values, -1)
    best = np.argmax(candidates, axis=1)
    top = np.take_along_axis(candidates, best[:, None], axis=1)
    ties = ((candidates == top) & outside).sum(axis=1)
    none = ~outside.any(axis=1)
    return np.where(none, -1, best).astype(np.int64), np.where(none, 0, ties).astype(np.int64)


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


def key_centres(
    keys: npt.NDArray[np.integer],
    voxel_size: float,
    grid_offset: Sequence[float] | npt.NDArray[np.floating],
    out: npt.NDArray[np.float32] | None = None,
) -> npt.NDArray[np.float32]:
    """Voxel centres in metres (float32, same leading shape) of integer keys (..., 3), written to
    ``out`` when given. Computed in float64 and rounded once to float32; in place, the same operations
    in the same order as ``((keys + 0.5 - offset) * voxel_size).astype(float32)``, so the same bits,
    with one float64 temporary instead of four (a streaming reader does this for every batch)."""
    offset = np.asarray(grid_offset, dtype=np.float64)
    keys = np.asarray(keys)
    centres = np.add(keys, 0.5, dtype=np.float64)
    if centres.ndim >= 3 and offset.shape == centres.shape[-1:]:
        # A batch (B, N, 3): the offset repeated along each sample's row, so numpy's inner loop runs
        # N * 3 long instead of 3 (the same subtractions, 2.5x faster).
        rows = centres.reshape(-1, centres.shape[-2] * centres.shape[-1])
        rows -= np.tile(offset, centres.shape[-2])
    else:
        centres -= offset
    if out is None:
        out = np.empty(keys.shape, dtype=np.float32)
    return np.multiply(centres, float(voxel_size), out=out, casting="same_kind")


def mask_bits(masks: int | npt.ArrayLike, width: int) -> npt.NDArray[np.bool_]:
    """One bool per view (bit v = view v) of a mask, or rows of them for an array of masks."""
    values = np.asarray(masks, dtype=np.uint64)
    bits = np.arange(width, dtype=np.uint64)
    return ((values[..., None] >> bits) & np.uint64(1)).astype(bool)


def resample_indices(count: int, num_points: int, seed: int, epoch: int, index: int) -> npt.NDArray[np.int64]:
    """Which of ``count`` points make the ``num_points`` of sample ``index`` in ``epoch``."""
    return stream_indices(count, num_points, (seed, epoch, index))


def stream_indices(count: int, num_points: int, stream: Sequence[int]) -> npt.NDArray[np.int64]:
    """Which of ``count`` points make a cloud of ``num_points``, drawn from random stream ``stream``:
    with replacement only when there are fewer points than asked for."""
    rng = np.random.default_rng(np.random.SeedSequence(list(stream)))
    # shuffle=False: the order of a point set carries nothing, and it is ~40 % cheaper.
    return rng.choice(count, size=num_points, replace=count < num_points, shuffle=False)


def cloud_positions(
    count: int, num_points: int, seed: int, epoch: int, index: int, windowed: bool
) -> npt.NDArray[np.int64]:
    """Which stored points of a cloud of ``count`` make the ``num_points`` of sample ``index`` in
    ``epoch``. ``windowed`` (a cloud stored in `schemas.shard.point_order`, see `windowed_cloud`) and
    more points than asked for: the window of ``num_points`` consecutive stored points from a start
    drawn from stream (seed, epoch, index), wrapping past the end, so every point is as likely as any
    other and each epoch sees another window; otherwise `resample_indices`. The start is the stream's
    first 64-bit word (PCG64, what ``default_rng`` draws from) modulo ``count``: half the cost of a
    Generator, and a bias below count / 2^64."""
    if not windowed or count <= num_points:
        return resample_indices(count, num_points, seed, epoch, index)
    first_word = int(np.random.PCG64(np.random.SeedSequence([seed, epoch, index])).random_raw())
    return _window(first_word % count, num_points, count)


def many_cloud_positions(
    counts: Sequence[int], num_points: int, seed: int, epoch: int, indices: Sequence[int], windowed: bool
) -> list[npt.NDArray[np.int64]]:
    """``[cloud_positions(count, num_points, seed, epoch, index, windowed) ...]`` of many non-empty
    clouds, the same arrays for less CPU: the streams' PCG64 states are derived together
    (`storage.seeding.pcg64_states`, numpy's own states, else numpy's seeding per cloud) and one
    generator is set to each in turn. A PCG64 at a given state gives the same first word and a
    Generator on it the same ``choice``, so both the window start and `resample_indices`' draw are
    those of a generator seeded the plain way."""
    states = _shared_states(seed, epoch, indices)
    if states is None:
        pairs = zip(counts, indices, strict=True)
        return [cloud_positions(count, num_points, seed, epoch, index, windowed) for count, index in pairs]
    generator = StreamGenerator()
    out: list[npt.NDArray[np.int64]] = []
    for count, state in zip(counts, states, strict=True):
        rng = generator.at(state)
        if windowed and count > num_points:
            out.append(_window(int(rng.bit_generator.random_raw()) % count, num_points, count))
        else:
            out.append(rng.choice(count, size=num_points, replace=count < num_points, shuffle=False))
    return out


SHARED_SEEDING_FROM = 16
"""Fewest streams seeded together (`storage.seeding.pcg64_states`): its array arithmetic costs about
170 us whatever the count, numpy's own seeding about 12 us a stream, so a map-style reader's one
sample at a time is seeded the plain way (the same states either way)."""


def _shared_states(seed: int, epoch: int, indices: Sequence[int]) -> list[tuple[int, int]] | None:
    """The PCG64 states of streams (seed, epoch, index) computed together, or None where numpy's own
    seeding per stream is cheaper (fewer than `SHARED_SEEDING_FROM`) or must be used."""
    if len(indices) < SHARED_SEEDING_FROM:
        return None
    return pcg64_states([(seed, epoch, index) for index in indices])


def _window(start: int, num_points: int, count: int) -> npt.NDArray[np.int64]:
    """Positions ``start, start + 1, ...`` of ``num_points`` stored points, wrapping past ``count``."""
    positions = np.arange(start, start + num_points, dtype=np.int64)
    if start + num_points > count:
        positions[count - start :] -= count
    return positions


def windowed_cloud(schema_version: int, source: str) -> bool:
    """Whether clouds ``source`` of a dataset of ``schema_version`` are read by windows (`cloud_positions`)."""
    return ordered_points(schema_version, source)


def gather_clouds(
    take: Callable[[npt.NDArray[np.int64]], KeyArray],
    starts: npt.NDArray[np.int64],
    sizes: npt.NDArray[np.int64],
    streams: npt.NDArray[np.int64],
    num_points: int,
    seed: int,
    epoch: int,
    windowed: bool,
) -> KeyArray:
    """(S, num_points, 3) keys of S clouds stored at rows ``starts[s]:starts[s] + sizes[s]`` of a key
    array that ``take`` reads (rows -> keys), each resampled from stream (seed, epoch, streams[s]) by
    `cloud_positions` (`many_cloud_positions`, the streams seeded together): every reader gathers
    through here, so only the rows used need decoding. An empty cloud stays at the zero key."""
    chosen = np.zeros((starts.size, num_points, 3), dtype=np.int16)
    filled = np.flatnonzero(sizes > 0)
    if filled.size:
        counts, firsts = sizes[filled].tolist(), starts[filled].tolist()
        drawn = many_cloud_positions(counts, num_points, seed, epoch, streams[filled].tolist(), windowed)
        positions = [first + where for first, where in zip(firsts, drawn, strict=True)]
        chosen[filled] = take(np.concatenate(positions)).reshape(filled.size, num_points, 3)
    return chosen


def resample_cloud(points: npt.NDArray[np.float32], num_points: int, stream: Sequence[int]) -> npt.NDArray[np.float32]:
    """``num_points`` of a cloud (K, 3) in metres, drawn from ``stream`` (`stream_indices`); zeros when
    empty. What a planner does to a scene's cloud before its network sees it."""
    if points.shape[0] == 0:
        return np.zeros((num_points, 3), dtype=np.float32)
    return np.take(points, stream_indices(points.shape[0], num_points, stream), axis=0)


def resample_keys(
    keys: KeyArray, num_points: int, seed: int, epoch: int, index: int, windowed: bool = False
) -> KeyArray:
    """``num_points`` keys of a whole cloud (K, 3) as stored, chosen by `cloud_positions` from stream
    (seed, epoch, index); zeros when empty."""
    if keys.shape[0] == 0:
        return np.zeros((num_points, 3), dtype=np.int16)
    # np.take: the same rows as keys[...], gathered about 4x faster (it matters at thousands of clouds/s).
    return np.take(keys, cloud_positions(keys.shape[0], num_points, seed, epoch, index, windowed), axis=0)


def resample_many_keys(
    clouds: Sequence[KeyArray], num_points: int, seed: int, epoch: int, indices: Sequence[int]
) -> list[KeyArray]:
    """``[resample_keys(cloud, num_points, seed, epoch, index) ...]`` of many clouds read whole (windows
    of version-4 clouds are `gather_clouds`'), the same arrays for less CPU: the streams' PCG64 states
    are derived together and one generator is set to each in turn (`storage.seeding`) instead of a
    SeedSequence and a generator built per cloud."""
    states = _shared_states(seed, epoch, indices)
    if states is None:
        pairs = zip(clouds, indices, strict=True)
        return [resample_keys(cloud, num_points, seed, epoch, index) for cloud, index in pairs]
    generator = StreamGenerator()
    out: list[KeyArray] = []
    for cloud, state in zip(clouds, states, strict=True):
        count = cloud.shape[0]
        if count == 0:
            out.append(np.zeros((num_points, 3), dtype=np.int16))
            continue
        # A sequential copy first: the gather's random reads then hit the cache (the cloud was just
        # decoded among a whole shard's arrays); half the gather's time on a shard of 40 clouds.
        cloud = np.array(cloud, order="C")
        # The draw of `stream_indices`, from the same generator state.
        chosen = generator.at(state).choice(count, size=num_points, replace=count < num_points, shuffle=False)
        out.append(np.take(cloud, chosen, axis=0))
    return out


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
