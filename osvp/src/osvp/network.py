"""The OSVP network (AIR-OSVP, "Network Architecture"): point-cloud transformer + view-state transformer.

- Point cloud: a PoinTr-style encoder. A DGCNN-like grouper picks centres by farthest point sampling
  in two stages and describes each by an edge convolution over its k nearest neighbours; the centres,
  with a learned embedding of their position, go through a transformer (no dropout, as PoinTr's); a
  max over them and a linear layer give the cloud feature. (PoinTr's blocks add kNN geometric
  attention; plain self-attention is used here.)
- View state: one token per candidate view (its taken/not-taken bit embedded, plus a learned
  embedding of the view's identity), a transformer, a mean over the views and a linear layer. It
  works for any number of views, which comes from the dataset.
- The two features (1,024-d in the paper) are summed; an MLP gives one logit per view.

Points are taken in the task frame the dataset uses (object centred at the origin, where the
candidate views are defined) and only scaled by `COORDINATE_SCALE`, so planners at test time see
exactly what training saw. Farthest point sampling starts at the first point and uses no RNG: the
forward pass is deterministic in eval mode.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch
from torch import Tensor, nn

COORDINATE_SCALE = 1.0 / 0.15
"""Metres to network units: the largest object the generator makes is 0.15 m across."""


@dataclass(frozen=True)
class NetworkPreset:
    """Every size of the network, as plain numbers (stored in checkpoints)."""

    name: str
    num_points: int
    """Points per input cloud the network is trained with."""
    centres: tuple[int, int]
    """Centres of the grouper's two farthest-point-sampling stages."""
    neighbours: int
    embed_dim: int
    depth: int
    heads: int
    view_dim: int
    view_layers: int
    view_heads: int
    feature_dim: int
    dropout: float
    """Dropout of the view-state transformer and the head (the point transformer has none)."""

    def as_dict(self) -> dict[str, object]:
        data = asdict(self)
        data["centres"] = list(self.centres)
        return data

    @classmethod
    def from_dict(cls, data: dict[str, object]) -> NetworkPreset:
        expected = {f.name for f in fields(cls)}
        if not isinstance(data, dict) or set(data) != expected:
            got = sorted(data) if isinstance(data, dict) else type(data).__name__
            raise ValueError(f"a network preset needs exactly {sorted(expected)}, got {got}")
        centres = data["centres"]
        if not isinstance(centres, (list, tuple)) or len(centres) != 2:
            raise ValueError(f"centres must be two numbers, got {centres!r}")
        values = {**data, "centres": (int(centres[0]), int(centres[1]))}
        preset = cls(**values)  # type: ignore[arg-type]
        sizes: list[object] = [preset.num_points, *preset.centres, preset.neighbours, preset.embed_dim, preset.depth]
        sizes += [preset.heads, preset.view_dim, preset.view_layers, preset.view_heads, preset.feature_dim]
        if any(not isinstance(v, int) or v < 1 for v in sizes):
            raise ValueError(f"every size of preset {preset.name!r} must be a positive whole number")
        if preset.embed_dim % preset.heads or preset.view_dim % preset.view_heads or preset.embed_dim % 4:
            raise ValueError(f"preset {preset.name!r}: widths must divide by their head counts (and embed_dim by 4)")
        if not 0.0 <= preset.dropout < 1.0:
            raise ValueError(f"preset {preset.name!r}: dropout {preset.dropout} must be in [0, 1)")
        return preset


PRESETS: dict[str, NetworkPreset] = {
    "paper": NetworkPreset("paper", 2048, (512, 256), 16, 384, 6, 6, 64, 4, 4, 1024, 0.1),
    "small": NetworkPreset("small", 1024, (128, 32), 16, 128, 3, 4, 32, 2, 4, 256, 0.1),
}


def farthest_point_sample(points: Tensor, count: int) -> Tensor:
    """(B, count) indices of a farthest-point sample of (B, N, 3) points, starting at index 0."""
    batch, total, _ = points.shape
    count = min(count, total)
    chosen = torch.zeros(batch, count, dtype=torch.long, device=points.device)
    nearest = torch.full((batch, total), float("inf"), device=points.device, dtype=points.dtype)
    current = torch.zeros(batch, dtype=torch.long, device=points.device)
    rows = torch.arange(batch, device=points.device)
    for step in range(count):
        chosen[:, step] = current
        distance = ((points - points[rows, current][:, None, :]) ** 2).sum(-1)
        nearest = torch.minimum(nearest, distance)
        current = nearest.argmax(dim=1)
    return chosen


def nearest_neighbours(queries: Tensor, points: Tensor, k: int) -> Tensor:
    """(B, M, k) indices of the k points nearest to each query (the query itself included)."""
    k = min(k, points.shape[1])
    return torch.cdist(queries, points).topk(k, dim=-1, largest=False).indices


def gather(values: Tensor, index: Tensor) -> Tensor:
    """values (B, N, C) at index (B, ...) -> (B, ..., C)."""
    batch = values.shape[0]
    flat = index.reshape(batch, -1)
    picked = torch.gather(values, 1, flat[..., None].expand(-1, -1, values.shape[-1]))
    return picked.reshape(*index.shape, values.shape[-1])


class EdgeConv(nn.Module):
    """Describe each centre by the max over its neighbours of an MLP of (neighbour - centre, centre)."""

    def __init__(self, inputs: int, outputs: int) -> None:
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(2 * inputs, outputs), nn.LayerNorm(outputs), nn.GELU())

    def forward(self, features: Tensor, centre_index: Tensor, neighbour_index: Tensor) -> Tensor:
        centres = gather(features, centre_index)  # (B, M, C)
        neighbours = gather(features, neighbour_index)  # (B, M, k, C)
        edges = torch.cat([neighbours - centres[:, :, None], centres[:, :, None].expand_as(neighbours)], dim=-1)
        return self.mlp(edges).max(dim=2).values


class PointCloudEncoder(nn.Module):
    """Grouper (two FPS + edge-convolution stages) and a transformer over the centres."""

    def __init__(self, preset: NetworkPreset) -> None:
        super().__init__()
        self.preset = preset
        width = preset.embed_dim
        self.stage_one = EdgeConv(3, width // 4)
        self.stage_two = EdgeConv(width // 4, width // 2)
        self.lift = nn.Linear(width // 2, width)
        self.position = nn.Sequential(nn.Linear(3, width), nn.GELU(), nn.Linear(width, width))
        # No dropout here (PoinTr's encoder has none): dropout in these blocks trained a network whose
        # eval-mode output (dropout off) blew up on small clouds, all views at logit ~ +15.
        layer = nn.TransformerEncoderLayer(
            width, preset.heads, 2 * width, 0.0, activation="gelu", batch_first=True, norm_first=True
        )
        self.blocks = nn.TransformerEncoder(layer, preset.depth, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(width)
        self.out = nn.Linear(width, preset.feature_dim)

    def forward(self, points: Tensor) -> Tensor:
        first = farthest_point_sample(points, self.preset.centres[0])
        first_xyz = gather(points, first)
        features = self.stage_one(points, first, nearest_neighbours(first_xyz, points, self.preset.neighbours))
        second = farthest_point_sample(first_xyz, self.preset.centres[1])
        second_xyz = gather(first_xyz, second)
        neighbours = nearest_neighbours(second_xyz, first_xyz, self.preset.neighbours)
        tokens = self.lift(self.stage_two(features, second, neighbours)) + self.position(second_xyz)
        tokens = self.norm(self.blocks(tokens))
        return self.out(tokens.max(dim=1).values)


class ViewStateEncoder(nn.Module):
    """One token per candidate view: its state bit and its identity, through a transformer."""

    def __init__(self, preset: NetworkPreset, num_views: int) -> None:
        super().__init__()
        self.state = nn.Embedding(2, preset.view_dim)
        self.identity = nn.Parameter(torch.zeros(num_views, preset.view_dim))
        nn.init.normal_(self.identity, std=0.02)
        layer = nn.TransformerEncoderLayer(
            preset.view_dim,
            preset.view_heads,
            2 * preset.view_dim,
            preset.dropout,
            activation="gelu",
            batch_first=True,
            norm_first=True,
        )
        self.blocks = nn.TransformerEncoder(layer, preset.view_layers, enable_nested_tensor=False)
        self.out = nn.Linear(preset.view_dim, preset.feature_dim)

    def forward(self, view_state: Tensor) -> Tensor:
        tokens = self.state((view_state > 0.5).long()) + self.identity[None]
        return self.out(self.blocks(tokens).mean(dim=1))


class OSVPNetwork(nn.Module):
    """(points (B, N, 3) metres, view state (B, n) 0/1) -> one logit per view (B, n)."""

    def __init__(self, preset: NetworkPreset, num_views: int) -> None:
        super().__init__()
        if num_views < 1:
            raise ValueError(f"num_views = {num_views} must be >= 1")
        self.preset = preset
        self.num_views = num_views
        self.cloud = PointCloudEncoder(preset)
        self.views = ViewStateEncoder(preset, num_views)
        width = preset.feature_dim
        self.head = nn.Sequential(
            nn.Linear(width, width),
            nn.GELU(),
            nn.Dropout(preset.dropout),
            nn.Linear(width, width),
            nn.GELU(),
            nn.Linear(width, num_views),
        )

    def forward(self, points: Tensor, view_state: Tensor) -> Tensor:
        if points.ndim != 3 or points.shape[-1] != 3 or points.shape[1] < 1:
            raise ValueError(f"points must be (B, N >= 1, 3), got {tuple(points.shape)}")
        if view_state.shape != (points.shape[0], self.num_views):
            raise ValueError(f"view_state must be ({points.shape[0]}, {self.num_views}), got {tuple(view_state.shape)}")
        feature = self.cloud(points * COORDINATE_SCALE) + self.views(view_state)
        return self.head(feature)


def build_network(preset: str | NetworkPreset, num_views: int) -> OSVPNetwork:
    if isinstance(preset, str):
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; choose {', '.join(sorted(PRESETS))}")
        preset = PRESETS[preset]
    return OSVPNetwork(preset, num_views)
