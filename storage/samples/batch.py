"""The one batch type every reader gives and every trainer takes: `SampleBatch`.

A batch of samples is one `SampleBatch` whatever read it (`storage.readers.memory`, `storage.stream`,
`storage.torch`, osvp): its numpy arrays, or the same as torch tensors (`SampleBatch.tensors`). Which
cloud a reader gives is its `Source`: the refined one P(O_S) or what the input views saw.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from dataclasses import field as dataclass_field
from typing import TYPE_CHECKING, Any, Generic, Literal, TypeVar

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    import torch


KeyArray = npt.NDArray[np.int16]

Source = Literal["points", "observed"]
"""Which cloud a reader gives: the refined one P(O_S) (``points``) or what the input views saw."""

SOURCES: tuple[Source, ...] = ("points", "observed")

ArrayT = TypeVar("ArrayT")

OtherT = TypeVar("OtherT")


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
    ``cover_mask``). Every field is registered in `storage.samples.sample_fields`; one this class does not
    declare (a plug-in's) is in ``extra``, by name. A DataLoader pins it (`pin_memory`) and passes it
    through untouched.
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
    probabilities indexed [x, y, z], 0.5 unknown (`storage.samples.occupancy_grid`)."""
    extra: Mapping[str, ArrayT] = dataclass_field(default_factory=dict)
    """Registered fields this class does not declare, by name."""

    @classmethod
    def of(cls, values: Mapping[str, ArrayT]) -> SampleBatch[ArrayT]:
        """The batch of these fields by name: declared ones as attributes, any other in ``extra``."""
        known = _declared()
        return cls(
            **{name: value for name, value in values.items() if name in known},
            extra={name: value for name, value in sorted(values.items()) if name not in known},
        )

    def __len__(self) -> int:
        return len(self.index)  # type: ignore[arg-type]

    def as_dict(self) -> dict[str, ArrayT]:
        """The fields that are present, by name (``extra``'s among them)."""
        found = ((name, getattr(self, name)) for name in _declared())
        return {name: value for name, value in found if value is not None} | dict(self.extra)

    def field(self, name: str) -> ArrayT:
        """Field ``name``, declared or in ``extra`` (a `KeyError` when the batch lacks it)."""
        found = self.as_dict().get(name)
        if found is None:
            raise KeyError(f"this batch has no field {name!r}; it has {', '.join(self.as_dict())}")
        return found

    def map(self, convert: Callable[[ArrayT], OtherT]) -> SampleBatch[OtherT]:
        """Every present field through ``convert`` (absent ones stay None)."""
        return SampleBatch.of({name: convert(value) for name, value in self.as_dict().items()})

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


def _declared() -> tuple[str, ...]:
    """The fields `SampleBatch` holds as attributes."""
    return tuple(found.name for found in fields(SampleBatch) if found.name != "extra")
