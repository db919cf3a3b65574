"""numpy's seeding of a PCG64 from ``SeedSequence([a, b, c])``, for many streams at once.

A reader resamples every cloud from its own stream (seed, epoch, index) (`storage.samples.resampling`), and
``np.random.default_rng(np.random.SeedSequence([seed, epoch, index]))`` costs about 10 us a sample,
more than a third of the draw itself: a SeedSequence object, its Python-level hashing, a PCG64
object. Here the same arithmetic runs on arrays of streams (numpy's ``SeedSequence`` hashes uint32
words with fixed constants; a PCG64 seeds itself from the first four 64-bit words it generates), and
one PCG64 is set to each resulting state in turn: the same generator state, so the same draws.
`tests/storage/test_read_kernels.py` checks the states against numpy's own for many streams, and
`pcg64_states` checks one probe stream against numpy once per process: should a numpy release ever
seed otherwise, every caller falls back to numpy's own seeding instead of drawing other points.

Only streams whose three numbers each lie in [0, 2**32) take this path (numpy writes a larger one
as several words); `pcg64_states` gives None for any other, and its caller seeds the plain way.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

POOL_SIZE = 4
"""Words of a SeedSequence's entropy pool (numpy's default)."""
INIT_A, MULT_A = 0x43B0D7E5, 0x931E8875
"""The hash constants numpy mixes the entropy into the pool with."""
INIT_B, MULT_B = 0x8B51F9DD, 0x58F38DED
"""The hash constants numpy generates words from the pool with."""
MIX_MULT_L, MIX_MULT_R = 0xCA01F9DD, 0x4973F715
XSHIFT = 16
WORD = 0xFFFFFFFF
PCG_MULTIPLIER = 0x2360ED051FC65DA44385DF649FCCF645
"""PCG64's 128-bit LCG multiplier."""
LIMIT_128 = (1 << 128) - 1

U32 = npt.NDArray[np.uint32]


class _Hash:
    """numpy's ``hashmix``: a running constant (the same for every stream) and a word array."""

    def __init__(self, start: int, multiplier: int) -> None:
        self.constant, self.multiplier = start, multiplier

    def __call__(self, value: U32) -> U32:
        value = value ^ np.uint32(self.constant)
        self.constant = (self.constant * self.multiplier) & WORD
        value = value * np.uint32(self.constant)
        return value ^ (value >> np.uint32(XSHIFT))


def _mix(x: U32, y: U32) -> U32:
    result = np.uint32(MIX_MULT_L) * x - np.uint32(MIX_MULT_R) * y
    return result ^ (result >> np.uint32(XSHIFT))


def seed_words(entropy: Sequence[npt.NDArray[np.uint32]], words: int) -> list[U32]:
    """``SeedSequence(entropy).generate_state(words, np.uint32)`` for every stream: ``entropy`` holds
    one array per entropy word (fewer than `POOL_SIZE`; one word a number, no spawn key)."""
    if not 0 < len(entropy) <= POOL_SIZE:
        raise ValueError(f"{len(entropy)} entropy words: this mixes 1 to {POOL_SIZE}")
    size = entropy[0].shape
    hashmix = _Hash(INIT_A, MULT_A)
    pool = [hashmix(entropy[i] if i < len(entropy) else np.zeros(size, np.uint32)) for i in range(POOL_SIZE)]
    for source in range(POOL_SIZE):
        for target in range(POOL_SIZE):
            if source != target:
                pool[target] = _mix(pool[target], hashmix(pool[source]))
    generate = _Hash(INIT_B, MULT_B)
    return [generate(pool[i % POOL_SIZE]) for i in range(words)]


def pcg64_states(streams: Sequence[Sequence[int]]) -> list[tuple[int, int]] | None:
    """The (state, inc) of ``PCG64(SeedSequence(list(stream)))`` for each stream of three numbers,
    or None when a number lies outside [0, 2**32) (numpy would hash it as other words), or when this
    numpy seeds the probe stream otherwise (`agrees_with_numpy`)."""
    if not streams:
        return []
    if not agrees_with_numpy():
        return None
    return _states(streams)


PROBE_STREAM = (20261127, 3, 4000000007)


@functools.cache
def agrees_with_numpy() -> bool:
    """Whether this arithmetic gives numpy's own PCG64 state for a probe stream (checked once)."""
    expected = np.random.PCG64(np.random.SeedSequence(list(PROBE_STREAM))).state["state"]
    found = _states([PROBE_STREAM])
    return found is not None and found[0] == (expected["state"], expected["inc"])


def _states(streams: Sequence[Sequence[int]]) -> list[tuple[int, int]] | None:
    """`pcg64_states` without the probe check."""
    values = np.asarray(streams, dtype=object).reshape(len(streams), -1)
    plain = all(type(v) is int and 0 <= v <= WORD for v in values.flat)
    if values.shape[1] != 3 or not plain:
        return None
    columns = [np.asarray(values[:, k].tolist(), dtype=np.uint32).reshape(-1) for k in range(3)]
    out = seed_words(columns, 8)
    # Words are little-endian halves of 4 uint64s: [seed high, seed low, inc high, inc low].
    halves = [w.astype(np.uint64).tolist() for w in out]
    states: list[tuple[int, int]] = []
    for k in range(len(streams)):
        u = [halves[2 * j][k] | (halves[2 * j + 1][k] << 32) for j in range(4)]
        initial, sequence = (u[0] << 64) | u[1], (u[2] << 64) | u[3]
        inc = ((sequence << 1) | 1) & LIMIT_128
        state = (inc + initial) & LIMIT_128  # state 0 stepped once is inc; then the initial state added
        state = (state * PCG_MULTIPLIER + inc) & LIMIT_128
        states.append((state, inc))
    return states


class StreamGenerator:
    """One reusable ``np.random.Generator`` set to a stream's PCG64 state in turn (cheaper than a
    new generator a stream; the same draws)."""

    def __init__(self) -> None:
        self._bits = np.random.PCG64(0)
        self.rng = np.random.Generator(self._bits)

    def at(self, state: tuple[int, int]) -> np.random.Generator:
        """The generator, freshly seeded to ``state`` (from `pcg64_states`)."""
        self._bits.state = {
            "bit_generator": "PCG64",
            "state": {"state": state[0], "inc": state[1]},
            "has_uint32": 0,
            "uinteger": 0,
        }
        return self.rng
