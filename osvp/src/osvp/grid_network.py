"""Grid-input planners: a 3D CNN over the case's 32^3 occupancy grid, in the manner of NBVNet and SCVP.

Both families of the AIR-OSVP paper's Tables II and III that read MA-SCVP's occupancy grid
(docs/pipeline.md section 8.2) share one body here:

- ``nbvnet`` (Mendoza et al., 2020): the grid alone in, one logit per candidate view out, trained as a
  classification of the best next view (target ``best_view``) and played step by step.
- ``scvp`` (Pan et al., 2022): the grid and the view state in, one logit per view out, trained on the
  set-cover label (the cover targets) and played one shot.

The body is NBVNet's: three blocks of a 3x3x3 convolution, a ReLU and a 2x max pool (32 -> 4 cells a
side), then fully connected layers with dropout. SCVP concatenates the view state to the flattened
grid features before the fully connected layers, as its network does. Occupancy probabilities enter
centred, ``2 (p - 0.5)``, so an unknown cell is 0 and the convolutions see free space and surface
with opposite signs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch
from torch import Tensor, nn

from storage.samples import GRID_SIDE


@dataclass(frozen=True)
class GridPreset:
    """Every size of a grid network, as plain numbers (stored in checkpoints)."""

    name: str
    channels: tuple[int, int, int]
    """Filters of the three convolution blocks (NBVNet: 10, 12, 8)."""
    hidden: tuple[int, ...]
    """Widths of the fully connected layers before the output (NBVNet: 1500, 500, 100)."""
    view_state: bool
    """Whether the view state joins the grid features (SCVP) or not (NBVNet)."""
    dropout: float

    num_points = 1
    """A grid network reads no cloud; the sample contract's batch still carries one point per sample."""

    def as_dict(self) -> dict[str, object]:
        data = asdict(self)
        data["channels"], data["hidden"] = list(self.channels), list(self.hidden)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> GridPreset:
        expected = {f.name for f in fields(cls)}
        if not isinstance(data, dict) or set(data) != expected:
            got = sorted(data) if isinstance(data, dict) else type(data).__name__
            raise ValueError(f"a grid preset needs exactly {sorted(expected)}, got {got}")
        channels, hidden = data["channels"], data["hidden"]
        if not isinstance(channels, (list, tuple)) or len(channels) != 3 or not isinstance(hidden, (list, tuple)):
            raise ValueError(f"channels must be three numbers and hidden a list, got {channels!r}, {hidden!r}")
        preset = cls(
            name=str(data["name"]),
            channels=(int(channels[0]), int(channels[1]), int(channels[2])),
            hidden=tuple(int(h) for h in hidden),
            view_state=bool(data["view_state"]),
            dropout=float(data["dropout"]),  # type: ignore[arg-type]
        )
        if min(preset.channels) < 1 or any(h < 1 for h in preset.hidden):
            raise ValueError(f"every width of grid preset {preset.name!r} must be a positive whole number")
        if not 0.0 <= preset.dropout < 1.0:
            raise ValueError(f"grid preset {preset.name!r}: dropout {preset.dropout} must be in [0, 1)")
        return preset


NBVNET_PRESETS: dict[str, GridPreset] = {
    "paper": GridPreset("paper", (10, 12, 8), (1500, 500, 100), False, 0.3),
    "small": GridPreset("small", (10, 12, 8), (512, 256), False, 0.3),
}
"""NBVNet's sizes (``paper``) and a narrower head for CPU runs (``small``)."""

SCVP_PRESETS: dict[str, GridPreset] = {
    name: GridPreset(name, preset.channels, preset.hidden, True, preset.dropout)
    for name, preset in NBVNET_PRESETS.items()
}
"""The same sizes with the view state joined to the grid features."""


class GridNetwork(nn.Module):
    """(grid (B, 32, 32, 32) occupancy probabilities, view state (B, n) 0/1) -> one logit per view (B, n)."""

    def __init__(self, preset: GridPreset, num_views: int) -> None:
        super().__init__()
        if num_views < 1:
            raise ValueError(f"num_views = {num_views} must be >= 1")
        self.preset = preset
        self.num_views = num_views
        blocks: list[nn.Module] = []
        inputs = 1
        for width in preset.channels:
            blocks += [nn.Conv3d(inputs, width, 3, padding=1), nn.ReLU(), nn.MaxPool3d(2)]
            inputs = width
        self.body = nn.Sequential(*blocks, nn.Flatten())
        side = GRID_SIDE // 2 ** len(preset.channels)
        width = inputs * side**3 + (num_views if preset.view_state else 0)
        layers: list[nn.Module] = []
        for hidden in preset.hidden:
            layers += [nn.Linear(width, hidden), nn.ReLU(), nn.Dropout(preset.dropout)]
            width = hidden
        layers.append(nn.Linear(width, num_views))
        self.head = nn.Sequential(*layers)

    def forward(self, grid: Tensor, view_state: Tensor) -> Tensor:
        batch = grid.shape[0]
        if grid.shape[1:] != (GRID_SIDE, GRID_SIDE, GRID_SIDE):
            raise ValueError(f"grid must be (B, {GRID_SIDE}, {GRID_SIDE}, {GRID_SIDE}), got {tuple(grid.shape)}")
        if view_state.shape != (batch, self.num_views):
            raise ValueError(f"view_state must be ({batch}, {self.num_views}), got {tuple(view_state.shape)}")
        features = self.body((2.0 * grid.to(torch.float32) - 1.0)[:, None])
        if self.preset.view_state:
            features = torch.cat([features, view_state.to(features.dtype)], dim=1)
        return self.head(features)
