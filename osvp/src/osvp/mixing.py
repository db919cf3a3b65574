"""A second dataset mixed into training: a fixed share of every epoch's samples comes from it.

Real objects are few and synthetic ones cheap, so a run may train on its dataset and draw a
fraction ``f`` of each epoch's samples from another (``osvp train --mix-data URL --mix-fraction F``):
an epoch then holds every training row once (or as ``--case-balance`` draws them) and
``round(N f / (1 - f))`` rows of the mixed-in dataset, each row of it at most once until all of it
has been drawn. Which rows, and where in the epoch each lands, come from the stream (seed, epoch,
`MIX_STREAM`), and a mixed-in sample's points from its own resampling stream (`mixed_seed`), so a
resumed run sees the same batches. Validation never mixes: it stays on the run's own validation rows.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import torch

from osvp.data import Batch, DataError, SampleBank

MIX_STREAM = 0x313C5
"""Tag of the mixing streams (seed, epoch, tag), apart from the epochs' (seed, epoch, k) and the subsets'."""


@dataclass(frozen=True)
class Mixture:
    """The mixed-in dataset in memory and the share of an epoch's samples it gives."""

    bank: SampleBank
    fraction: float

    def count(self, own: int) -> int:
        """Rows drawn from the mixed-in dataset in an epoch beside ``own`` of the run's own."""
        return mixed_count(own, self.fraction)


def check_fraction(fraction: float) -> None:
    if not 0.0 < fraction < 1.0:
        raise DataError(f"--mix-fraction {fraction}: give the mixed-in share of an epoch's samples, in (0, 1)")


def mixed_count(own: int, fraction: float) -> int:
    """How many mixed-in rows make them ``fraction`` of an epoch that holds ``own`` rows of the run's own."""
    check_fraction(fraction)
    return round(own * fraction / (1.0 - fraction))


def mixed_seed(seed: int) -> int:
    """The resampling seed of the mixed-in samples: their rows must not share the own rows' streams."""
    return int(np.random.SeedSequence([seed, MIX_STREAM]).generate_state(1, dtype=np.uint32)[0])


def check_mixable(bank: SampleBank, mixed: SampleBank) -> None:
    """Refuse, in one line, a mixed-in dataset whose samples do not mean what the run's own do (its
    covers, where the target needs them, were checked as it loaded: `SampleBank.load`'s ``covers_for``)."""
    url = mixed.url
    for what, own, theirs in (
        ("views", bank.num_views, mixed.num_views),
        ("schema version", bank.schema_version, mixed.schema_version),
        ("voxel size", bank.voxel_size, mixed.voxel_size),
    ):
        if own != theirs:
            raise DataError(
                f"{url}: its {what} is {theirs}, the training data's {own}; mix in a dataset made with the same "
                "view space, schema and voxel"
            )


def epoch_plan(
    own: npt.NDArray[np.int64], mixed_rows: int, fraction: float, rng: np.random.Generator
) -> tuple[npt.NDArray[np.bool_], npt.NDArray[np.int64]]:
    """(which positions of the epoch are mixed-in, the mixed-in rows in order) for an epoch of the
    ``own`` rows (already in their order): every mixed-in row once per pass through all of them."""
    if mixed_rows < 1:
        raise DataError("the mixed-in dataset holds no samples; mix in a dataset with samples")
    wanted = mixed_count(len(own), fraction)
    passes = -(-wanted // mixed_rows)
    drawn = np.concatenate([rng.permutation(mixed_rows) for _ in range(passes)])[:wanted].astype(np.int64)
    is_mixed = np.zeros(len(own) + wanted, dtype=np.bool_)
    is_mixed[rng.permutation(len(is_mixed))[:wanted]] = True
    return is_mixed, drawn


def mixed_batches(
    bank: SampleBank,
    own: npt.NDArray[np.int64],
    mixture: Mixture,
    rng: np.random.Generator,
    batch_size: int,
    num_points: int,
    seed: int,
    epoch: int,
    with_covers: bool,
) -> Iterator[Batch]:
    """An epoch's batches of the ``own`` rows (in their order) with the mixed-in rows placed among them."""
    is_mixed, drawn = epoch_plan(own, len(mixture.bank), mixture.fraction, rng)
    own_at = mixed_at = 0
    for start in range(0, len(is_mixed), batch_size):
        flags = is_mixed[start : start + batch_size]
        mixed_now = int(flags.sum())
        own_now = len(flags) - mixed_now
        parts = []
        if own_now:
            parts.append(bank.batch(own[own_at : own_at + own_now], num_points, seed, epoch, with_covers))
        if mixed_now:
            rows = drawn[mixed_at : mixed_at + mixed_now]
            parts.append(mixture.bank.batch(rows, num_points, mixed_seed(seed), epoch, with_covers))
        own_at, mixed_at = own_at + own_now, mixed_at + mixed_now
        yield in_place(concat_batches(parts), flags)


def in_place(joined: Batch, flags: npt.NDArray[np.bool_]) -> Batch:
    """The batch of own samples then mixed-in ones, reordered so that each sits where ``flags``
    (True: mixed-in) puts it in the epoch."""
    mixed_now = int(flags.sum())
    if mixed_now in (0, len(flags)):
        return joined
    place = np.empty(len(flags), dtype=np.int64)
    place[~flags] = np.arange(len(flags) - mixed_now)
    place[flags] = len(flags) - mixed_now + np.arange(mixed_now)
    order = torch.from_numpy(place)
    return joined.map(lambda values: values[order])


def concat_batches(parts: list[Batch]) -> Batch:
    """One batch of these, in order; the listed covers padded to the longest listing (``cover_mask``
    False on the padding)."""
    if len(parts) == 1:
        return parts[0]
    held = [part.as_dict() for part in parts]
    names = set(held[0])
    if any(set(fields) != names for fields in held[1:]):
        raise DataError(
            "the mixed-in batches hold other fields than the training data's; mix in a dataset of the same schema"
        )
    joined: dict[str, torch.Tensor] = {}
    for name in sorted(names):
        values = [fields[name] for fields in held]
        if name in ("covers", "cover_mask"):
            values = _pad_listings(values)
        joined[name] = torch.cat(values, dim=0)
    return Batch.of(joined)


def _pad_listings(values: list[torch.Tensor]) -> list[torch.Tensor]:
    """Pad dimension 1 (the listed covers) with zeros (False) to the longest."""
    longest = max(int(value.shape[1]) for value in values)
    padded = []
    for value in values:
        extra = longest - int(value.shape[1])
        if extra:
            shape = (value.shape[0], extra, *value.shape[2:])
            value = torch.cat([value, torch.zeros(shape, dtype=value.dtype)], dim=1)
        padded.append(value)
    return padded
