"""The one path from a shard's rows to a `storage.samples.SampleBatch`, shared by every reader.

`hold_samples` reads every chosen field (`storage.samples.sample_fields`) for some rows of one shard;
`place_samples` puts such pieces in position order (a whole in-memory load, or a stream's batch
gathered from the shards in its shuffle buffer); `finish_batch` makes the batch of some held
samples. `storage.readers.memory`, `storage.stream` and `storage.torch` differ only in when they call these
(once per load, once per shard read, once per item), so a field is read and batched one way.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from storage.samples.batch import SampleBatch
from storage.samples.held import Held, Positions, placed
from storage.samples.sample_fields import BatchFacts, SampleField, ShardRows

HeldSamples = dict[str, Held]
"""Some samples' held values, by field name."""


def hold_samples(fields: Sequence[SampleField], rows: ShardRows) -> HeldSamples:
    """Every field's held values for ``rows`` of one shard."""
    return {field.name: field.held(rows) for field in fields}


def place_samples(pieces: Sequence[tuple[Positions, HeldSamples]], total: int) -> HeldSamples:
    """One `HeldSamples` of ``total`` samples from pieces (their positions, their held values)."""
    if not pieces:
        return {}
    names = list(pieces[0][1])
    return {name: placed([(positions, held[name]) for positions, held in pieces], total) for name in names}


def take_samples(held: HeldSamples, positions: Positions) -> HeldSamples:
    return {name: values.take(positions) for name, values in held.items()}


def finish_arrays(
    fields: Sequence[SampleField], held: HeldSamples, positions: Positions, facts: BatchFacts
) -> dict[str, npt.NDArray[Any]]:
    """Every field's batch array for the samples at ``positions`` of ``held``, by name."""
    index = np.asarray(positions, dtype=np.int64).reshape(-1)
    return {field.name: field.finish(held[field.name], index, facts) for field in fields}


def finish_batch(
    fields: Sequence[SampleField], held: HeldSamples, positions: Positions, facts: BatchFacts
) -> SampleBatch[npt.NDArray[Any]]:
    """The `SampleBatch` of the samples at ``positions`` of ``held``."""
    return SampleBatch.of(finish_arrays(fields, held, positions, facts))
