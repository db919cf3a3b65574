"""Clouds as a consumer gets them: key centres in metres, resampled to a fixed point count.

- a key is the centre of its voxel, in metres: ``(key + 0.5 - grid_offset) * voxel_size``;
- a cloud is resampled to a fixed point count from its own stream ``(seed, epoch, index)``, with
  replacement only when it holds fewer points, so a tensor never depends on batch size, worker
  count or read order; an empty cloud becomes ``num_points`` zero keys. A cloud stored in
  `schemas.shard.point_order` (version 4's refined clouds) larger than the count gives instead one
  window of its stored order, from a start drawn from that stream (wrapping past the end): a uniform
  random subset that a reader gets by decoding one or two chunks (`cloud_positions`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import numpy.typing as npt

from schemas.shard import ordered_points
from storage.samples.batch import KeyArray
from storage.samples.seeding import StreamGenerator, pcg64_states


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
    (`storage.samples.pcg64_states`, numpy's own states, else numpy's seeding per cloud) and one
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
"""Fewest streams seeded together (`storage.samples.pcg64_states`): its array arithmetic costs about
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
    are derived together and one generator is set to each in turn (`storage.samples.seeding`) instead of a
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
