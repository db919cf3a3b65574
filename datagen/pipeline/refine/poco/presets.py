"""Named POCO configurations.

``official`` mirrors the released networks exactly (so their checkpoints load). The smaller presets
are ours, sized for weights trained and run on CPU: the backbone width ``hidden`` sets most of the
parameters, but the per-query decoder dominates refinement time, so they also shrink the decoder
(latent width, neighbour count K, attention heads) and the query budget.

A ``_sv`` variant feeds each point its unit direction to the camera next to the constant ones
(6 input channels; after Sulzer et al.'s "sensor vector" POCO), which changes only ``net.cv0``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass


@dataclass(frozen=True)
class PocoPreset:
    """Architecture and input sizes of one POCO configuration."""

    name: str
    hidden: int
    """Backbone width at the finest level (64 -> 1024 over five levels for 64)."""
    latent: int
    """Per-point latent size = decoder width."""
    decoder_k: int
    """Input points each query attends to."""
    heads: int
    """Attention heads of the decoder (softmaxed separately, then averaged)."""
    input_channels: int = 3
    """3: constant ones (POCO); 6: ones + unit direction to the camera (``_sv`` variants)."""
    num_input_points: int = 3000
    """Points fed to the encoder per sample (training and inference)."""
    num_queries: int = 2048
    """Labelled queries per training sample."""
    encoder_k: int = 16
    """Neighbours per FKAConv neighbourhood."""
    kernel_size: int = 16
    """FKAConv kernel slots."""
    sampling_ratio: float = 0.25
    """Fraction of points kept per level by quantized sampling."""

    def __post_init__(self) -> None:
        if self.input_channels not in (3, 6):
            raise ValueError(
                f"input_channels must be 3 (ones) or 6 (ones + camera direction), got {self.input_channels}"
            )
        if self.hidden < 2 or self.hidden % 2:
            raise ValueError(f"hidden must be an even width >= 2, got {self.hidden}")
        for field in ("latent", "decoder_k", "heads", "num_input_points", "num_queries", "encoder_k", "kernel_size"):
            if getattr(self, field) < 1:
                raise ValueError(f"{field} must be >= 1")
        if not 0.0 < self.sampling_ratio <= 1.0:
            raise ValueError(f"sampling_ratio must be in (0, 1], got {self.sampling_ratio}")

    @property
    def uses_directions(self) -> bool:
        return self.input_channels == 6

    def with_directions(self) -> PocoPreset:
        """The same preset with camera directions as extra input channels (name suffix ``_sv``)."""
        if self.uses_directions:
            return self
        return dataclasses.replace(self, name=f"{self.name}_sv", input_channels=6)


OFFICIAL = PocoPreset(name="official", hidden=64, latent=32, decoder_k=64, heads=64, num_input_points=3000)
"""valeoai/POCO ShapeNet_3k (and AIR-OSVP): 12.79 M parameters, ~0.5 MFLOP per query."""

SMALL = PocoPreset(name="small", hidden=16, latent=16, decoder_k=32, heads=8, num_input_points=3000, num_queries=2048)
"""~1/16 of the official backbone, a decoder ~15x cheaper per query (latent 16, K 32, 8 heads)."""

TINY = PocoPreset(name="tiny", hidden=8, latent=16, decoder_k=16, heads=4, num_input_points=2048, num_queries=1024)
"""Smoke-test and fast-CPU size: K 16 and 4 heads; 2048 input points."""

FAST = PocoPreset(name="fast", hidden=16, latent=16, decoder_k=16, heads=8, num_input_points=1500, num_queries=2048)
"""``small`` with half its decoder neighbours (K 16) and half its encoder input (1,500 points): the
same weight shapes, so ``small`` weights start its training (`datagen poco train --init`), at 0.52x
of ``small``'s refinement CPU (benchmarks/generation/results/task-cost-v4.md; issue 50)."""

PRESETS: dict[str, PocoPreset] = {
    p.name: p for base in (OFFICIAL, SMALL, TINY, FAST) for p in (base, base.with_directions())
}


def get_preset(name: str | PocoPreset) -> PocoPreset:
    """The preset of that name (``official``, ``small``, ``tiny``, ``fast``, each also with ``_sv``)."""
    if isinstance(name, PocoPreset):
        return name
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown POCO preset {name!r}; known: {', '.join(sorted(PRESETS))}") from None
