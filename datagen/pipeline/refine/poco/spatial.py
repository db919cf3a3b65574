"""POCO's spatial preprocessing: quantized sampling and the kNN index tables.

Everything here is index bookkeeping done without gradients before the network runs: four nested
subsamplings (ratio 0.25 each) by quantized sampling, the K = 16 neighbour tables ``idsAB`` (for each
level-B point, its neighbours among level A), the K = 1 upsampling tables and the decoder table
(each query's K nearest input points). All randomness comes from an explicit generator, so a table set
is reproducible from a seed; nothing touches the global RNG.

Conventions (channels-first, as in the network): positions are (B, 3, N) tensors, tables are
(B, N_target, K) int64 indices into the *source* points.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from typing import Literal

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

KnnBackend = Literal["auto", "scipy", "pykdtree", "torch", "ordered"]
GeneratorLike = torch.Generator | np.random.Generator | int | None

LEVELS = 4
"""Number of subsampled levels below the input (the backbone is built for exactly four)."""

# Pairs (source level, target level) of the K = 16 tables, and of the K = 1 upsampling tables.
CONV_TABLES: tuple[tuple[int, int], ...] = ((0, 0), (0, 1), (1, 1), (1, 2), (2, 2), (2, 3), (3, 3), (3, 4), (4, 4))
UP_TABLES: tuple[tuple[int, int], ...] = ((4, 3), (3, 2), (2, 1), (1, 0))

_MAX_DISTANCES = 1 << 24
"""Distances held at once by the torch kNN backend (64 MiB of float32): bounds memory, not results."""


def pykdtree_available() -> bool:
    """Whether the optional ``pykdtree`` backend can be used (it is a little faster than scipy)."""
    try:
        import pykdtree.kdtree  # noqa: F401
    except ImportError:
        return False
    return True


def torch_generator(generator: GeneratorLike) -> torch.Generator:
    """A CPU torch generator from whatever the caller seeds with.

    A numpy Generator (or an int seed) is turned into a torch one by drawing a seed from it, so one
    seeded object drives everything; ``None`` means fresh OS entropy (not reproducible, by request).
    """
    if isinstance(generator, torch.Generator):
        return generator
    if isinstance(generator, np.random.Generator):
        seed = int(generator.integers(0, 2**63 - 1))
    elif isinstance(generator, int):
        seed = generator
    else:
        seed = int.from_bytes(os.urandom(8), "little") >> 1
    return torch.Generator().manual_seed(seed)


# --------------------------------------------------------------------------------------------------
# kNN


def knn(
    source: Tensor,
    target: Tensor,
    k: int,
    *,
    backend: KnnBackend = "auto",
    workers: int | None = None,
) -> Tensor:
    """Indices of the k nearest source points of every target point (exact Euclidean kNN).

    ``source`` (B, 3, N) and ``target`` (B, 3, M), or unbatched (3, N) / (3, M). Returns (B, M, k')
    int64 on ``target``'s device, k' = min(k, N), nearest first; a target equal to a source point
    finds itself. Backends: ``scipy`` (cKDTree, using torch's thread count) and the optional
    ``pykdtree`` (OpenMP threads) run on CPU, ``torch`` (chunked squared distances + topk) runs
    anywhere; ``auto`` picks scipy on CPU and torch on an accelerator.
    Neighbour order and ties may differ between those backends: every consumer is order-invariant over
    K. ``ordered`` is the one defined answer (`knn_ordered`), the same on every device.
    """
    if source.ndim == 2:
        return knn(source[None], target[None], k, backend=backend, workers=workers)[0]
    if source.ndim != 3 or target.ndim != 3 or source.shape[1] != target.shape[1] or source.shape[0] != target.shape[0]:
        raise ValueError(f"knn expects (B, D, N) and (B, D, M), got {tuple(source.shape)} and {tuple(target.shape)}")
    batch, _, n_source = source.shape
    n_target = target.shape[2]
    if n_source == 0:
        raise ValueError("knn needs at least one source point")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    k = min(k, n_source)
    if n_target == 0:
        return torch.empty((batch, 0, k), dtype=torch.int64, device=target.device)
    if backend == "auto":
        # scipy (a declared dependency) on CPU so results never depend on optional installs.
        backend = "scipy" if target.device.type == "cpu" else "torch"
    with torch.no_grad():
        if backend == "ordered":
            return knn_ordered(source, target, k)
        if backend == "torch":
            return _knn_torch(source, target, k)
        if backend in ("scipy", "pykdtree"):
            return _knn_tree(source, target, k, backend, workers).to(target.device)
    raise ValueError(f"unknown kNN backend {backend!r}")


def _knn_tree(source: Tensor, target: Tensor, k: int, backend: str, workers: int | None) -> Tensor:
    """kNN with a k-d tree per sample; float64 so ties are decided as exactly as the data allows."""
    src = source.detach().to("cpu", torch.float64).transpose(1, 2).contiguous().numpy()
    dst = target.detach().to("cpu", torch.float64).transpose(1, 2).contiguous().numpy()
    out = np.empty((src.shape[0], dst.shape[1], k), dtype=np.int64)
    for b in range(src.shape[0]):
        if backend == "pykdtree":
            from pykdtree.kdtree import KDTree

            _, idx = KDTree(src[b]).query(dst[b], k=k)
        else:
            from scipy.spatial import cKDTree

            # One worker per torch thread: the caller's thread budget governs the tree too.
            _, idx = cKDTree(src[b]).query(dst[b], k=k, workers=workers or torch.get_num_threads())
        out[b] = np.asarray(idx, dtype=np.int64).reshape(dst.shape[1], k)
    return torch.from_numpy(out)


def _knn_torch(source: Tensor, target: Tensor, k: int) -> Tensor:
    """Squared distances by matmul, in chunks of targets so memory stays bounded, then topk."""
    src = source.detach().transpose(1, 2)  # (B, N, 3)
    dst = target.detach().transpose(1, 2)  # (B, M, 3)
    src_sq = (src * src).sum(-1)  # (B, N)
    batch, n_source = src.shape[:2]
    chunk = max(1, _MAX_DISTANCES // max(1, batch * n_source))
    parts = []
    for start in range(0, dst.shape[1], chunk):
        q = dst[:, start : start + chunk]
        d2 = (q * q).sum(-1, keepdim=True) - 2.0 * torch.bmm(q, src.transpose(1, 2)) + src_sq[:, None, :]
        parts.append(torch.topk(d2, k, dim=2, largest=False, sorted=True).indices)
    return torch.cat(parts, dim=1)


# --------------------------------------------------------------------------------------------------
# kNN with one defined answer (refiner version 3)

ORDERED_SPARE = 4
"""Neighbours a tree fetches beyond k, so that ties across the k-th place are seen and resolved."""
_TREE_SLACK = 16.0
"""A tree's distances may be off by a few rounding units of the largest coordinate: a gap between the
k-th and the farthest fetched candidate wider than this many units proves nothing unfetched can tie."""


def ordered_sq_distances(source: Tensor, target: Tensor) -> Tensor:
    """Squared distances (B, M, N) in float64 as ``(dx*dx + dy*dy) + dz*dz``, each operation its own.

    Float32 coordinates make every difference and square exact in float64, and the two sums are
    rounded in a fixed order with no fused multiply-add, so every device computes the same bits and a
    tie is a tie everywhere.
    """
    src = source.detach().to(torch.float64)
    dst = target.detach().to(torch.float64)
    total: Tensor | None = None
    for axis in range(src.shape[1]):
        diff = dst[:, axis, :, None] - src[:, axis, None, :]
        square = diff * diff
        total = square if total is None else total + square
    assert total is not None
    return total


def knn_ordered(source: Tensor, target: Tensor, k: int) -> Tensor:
    """The k nearest source points of every target, ordered by (squared distance, source index).

    Exact and defined, not just exact: among points at equal distance the lower index comes first, so
    the answer (order included) is a function of the inputs alone, whatever the device or search. On
    the CPU a k-d tree proposes k + `ORDERED_SPARE` candidates, ordered exactly, and rows whose ties
    reach past them ask again for more; on an accelerator the distances are computed in tiles of targets
    and sorted stably. ``source`` (B, 3, N), ``target`` (B, 3, M); returns (B, M, min(k, N)) int64 on
    ``target``'s device.
    """
    k = min(k, source.shape[2])
    with torch.no_grad():
        if target.device.type == "cpu":
            return _knn_ordered_tree(source, target, k)
        return _knn_ordered_brute(source, target, k)


def _knn_ordered_brute(source: Tensor, target: Tensor, k: int) -> Tensor:
    """`knn_ordered` by every distance: tiles of targets, a stable sort of each row (ties by index)."""
    batch, _, n_source = source.shape
    chunk = max(1, (_MAX_DISTANCES // 2) // max(1, batch * n_source))
    parts = []
    for start in range(0, target.shape[2], chunk):
        d2 = ordered_sq_distances(source, target[:, :, start : start + chunk])
        parts.append(torch.sort(d2, dim=2, stable=True).indices[:, :, :k])
    return torch.cat(parts, dim=1) if parts else torch.empty((batch, 0, k), dtype=torch.int64, device=target.device)


def _knn_ordered_tree(source: Tensor, target: Tensor, k: int) -> Tensor:
    """`knn_ordered` on the CPU: a k-d tree's candidates (pykdtree when installed, else scipy's
    cKDTree), ordered exactly; rows whose ties reach past the candidates fetched are asked again
    with twice as many (every point at the last). The tree only proposes: the answer is the same
    whichever tree, and however it rounds."""
    batch, _, n_source = source.shape
    out = np.empty((batch, target.shape[2], k), dtype=np.int64)
    for b in range(batch):
        src32 = np.ascontiguousarray(source[b].detach().to("cpu", torch.float32).T.numpy())
        dst32 = np.ascontiguousarray(target[b].detach().to("cpu", torch.float32).T.numpy())
        src, dst = src32.astype(np.float64), dst32.astype(np.float64)
        query, unit = _candidate_search(src32)
        scale = max(float(np.abs(src).max(initial=0.0)), float(np.abs(dst).max(initial=0.0)))
        slack = _TREE_SLACK * unit * max(scale, np.finfo(np.float64).tiny)
        rows = np.arange(dst.shape[0])
        fetch = min(n_source, k + ORDERED_SPARE)
        while rows.size:
            candidates = query(dst32[rows], fetch)
            d2 = _row_sq_distances(src, dst[rows], candidates)
            candidates, d2 = _by_distance_then_index(candidates, d2)
            out[b, rows] = candidates[:, :k]
            if fetch == n_source:
                break
            rows = rows[np.sqrt(d2[:, -1]) - np.sqrt(d2[:, k - 1]) <= slack]
            fetch = min(n_source, fetch * 2)
    return torch.from_numpy(out).to(target.device)


def _candidate_search(
    src32: npt.NDArray[np.float32],
) -> tuple[Callable[[npt.NDArray[np.float32], int], npt.NDArray[np.int64]], float]:
    """A k-nearest query over ``src32`` and the relative rounding unit of the distances it compares."""
    if pykdtree_available():
        from pykdtree.kdtree import KDTree

        tree = KDTree(src32.astype(np.float64))

        def query_pykdtree(rows: npt.NDArray[np.float32], fetch: int) -> npt.NDArray[np.int64]:
            _, found = tree.query(rows.astype(np.float64), k=fetch)
            return np.asarray(found, dtype=np.int64).reshape(rows.shape[0], fetch)

        return query_pykdtree, float(np.finfo(np.float64).eps)
    from scipy.spatial import cKDTree

    ctree = cKDTree(src32.astype(np.float64))

    def query_ckdtree(rows: npt.NDArray[np.float32], fetch: int) -> npt.NDArray[np.int64]:
        _, found = ctree.query(rows.astype(np.float64), k=fetch, workers=torch.get_num_threads())
        return np.asarray(found, dtype=np.int64).reshape(rows.shape[0], fetch)

    return query_ckdtree, float(np.finfo(np.float64).eps)


def _row_sq_distances(
    src: npt.NDArray[np.float64], dst: npt.NDArray[np.float64], candidates: npt.NDArray[np.int64]
) -> npt.NDArray[np.float64]:
    """`ordered_sq_distances` of each target row to its candidates (the same operations, numpy)."""
    total: npt.NDArray[np.float64] | None = None
    for axis in range(src.shape[1]):
        diff = np.subtract(dst[:, axis, None], np.ascontiguousarray(src[:, axis])[candidates])
        np.multiply(diff, diff, out=diff)
        total = diff if total is None else np.add(total, diff, out=total)
    assert total is not None
    return total


def _by_distance_then_index(
    candidates: npt.NDArray[np.int64], d2: npt.NDArray[np.float64]
) -> tuple[npt.NDArray[np.int64], npt.NDArray[np.float64]]:
    """Each row's candidates sorted by (squared distance, index), with their distances. A tree lists
    them nearly in order, so a stable sort by distance is cheap; only rows with equal distances are
    sorted again with the index as the second key."""
    order = np.argsort(d2, axis=1, kind="stable")
    candidates = np.take_along_axis(candidates, order, axis=1)
    d2 = np.take_along_axis(d2, order, axis=1)
    # Equal distances share a rank (its place among the row's distinct distances); one sort of
    # rank * 2^32 + index then orders the row by (distance, index).
    rank = np.zeros(d2.shape, dtype=np.int64)
    np.cumsum(d2[:, 1:] != d2[:, :-1], axis=1, out=rank[:, 1:])
    again = np.argsort((rank << 32) | candidates, axis=1)
    return np.take_along_axis(candidates, again, axis=1), d2


# --------------------------------------------------------------------------------------------------
# Quantized sampling


def _rotation(generator: torch.Generator) -> Tensor:
    """A random rotation: uniform angles in [-pi, pi] about x, then y, then z (float64, CPU)."""
    ax, ay, az = ((torch.rand(3, generator=generator, dtype=torch.float64) * 2.0 - 1.0) * math.pi).tolist()
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]], dtype=torch.float64)
    ry = torch.tensor([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]], dtype=torch.float64)
    rz = torch.tensor([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return rz @ ry @ rx


def _voxel_representatives(points: Tensor, voxel: float, generator: torch.Generator) -> Tensor:
    """Positions (into ``points`` (3, R)) of one point per occupied voxel of a randomly rotated grid.

    The rotation only decides the partition; the representative of a voxel is its highest position,
    a fixed rule so the result depends on the generator alone (scatter order never matters).
    """
    count = points.shape[1]
    rotated = _rotation(generator).to(points.device) @ points
    rotated = rotated - rotated.min(dim=1, keepdim=True).values
    extent = float(rotated.max())
    if not voxel > 0.0 or extent / voxel > 2.0**40:
        # Degenerate (all points equal) or cells finer than any spacing: every point stands alone.
        return torch.arange(count, device=points.device)
    cells = torch.floor(rotated / voxel).to(torch.int64)  # (3, R), non-negative
    dims = cells.max(dim=1).values + 1
    if float(dims[0]) * float(dims[1]) * float(dims[2]) < 2.0**62:
        key = (cells[0] * dims[1] + cells[1]) * dims[2] + cells[2]
        _, inverse = torch.unique(key, return_inverse=True)
    else:
        _, inverse = torch.unique(cells, dim=1, return_inverse=True)
    n_cells = int(inverse.max()) + 1
    order = torch.arange(count, device=points.device)
    reps = torch.full((n_cells,), -1, dtype=torch.int64, device=points.device)
    return reps.scatter_reduce(0, inverse, order, reduce="amax", include_self=True)


def quantized_sampling(points: Tensor, n: int, generator: GeneratorLike = None) -> Tensor:
    """Indices of ``n`` distinct points of ``points`` (3, N), spread roughly uniformly in space.

    POCO's rule: voxelise with cell size bbox-diagonal / sqrt(n) in a random rotation, keep one point
    per occupied cell; if that is still fewer than n, remove them from the candidates, halve the cell
    and repeat; the pass that would overshoot contributes a uniformly random subset that fills n
    exactly. The result is sorted (consumers do not care about order; sorting makes it canonical).
    """
    if points.ndim != 2 or points.shape[0] != 3:
        raise ValueError(f"quantized_sampling expects (3, N) points, got {tuple(points.shape)}")
    total = points.shape[1]
    if not 0 < n <= total:
        raise ValueError(f"cannot sample {n} of {total} points")
    device = points.device
    if n == total:
        return torch.arange(total, device=device)
    gen = torch_generator(generator)
    with torch.no_grad():
        pos = points.detach().to(torch.float64)
        diagonal = float((pos.max(dim=1).values - pos.min(dim=1).values).norm())
        voxel = diagonal / math.sqrt(n)
        remaining = torch.arange(total, device=device)
        chosen: list[Tensor] = []
        count = 0
        while True:
            need = n - count
            if remaining.numel() <= need:
                # Every later pass would keep all of them anyway: take them now.
                chosen.append(remaining)
                break
            reps = _voxel_representatives(pos[:, remaining], voxel, gen)
            if reps.numel() < need:
                chosen.append(remaining[reps])
                count += reps.numel()
                keep = torch.ones(remaining.numel(), dtype=torch.bool, device=device)
                keep[reps] = False
                remaining = remaining[keep]
                voxel /= 2.0
            else:
                pick = torch.randperm(reps.numel(), generator=gen)[:need].to(device)
                chosen.append(remaining[reps[pick]])
                break
        return torch.sort(torch.cat(chosen)).values


def level_sizes(n_points: int, levels: int = LEVELS, ratio: float = 0.25) -> list[int]:
    """Point counts per level: level l+1 keeps max(1, int(N_l * ratio)) points of level l."""
    sizes = [n_points]
    for _ in range(levels):
        sizes.append(max(1, int(sizes[-1] * ratio)))
    return sizes


# --------------------------------------------------------------------------------------------------
# The table set


def gather_points(points: Tensor, index: Tensor) -> Tensor:
    """points (B, C, N) indexed by (B, M) -> (B, C, M)."""
    return torch.gather(points, 2, index[:, None, :].expand(-1, points.shape[1], -1))


def level_points(points: Tensor, tables: dict[str, Tensor]) -> list[Tensor]:
    """Positions (B, 3, N_l) of every level, from the input and the ``sampleL`` tables."""
    out = [points]
    for level in range(1, LEVELS + 1):
        out.append(gather_points(out[-1], tables[f"sample{level}"]))
    return out


def spatial_tables(
    points: Tensor,
    generator: GeneratorLike = None,
    *,
    queries: Tensor | None = None,
    encoder_k: int = 16,
    decoder_k: int = 64,
    ratio: float = 0.25,
    backend: KnnBackend = "auto",
    knn_device: torch.device | str | None = None,
) -> dict[str, Tensor]:
    """Every index table the network needs for ``points`` (B, 3, N), as a dict of int64 tensors.

    ``sampleL`` (B, N_L): indices of level L's points among level L-1's (quantized sampling, per
    sample, with the generator consumed in batch order). ``idsAB`` (B, N_B, K): for each level-B
    point its ``encoder_k`` nearest level-A points (A = B or B-1), or for the upsampling tables
    (A = B+1) its single nearest. ``proj_indices`` (B, M, decoder_k), only when ``queries`` (B, 3, M)
    is given: each query's nearest input points. The sampling runs where ``points`` are (the CPU, so
    that its float64 voxel cells are the same everywhere); ``knn_device`` (default: there too) runs the
    neighbour searches, and the tables come back on ``points``' device.
    """
    if points.ndim != 3 or points.shape[1] != 3:
        raise ValueError(f"spatial_tables expects (B, 3, N) points, got {tuple(points.shape)}")
    gen = torch_generator(generator)
    tables: dict[str, Tensor] = {}
    with torch.no_grad():
        sizes = level_sizes(points.shape[2], LEVELS, ratio)
        current = points.detach()
        for level in range(1, LEVELS + 1):
            picks = [quantized_sampling(current[b], sizes[level], gen) for b in range(points.shape[0])]
            index = torch.stack(picks).to(points.device)
            tables[f"sample{level}"] = index
            current = gather_points(current, index)
        home = points.device
        searched = torch.device(knn_device) if knn_device is not None else home
        levels = [level.to(searched) for level in level_points(points.detach(), tables)]
        for a, b in CONV_TABLES:
            tables[f"ids{a}{b}"] = knn(levels[a], levels[b], encoder_k, backend=backend).to(home)
        for a, b in UP_TABLES:
            tables[f"ids{a}{b}"] = knn(levels[a], levels[b], 1, backend=backend).to(home)
        if queries is not None:
            found = knn(levels[0], queries.detach().to(searched), decoder_k, backend=backend)
            tables["proj_indices"] = found.to(home)
    return tables
