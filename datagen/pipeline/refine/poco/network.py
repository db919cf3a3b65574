"""POCO (Boulch & Marlet, CVPR 2022) in plain PyTorch: FKAConv U-Net encoder + attention decoder.

The module tree and parameter names mirror the official release (``net`` = backbone, ``projection``
= decoder, and every attribute below them), so its checkpoints load with ``strict=True``; this is
also why the dead ``cv5``/``bn5`` layers exist. Tensors are channels-first: positions (B, 3, N),
features (B, C, N), neighbour tables (B, N_target, K) of indices into the source level.
The neighbour tables come from `datagen.pipeline.refine.poco.spatial.spatial_tables`.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from datagen.pipeline.refine.poco import spatial
from datagen.pipeline.refine.poco.presets import PocoPreset, get_preset
from datagen.pipeline.refine.poco.spatial import GeneratorLike, KnnBackend, level_points

_DECODER_BUDGET = 1 << 21
"""Elements of one (queries x K x width) decoder activation per chunk: bounds memory, keeps it in cache."""
_INFERENCE_BUDGET = 1 << 19
"""The same for `PocoModel.decode_inference`: 2 MiB of float32 per activation, so a chunk's activations
stay in a core's L2 cache (measured on the 2-core CPU: 8192-query chunks of the small preset, 16 MiB
each, ran 2.4x slower than 1024-query ones, with bit-identical logits)."""


def neighbour_distances(local: Tensor, fast: bool = True) -> Tensor:
    """Euclidean lengths of local offsets (B, 3, M, K) over the coordinate axis -> (B, M, K).

    Bit-identical to ``local.norm(dim=1)``, which on CPU runs a scalar loop for this layout (4 ms for
    one 3000 x 16 neighbourhood table, a sixth of a level-0 FKAConv). That kernel rounds
    ``(x*x + y*y) + z*z`` in float32, in this order, without fused multiply-adds, then takes the
    correctly rounded root (``std::sqrt``); here the sum is the same float32 vector ops and the root is
    numpy's, the correctly rounded hardware one. torch's vectorised ``sqrt`` is not correctly rounded
    (it differs in ~0.6 % of float32 values), hence numpy. Other dtypes, devices or shapes, and
    ``fast=False`` (the original operations, for the tests that compare the two), use ``norm``.
    """
    if not fast or local.device.type != "cpu" or local.dtype != torch.float32 or local.shape[1] != 3:
        return local.norm(dim=1)
    square = local * local
    total = (square[:, 0] + square[:, 1]).add_(square[:, 2])
    np.sqrt(total.numpy(), out=total.numpy())
    return total


def gather_channels_last(values: Tensor, index: Tensor) -> Tensor:
    """values (B, N, C) indexed by index (B, M, K) -> (B, M, K, C) (one flat index_select)."""
    batch, n, channels = values.shape
    offset = (torch.arange(batch, device=index.device) * n).view(batch, 1, 1)
    flat = values.reshape(batch * n, channels).index_select(0, (index + offset).reshape(-1))
    return flat.view(*index.shape, channels)


def gather_neighbours(values: Tensor, index: Tensor) -> Tensor:
    """values (B, C, N) indexed by index (B, M, K) -> (B, C, M, K)."""
    batch, channels, _ = values.shape
    flat = index.reshape(batch, 1, -1).expand(-1, channels, -1)
    return torch.gather(values, 2, flat).view(batch, channels, *index.shape[1:])


_TREE_MAX_FROM = 1 << 16
"""Elements from which `neighbour_max` compares halves instead of calling ``amax``: below it the
tree's four calls cost more than they save (4x slower on a (2, 8, 100, 32) table)."""


def neighbour_max(values: Tensor, keepdim: bool = False, fast: bool = True) -> Tensor:
    """Max of (B, C, M, K) over K. Without autograd ``amax``, or a tree of elementwise maxima for a
    power-of-two K (2x and ~3.5x faster than ``max``: no argmax); with it, or with
    ``fast=False``, ``max(...).values``, whose gradient goes to one of tied maxima where amax's would be
    split among them (ReLU zeros tie often). The values are the same either way."""
    if not fast or (torch.is_grad_enabled() and values.requires_grad):
        return values.max(dim=3, keepdim=keepdim).values
    width = values.shape[3]
    if width < 2 or width & (width - 1) or values.numel() < _TREE_MAX_FROM:
        return values.amax(dim=3, keepdim=keepdim)
    # A power-of-two K: halves compared elementwise until one column is left, 1.4-1.8x faster than
    # amax's short inner reduction (K = 16 in the encoder); a maximum is exact, so the same values.
    while width > 1:
        width //= 2
        values = torch.maximum(values[..., :width], values[..., width:])
    return values if keepdim else values.squeeze(3)


def max_pool(values: Tensor, index: Tensor, fast: bool = True) -> Tensor:
    """Max of (B, C, N) over each neighbourhood of index (B, M, K) -> (B, C, M)."""
    return neighbour_max(gather_neighbours(values, index), fast=fast)


def upsample_nearest(values: Tensor, index: Tensor) -> Tensor:
    """Copy coarse features (B, C, N_coarse) to fine points through a K = 1 table (B, N_fine, 1)."""
    return gather_neighbours(values, index[:, :, :1]).squeeze(3)


class FKAConv(nn.Module):
    """FKAConv point convolution (adaptive normalisation variant, as in POCO).

    A small MLP maps each neighbour's normalised offset (with neighbourhood context from two
    distance-weighted max-pools) to ``kernel_size`` soft slot weights; the neighbours' features are
    projected onto the slots and a dense (Cout x Cin*S) matrix mixes them. ``norm_radius`` is a running
    statistic kept as a frozen Parameter because that is the released checkpoints' key type.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 16, dim: int = 3) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.radius_momentum = 0.1
        self.cv = nn.Conv2d(in_channels, out_channels, (1, kernel_size), bias=False)
        self.norm_radius = nn.Parameter(torch.ones(1), requires_grad=False)
        self.alpha = nn.Parameter(torch.ones(1))
        self.beta = nn.Parameter(torch.ones(1))
        self.fc1 = nn.Conv2d(dim, kernel_size, 1, bias=False)
        self.fc2 = nn.Conv2d(2 * kernel_size, kernel_size, 1, bias=False)
        self.fc3 = nn.Conv2d(2 * kernel_size, kernel_size, 1, bias=False)
        self.bn1 = nn.InstanceNorm2d(kernel_size, affine=True)
        self.bn2 = nn.InstanceNorm2d(kernel_size, affine=True)

    def forward(self, x: Tensor, pos: Tensor, support: Tensor, index: Tensor, fast: bool = True) -> Tensor:
        """x (B, Cin, N), pos (B, 3, N), support (B, 3, M), index (B, M, K) into pos -> (B, Cout, M);
        ``fast=False`` runs the original operations (the same values)."""
        batch, _, m, k = (*support.shape, index.shape[2])
        local = gather_neighbours(pos, index) - support.unsqueeze(3)  # (B, 3, M, K)
        distances = neighbour_distances(local.detach(), fast)  # (B, M, K)
        if self.training:
            # Running mean of the neighbourhood radius, updated before use (as upstream).
            mean_radius = distances.max(dim=2).values.mean()
            self.norm_radius.data.mul_(1.0 - self.radius_momentum).add_(self.radius_momentum * mean_radius)
        local = local / self.norm_radius

        # Distance weights from raw distances, rescaled to average ~1 over each neighbourhood.
        weight = torch.sigmoid(-self.alpha * distances + self.beta)
        total = weight.sum(dim=2, keepdim=True)
        total = total + (total == 0).to(total.dtype) + 1e-6
        weight = (weight / total * k).unsqueeze(1)  # (B, 1, M, K)

        # InstanceNorm statistics span every neighbourhood of the cloud (per sample and channel).
        use_norm = k > 1
        mat = self.fc1(local)
        mat = self._norm_relu(self.bn1, mat, fast) if use_norm else F.relu(mat)
        pooled = neighbour_max(mat * weight, keepdim=True, fast=fast).expand(-1, -1, -1, k)
        mat = self.fc2(torch.cat([mat, pooled], dim=1))
        mat = self._norm_relu(self.bn2, mat, fast) if use_norm else F.relu(mat)
        pooled = neighbour_max(mat * weight, keepdim=True, fast=fast).expand(-1, -1, -1, k)
        mat = F.relu(self.fc3(torch.cat([mat, pooled], dim=1))) * weight  # (B, S, M, K)

        # Project neighbour features on the slots: (B, M, Cin, K) @ (B, M, K, S) -> (B, M, Cin, S).
        feats = gather_channels_last(x.transpose(1, 2), index).transpose(2, 3)
        slots = torch.matmul(feats, mat.permute(0, 2, 3, 1))
        out = F.linear(slots.reshape(batch, m, -1), self.cv.weight.reshape(self.out_channels, -1))
        return out.transpose(1, 2)

    @staticmethod
    def _norm_relu(norm: nn.InstanceNorm2d, mat: Tensor, fast: bool = True) -> Tensor:
        """ReLU(norm(mat)). Without autograd, for one sample on CPU, it makes the very ``batch_norm``
        call that ``instance_norm`` makes (whose reshape to (1, B * C, M, K) is then the identity),
        without its wrapping (0.9 ms of 2.3 on a 3000 x 16 table), and the ReLU in place: the same values."""
        if (
            not fast
            or torch.is_grad_enabled()
            or mat.shape[0] != 1
            or mat.device.type != "cpu"
            or norm.track_running_stats
            or not mat.is_contiguous()
        ):
            return F.relu(norm(mat))
        momentum = norm.momentum if norm.momentum is not None else 0.0
        out = F.batch_norm(mat, None, None, norm.weight, norm.bias, True, momentum, norm.eps)
        return out.relu_()


class ResidualBlock(nn.Module):
    """Bottleneck block: 1x1 conv C -> C/2, FKAConv C/2 -> C/2, 1x1 conv C/2 -> C', plus a shortcut.

    When the block moves to a coarser level the shortcut is max-pooled over the same neighbourhoods.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 16) -> None:
        super().__init__()
        mid = in_channels // 2
        self.cv0 = nn.Conv1d(in_channels, mid, 1)
        self.bn0 = nn.BatchNorm1d(mid)
        self.cv1 = FKAConv(mid, mid, kernel_size)
        self.bn1 = nn.BatchNorm1d(mid)
        self.cv2 = nn.Conv1d(mid, out_channels, 1)
        self.bn2 = nn.BatchNorm1d(out_channels)
        self.shortcut: nn.Module = nn.Identity()
        self.bn_shortcut: nn.Module = nn.Identity()
        if in_channels != out_channels:
            self.shortcut = nn.Conv1d(in_channels, out_channels, 1)
            self.bn_shortcut = nn.BatchNorm1d(out_channels)

    def forward(self, x: Tensor, pos: Tensor, support: Tensor, index: Tensor, fast: bool = True) -> Tensor:
        h = F.relu(self.bn0(self.cv0(x)))
        h = F.relu(self.bn1(self.cv1(h, pos, support, index, fast)))
        h = self.bn2(self.cv2(h))
        short = self.bn_shortcut(self.shortcut(x))
        if short.shape[2] != h.shape[2]:
            short = max_pool(short, index, fast)
        return F.relu(h + short)


class FKAConvBackbone(nn.Module):
    """The FKAConv U-Net: five levels (widths h .. 16h) down, nearest-neighbour upsampling back up.

    ``cv5``/``bn5`` are the released model's dead branch (its output is overwritten upstream): they
    exist so checkpoints load, and are never computed, which leaves the output unchanged. One visible
    difference: upstream, train mode still updates bn5's running statistics; here they keep their
    loaded values (nothing ever reads them).
    """

    def __init__(self, in_channels: int, out_channels: int, hidden: int = 64, kernel_size: int = 16) -> None:
        super().__init__()
        h = hidden
        self.cv0 = FKAConv(in_channels, h, kernel_size)
        self.bn0 = nn.BatchNorm1d(h)
        self.resnetb01 = ResidualBlock(h, h, kernel_size)
        self.resnetb10 = ResidualBlock(h, 2 * h, kernel_size)
        self.resnetb11 = ResidualBlock(2 * h, 2 * h, kernel_size)
        self.resnetb20 = ResidualBlock(2 * h, 4 * h, kernel_size)
        self.resnetb21 = ResidualBlock(4 * h, 4 * h, kernel_size)
        self.resnetb30 = ResidualBlock(4 * h, 8 * h, kernel_size)
        self.resnetb31 = ResidualBlock(8 * h, 8 * h, kernel_size)
        self.resnetb40 = ResidualBlock(8 * h, 16 * h, kernel_size)
        self.resnetb41 = ResidualBlock(16 * h, 16 * h, kernel_size)
        self.cv5 = nn.Conv1d(32 * h, 16 * h, 1)
        self.bn5 = nn.BatchNorm1d(16 * h)
        self.cv3d = nn.Conv1d(24 * h, 8 * h, 1)
        self.bn3d = nn.BatchNorm1d(8 * h)
        self.cv2d = nn.Conv1d(12 * h, 4 * h, 1)
        self.bn2d = nn.BatchNorm1d(4 * h)
        self.cv1d = nn.Conv1d(6 * h, 2 * h, 1)
        self.bn1d = nn.BatchNorm1d(2 * h)
        self.cv0d = nn.Conv1d(3 * h, h, 1)
        self.bn0d = nn.BatchNorm1d(h)
        self.fcout = nn.Conv1d(h, out_channels, 1)
        self.dropout = nn.Dropout(0.0)

    def forward(self, x: Tensor, pos: Tensor, tables: dict[str, Tensor], fast: bool = True) -> Tensor:
        """x (B, C, N) input features, pos (B, 3, N) -> per-point latents (B, out, N); ``fast=False`` runs
        the original operations of the point convolutions (the same values)."""
        p0, p1, p2, p3, p4 = level_points(pos, tables)
        x0 = F.relu(self.bn0(self.cv0(x, p0, p0, tables["ids00"], fast)))
        x0 = self.resnetb01(x0, p0, p0, tables["ids00"], fast)
        x1 = self.resnetb10(x0, p0, p1, tables["ids01"], fast)
        x1 = self.resnetb11(x1, p1, p1, tables["ids11"], fast)
        x2 = self.resnetb20(x1, p1, p2, tables["ids12"], fast)
        x2 = self.resnetb21(x2, p2, p2, tables["ids22"], fast)
        x3 = self.resnetb30(x2, p2, p3, tables["ids23"], fast)
        x3 = self.resnetb31(x3, p3, p3, tables["ids33"], fast)
        x4 = self.resnetb40(x3, p3, p4, tables["ids34"], fast)
        x4 = self.resnetb41(x4, p4, p4, tables["ids44"], fast)
        # The released model computes relu(bn5(cv5([x4; global max]))) here and discards it: skipped.
        x3d = F.relu(self.bn3d(self.cv3d(torch.cat([upsample_nearest(x4, tables["ids43"]), x3], dim=1))))
        x2d = F.relu(self.bn2d(self.cv2d(torch.cat([upsample_nearest(x3d, tables["ids32"]), x2], dim=1))))
        x1d = F.relu(self.bn1d(self.cv1d(torch.cat([upsample_nearest(x2d, tables["ids21"]), x1], dim=1))))
        x0d = F.relu(self.bn0d(self.cv0d(torch.cat([upsample_nearest(x1d, tables["ids10"]), x0], dim=1))))
        out: Tensor = self.fcout(self.dropout(x0d))
        return out


class InterpAttentionKHeadsNet(nn.Module):
    """POCO's decoder: multi-head attention of a query over its K nearest input points' latents.

    For neighbour j of query q: h_j = MLP([z_j; q - p_j]); weights = mean over heads of the per-head
    softmax over j of fc_query(h_j); f = sum_j w_j fc_value(h_j); logits = fc8(f) (class 1 = inside).

    Two exact evaluations: ``reference`` follows the layout above on (B, C, M, K) tensors; ``fast``
    splits fc1 into a per-input-point part (computed once) and a per-query part, and applies the
    affine fc_value after the weighted sum (valid because the weights sum to 1), in whichever memory
    layout is faster for the decoder's width (`channels_last`).
    """

    def __init__(self, latent_size: int, out_channels: int = 2, k: int = 64, heads: int = 64) -> None:
        super().__init__()
        self.latent_size = latent_size
        self.k = k
        self.heads = heads
        self.fc1 = nn.Conv2d(latent_size + 3, latent_size, 1)
        self.fc2 = nn.Conv2d(latent_size, latent_size, 1)
        self.fc3 = nn.Conv2d(latent_size, latent_size, 1)
        self.fc8 = nn.Conv1d(latent_size, out_channels, 1)
        self.fc_query = nn.Conv2d(latent_size, heads, 1)
        self.fc_value = nn.Conv2d(latent_size, latent_size, 1)
        self.fast_layout: Literal["first", "last"] | None = None

    def forward(self, latents: Tensor, pos: Tensor, queries: Tensor, index: Tensor, fast: bool = True) -> Tensor:
        """latents (B, L, N), pos (B, 3, N), queries (B, 3, M), index (B, M, K) -> logits (B, 2, M)."""
        if not fast:
            return self.forward_reference(latents, pos, queries, index)
        return self.forward_fast(self.point_terms(latents, pos), queries, index)

    def forward_reference(self, latents: Tensor, pos: Tensor, queries: Tensor, index: Tensor) -> Tensor:
        """The released layout, 1x1 convolutions on (B, C, M, K): the definition the fast path must match."""
        z = gather_neighbours(latents, index)
        offsets = queries.unsqueeze(3) - gather_neighbours(pos, index)
        h = F.relu(self.fc1(torch.cat([z, offsets], dim=1)))
        h = F.relu(self.fc2(h))
        h = F.relu(self.fc3(h))
        attention = torch.softmax(self.fc_query(h), dim=3).mean(dim=1)  # (B, M, K)
        values = self.fc_value(h)  # (B, L, M, K)
        pooled = (values * attention.unsqueeze(1)).sum(dim=3)
        out: Tensor = self.fc8(pooled)
        return out

    def point_terms(self, latents: Tensor, pos: Tensor) -> Tensor:
        """The per-input-point part of fc1, W_z z_j - W_p p_j: (B, N, L) if `channels_last`, else (B, L, N).

        Computed once per cloud; every query chunk reuses it.
        """
        weight = self.fc1.weight.flatten(1)  # (L, L + 3)
        w_latent, w_pos = weight[:, : self.latent_size], weight[:, self.latent_size :]
        terms = torch.matmul(w_latent, latents) - torch.matmul(w_pos, pos)  # (B, L, N)
        return terms.transpose(1, 2).contiguous() if self.channels_last else terms

    @property
    def channels_last(self) -> bool:
        """Layout of the fast path, chosen for speed on CPU (both are exact).

        Channels-last wins for wide decoders (the official 32 x 64 heads: large matmuls); for narrow
        ones the (B, C, M, K) layout is faster, since its softmax runs over a contiguous K axis and
        1x1 convolutions handle few channels better. ``fast_layout`` overrides the choice.
        """
        if self.fast_layout is not None:
            return self.fast_layout == "last"
        return self.latent_size * self.heads >= 1024

    def forward_fast(self, point_terms: Tensor, queries: Tensor, index: Tensor) -> Tensor:
        """Decode from `point_terms` -> logits (B, 2, M); same result as `forward_reference`."""
        w_pos = self.fc1.weight.flatten(1)[:, self.latent_size :]
        bias = self.fc1.bias
        assert bias is not None  # fc1 is built with a bias
        if not self.channels_last:
            query_terms = torch.matmul(w_pos, queries) + bias[:, None]  # (B, L, M)
            h = F.relu(gather_neighbours(point_terms, index) + query_terms.unsqueeze(3))  # (B, L, M, K)
            h = F.relu(self.fc2(h))
            h = F.relu(self.fc3(h))
            attention = torch.softmax(self.fc_query(h), dim=3).mean(dim=1)  # (B, M, K), sums to 1 over K
            pooled = (h * attention.unsqueeze(1)).sum(dim=3)  # (B, L, M)
            values = F.conv1d(pooled, self.fc_value.weight.flatten(2), self.fc_value.bias)
            out: Tensor = self.fc8(values)
            return out
        query_terms = F.linear(queries.transpose(1, 2), w_pos, bias)  # (B, M, L)
        h = F.relu(gather_channels_last(point_terms, index) + query_terms.unsqueeze(2))  # (B, M, K, L)
        h = F.relu(F.linear(h, self.fc2.weight.flatten(1), self.fc2.bias))
        h = F.relu(F.linear(h, self.fc3.weight.flatten(1), self.fc3.bias))
        logits = F.linear(h, self.fc_query.weight.flatten(1), self.fc_query.bias)  # (B, M, K, H)
        attention = torch.softmax(logits, dim=2).mean(dim=3)  # (B, M, K), sums to 1 over K
        pooled = torch.matmul(attention.unsqueeze(2), h).squeeze(2)  # (B, M, L)
        values = F.linear(pooled, self.fc_value.weight.flatten(1), self.fc_value.bias)
        return F.linear(values, self.fc8.weight.flatten(1), self.fc8.bias).transpose(1, 2)

    def query_terms(self, queries: Tensor) -> Tensor:
        """The per-query part of fc1 in the channels-first layout, W_p q + b: (B, L, M)."""
        w_pos = self.fc1.weight.flatten(1)[:, self.latent_size :]
        bias = self.fc1.bias
        assert bias is not None  # fc1 is built with a bias
        return torch.matmul(w_pos, queries) + bias[:, None]

    def pooled_inference(self, point_terms: Tensor, query_terms: Tensor, index: Tensor) -> Tensor:
        """The channels-first `forward_fast` from its `query_terms` up to the attention-pooled features
        (B, L, M), for inference: the same operations on the same values in the same order, with less
        memory traffic (neighbour rows gathered by one ``index_select``, fresh intermediates updated in
        place; no autograd). `head_inference` finishes the logits."""
        batch, channels, _ = point_terms.shape
        if batch == 1:
            rows = point_terms[0].index_select(1, index.reshape(-1)).view(1, channels, *index.shape[1:])
        else:
            rows = gather_neighbours(point_terms, index)
        h = rows.add_(query_terms.unsqueeze(3)).relu_()  # (B, L, M, K)
        h = F.conv2d(h, self.fc2.weight, self.fc2.bias).relu_()
        h = F.conv2d(h, self.fc3.weight, self.fc3.bias).relu_()
        attention = torch.softmax(F.conv2d(h, self.fc_query.weight, self.fc_query.bias), dim=3).mean(dim=1)
        pooled: Tensor = h.mul_(attention.unsqueeze(1)).sum(dim=3)  # (B, L, M)
        return pooled

    def head_inference(self, pooled: Tensor) -> Tensor:
        """Logits (B, 2, M) from pooled features: `forward_fast`'s value and output convolutions."""
        values = F.conv1d(pooled, self.fc_value.weight.flatten(2), self.fc_value.bias)
        out: Tensor = F.conv1d(values, self.fc8.weight, self.fc8.bias)
        return out


def input_features(points: Tensor, input_channels: int = 3, directions: Tensor | None = None) -> Tensor:
    """The encoder's per-point input (B, C, N): constant ones, plus unit camera directions for C = 6.

    ``directions`` (B, 3, N) point from each point towards its camera; they are normalised here.
    """
    ones = torch.ones_like(points)
    if input_channels == 3:
        return ones
    if input_channels != 6:
        raise ValueError(f"input_channels must be 3 or 6, got {input_channels}")
    if directions is None or directions.shape != points.shape:
        raise ValueError("6-channel presets need directions (B, 3, N) from each point to its camera")
    unit = directions / directions.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return torch.cat([ones, unit.to(points.dtype)], dim=1)


class PocoModel(nn.Module):
    """POCO with the official state-dict layout (``net.*``, ``projection.*``) and a small API.

    ``encode`` -> per-point latents, ``decode`` -> 2-class logits per query (class 1 = inside).
    ``fast_decoder`` selects the exact rewrite of the decoder (default) or the reference layout.
    """

    def __init__(self, preset: PocoPreset | str = "official", fast_decoder: bool = True) -> None:
        super().__init__()
        self.preset = get_preset(preset)
        self.fast_decoder = fast_decoder
        p = self.preset
        self.net = FKAConvBackbone(p.input_channels, p.latent, hidden=p.hidden, kernel_size=p.kernel_size)
        self.projection = InterpAttentionKHeadsNet(p.latent, 2, k=p.decoder_k, heads=p.heads)

    def tables(
        self,
        points: Tensor,
        generator: GeneratorLike = None,
        queries: Tensor | None = None,
        backend: KnnBackend = "auto",
        knn_device: torch.device | str | None = None,
    ) -> dict[str, Tensor]:
        """`spatial_tables` with this preset's neighbour counts and sampling ratio."""
        p = self.preset
        return spatial.spatial_tables(
            points,
            generator,
            queries=queries,
            encoder_k=p.encoder_k,
            decoder_k=p.decoder_k,
            ratio=p.sampling_ratio,
            backend=backend,
            knn_device=knn_device,
        )

    def query_knn(self, points: Tensor, queries: Tensor, backend: KnnBackend = "auto") -> Tensor:
        """Decoder table (B, M, decoder_k): each query's nearest input points (where they are)."""
        return spatial.knn(points, queries, self.preset.decoder_k, backend=backend)

    def features(self, points: Tensor, directions: Tensor | None = None) -> Tensor:
        """The encoder input this preset expects (see `input_features`)."""
        return input_features(points, self.preset.input_channels, directions)

    def encode(self, points: Tensor, features: Tensor, tables: dict[str, Tensor], fast: bool = True) -> Tensor:
        """points (B, 3, N), features (B, C, N) -> latents (B, L, N). ``fast`` (the default) uses the
        bit-identical faster operations of `neighbour_distances`, `neighbour_max` and
        `FKAConv._norm_relu`; False the original ones (torch's norm, max with indices, instance_norm),
        for the tests and benchmarks that compare the two (`PocoRefiner(fast=False)`): a choice of
        the call, so two refiners sharing one model in two threads each get their own."""
        out: Tensor = self.net(features, points, tables, fast)
        return out

    def decode(
        self,
        latents: Tensor,
        points: Tensor,
        queries: Tensor,
        knn: Tensor,
        *,
        fast: bool | None = None,
        chunk_size: int | None = None,
    ) -> Tensor:
        """latents (B, L, N), points (B, 3, N), queries (B, 3, M), knn (B, M, K) -> logits (B, 2, M).

        Queries are processed in chunks so activations stay small (results do not depend on it).
        """
        decoder = self.projection
        fast = self.fast_decoder if fast is None else fast
        batch, _, m = queries.shape
        if chunk_size is None:
            per_query = batch * knn.shape[2] * max(decoder.latent_size, decoder.heads)
            chunk_size = min(1024, max(128, _DECODER_BUDGET // max(1, per_query)))
        point_terms = decoder.point_terms(latents, points) if fast else None
        parts = []
        for start in range(0, m, chunk_size):
            q = queries[:, :, start : start + chunk_size]
            idx = knn[:, start : start + chunk_size]
            if point_terms is not None:
                parts.append(decoder.forward_fast(point_terms, q, idx))
            else:
                parts.append(decoder.forward_reference(latents, points, q, idx))
        if not parts:
            return latents.new_zeros((batch, 2, 0))
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=2)

    def decode_inference(
        self, latents: Tensor, points: Tensor, queries: Tensor, knn: Tensor, reference_chunk: int
    ) -> Tensor:
        """Logits (B, 2, M) bit-identical to ``decode(..., chunk_size=reference_chunk)`` (fast layout),
        faster, without gradients.

        Some kernels round differently by input size, and which ones depends on the CPU: the
        (L x 3) @ (3 x m) matmul of the per-query fc1 term for m <= 8 (MKL), the value convolution
        for m = 1, and on AVX2-only CPUs (AMD EPYC) the two-channel output convolution at many sizes
        (oneDNN); the 1x1 convolutions over (B, L, m, K), softmax and reductions give the same bits at
        every size. So the query terms and the two per-query convolutions (cheap: no K axis) run on
        `decode`'s chunks of ``reference_chunk``, at exactly its shapes; only the neighbour part, which
        is nearly all the work, runs in sub-chunks of `_INFERENCE_BUDGET` elements per activation
        (1024 queries for the small preset: 8192-query activations, 16 MiB, ran 2.4x slower than
        ones that stay in a core's cache), never leaving a sub-chunk of fewer than 64 queries unless
        the chunk itself is that small. The channels-last layout (wide decoders) and accelerators
        (whose kernels choose algorithms by size in other ways; not verified) run `decode` itself.
        """
        decoder = self.projection
        if decoder.channels_last or not self.fast_decoder or queries.device.type != "cpu":
            with torch.no_grad():
                return self.decode(latents, points, queries, knn, chunk_size=reference_chunk)
        batch, _, m = queries.shape
        per_query = batch * knn.shape[2] * max(decoder.latent_size, decoder.heads)
        step = max(64, _INFERENCE_BUDGET // max(1, per_query))
        parts = []
        with torch.no_grad():
            point_terms = decoder.point_terms(latents, points)
            for start in range(0, m, reference_chunk):
                stop = min(m, start + reference_chunk)
                query_terms = decoder.query_terms(queries[:, :, start:stop])
                cuts = list(range(0, stop - start, step))
                if len(cuts) > 1 and stop - start - cuts[-1] < 64:
                    cuts.pop()  # the remainder joins the previous sub-chunk
                pooled = [
                    decoder.pooled_inference(point_terms, query_terms[:, :, a:b], knn[:, start + a : start + b])
                    for a, b in zip(cuts, [*cuts[1:], stop - start], strict=True)
                ]
                parts.append(decoder.head_inference(pooled[0] if len(pooled) == 1 else torch.cat(pooled, dim=2)))
        if not parts:
            return latents.new_zeros((batch, 2, 0))
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=2)

    def forward(
        self,
        points: Tensor,
        features: Tensor,
        tables: dict[str, Tensor],
        queries: Tensor,
        knn: Tensor,
        fast: bool = True,
    ) -> Tensor:
        """Encode then decode: logits (B, 2, M) (``fast``: `encode`'s operations)."""
        return self.decode(self.encode(points, features, tables, fast), points, queries, knn)

    def count_parameters(self, trainable_only: bool = True) -> int:
        """Number of (trainable) parameters; ``norm_radius`` scalars are frozen, cv5/bn5 are counted."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad or not trainable_only)
