"""``Compose``: apply callables in order, as torchvision's does for the authors' own transform classes."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any


class Compose:
    def __init__(self, transforms: Sequence[Callable[[Any], Any]]) -> None:
        self.transforms = list(transforms)

    def __call__(self, sample: Any) -> Any:
        for transform in self.transforms:
            sample = transform(sample)
        return sample
