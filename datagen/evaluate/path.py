"""Movement cost of a one-shot view set: local paths around the object and the shortest open tour.

The authors (docs/authors-code.md sections 8.2 and 8.3) charge the camera for moving between two
views along a "local path" that skirts an obstacle sphere around the object, and visit a one-shot set in the
order of the shortest open path (Held-Karp) from the initial view. We reproduce both with two deliberate
differences, each documented where it applies:

- the arc on the sphere is the shorter one (the authors' code can take the longer way round);
- an endpoint inside the sphere is a user error (the authors return a cost of 1e10 and carry on).

Pure numpy; no RNG is used.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator, Sequence

import numpy as np
import numpy.typing as npt

from datagen.errors import InvalidArgument

__all__ = [
    "MAX_HELD_KARP_NODES",
    "held_karp",
    "local_path_length",
    "open_path_heuristic",
    "order_views",
    "path_matrix",
    "visit_order",
]

MAX_HELD_KARP_NODES = 20
"""The DP table holds 2^(n-1)·n float64: 80 MB at n = 20, and the next node doubles it."""


def _centre_radius(centre: npt.ArrayLike, radius: float) -> tuple[npt.NDArray[np.float64], float]:
    c = np.asarray(centre, dtype=np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise InvalidArgument(f"centre must be 3 finite coordinates, got shape {c.shape}")
    r = float(radius)
    if not (np.isfinite(r) and r > 0.0):
        raise InvalidArgument(f"radius must be a positive finite number of metres, got {radius!r}")
    return c, r


def _points(points: npt.ArrayLike, name: str) -> npt.NDArray[np.float64]:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise InvalidArgument(f"{name} must be an (n, 3) array of finite coordinates, got shape {p.shape}")
    return p


def _check_outside(points: npt.NDArray[np.float64], c: npt.NDArray[np.float64], r: float, name: str) -> None:
    """The local path is undefined from inside the obstacle; the authors' 1e10 would silently poison a mean."""
    dist = np.linalg.norm(points - c, axis=1)
    inside = np.flatnonzero(dist < r)
    if inside.size:
        i = int(inside[0])
        raise InvalidArgument(
            f"{name}[{i}] lies inside the obstacle sphere (distance {dist[i]:.6g} m < radius {r:.6g} m): "
            "camera positions must be on or outside it"
        )


def _lengths(
    starts: npt.NDArray[np.float64], ends: npt.NDArray[np.float64], c: npt.NDArray[np.float64], r: float
) -> npt.NDArray[np.float64]:
    """Local path lengths for broadcastable (..., 3) start and end arrays whose points are all outside the sphere.

    Closed form, no plane needed: the segment enters the open ball only if its point closest to the centre lies
    strictly between the endpoints at a distance p < r. Entry P and exit Q sit h = sqrt(r² − p²) either side of
    that foot, so the two straight pieces add up to L − 2h, and the chord PQ (length 2h) subtends the angle
    2·atan2(h, p) ∈ (0, π] at the centre: the shorter great-circle arc in the plane (start, centre, end), which
    always contains P and Q. When start, centre and end are collinear (p = 0) that plane is undefined, but P and
    Q are antipodal and every great circle through them has the same half-circle arc, π·r, which the formula
    gives without special-casing. atan2 rather than asin(h/r) keeps full precision near p = 0.
    """
    d = ends - starts
    length2 = np.sum(d * d, axis=-1)
    length = np.sqrt(length2)
    safe2 = np.where(length2 > 0.0, length2, 1.0)
    t = np.sum((c - starts) * d, axis=-1) / safe2
    foot = starts + t[..., None] * d
    p = np.linalg.norm(foot - c, axis=-1)
    crosses = (length2 > 0.0) & (t > 0.0) & (t < 1.0) & (p < r)
    h = np.sqrt(np.where(crosses, (r - p) * (r + p), 0.0))
    detour = length - 2.0 * h + 2.0 * r * np.arctan2(h, p)
    return np.where(crosses, detour, length)


def local_path_length(start: npt.ArrayLike, end: npt.ArrayLike, centre: npt.ArrayLike, radius: float) -> float:
    """Length in metres of the camera's local path from `start` to `end` around the obstacle sphere.

    The straight segment when it does not pass through the sphere's interior (touching it is allowed);
    otherwise segment to the entry point, the shorter great-circle arc to the exit point, segment to `end`.
    The authors' code does not take the shorter arc (its arc can exceed π·r); we do, so our costs are never
    larger than theirs for the same geometry. Like theirs, it is not a true shortest path (no tangent lines).
    An endpoint strictly inside the sphere raises InvalidArgument.
    """
    c, r = _centre_radius(centre, radius)
    pts = _points(np.stack([np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)]), "start/end")
    _check_outside(pts, c, r, "start/end")
    return float(_lengths(pts[0], pts[1], c, r))


def path_matrix(positions: npt.ArrayLike, centre: npt.ArrayLike, radius: float) -> npt.NDArray[np.float64]:
    """All pairwise local path lengths: entry [i, j] is the path from positions[i] to positions[j], zero diagonal.

    Symmetric up to rounding (the local path is reversible); kept as a full matrix because Held-Karp takes an
    asymmetric one, as the authors' does.
    """
    c, r = _centre_radius(centre, radius)
    pts = _points(positions, "positions")
    _check_outside(pts, c, r, "positions")
    out = _lengths(pts[:, None, :], pts[None, :, :], c, r)
    np.fill_diagonal(out, 0.0)
    return np.ascontiguousarray(out, dtype=np.float64)


def _popcounts(m: int) -> npt.NDArray[np.int64]:
    masks = np.arange(1 << m, dtype=np.int64)
    counts = np.zeros(1 << m, dtype=np.int64)
    for b in range(m):
        counts += (masks >> b) & 1
    return counts


def held_karp(weights: npt.ArrayLike, start: int = 0) -> tuple[list[int], float]:
    """The shortest open path from node `start` through every node exactly once (no return), and its length.

    Exact bitmask DP, O(2^n·n²) time and O(2^(n-1)·n) memory, for an asymmetric `weights[i, j]` (cost of i → j).
    The DP runs backwards (g[visited, j] = cheapest way to finish from j), so the order can be rebuilt forwards.

    Tie-break: among optimal orders, the lexicographically smallest sequence of node indices, i.e. at every
    step the smallest next node that still completes an optimal path. "Optimal" means equal in the DP's own
    floating-point sums, so orders that tie only in exact arithmetic may be told apart by rounding; with
    exactly representable weights (integers, an all-equal matrix) the rule is exact: an all-equal matrix gives
    `start` followed by the other nodes ascending. The authors' DP breaks ties by its loop order instead
    (section 8.3); only the cost, not the order, is comparable with theirs when ties occur.

    The returned length is the forward sum of the weights along the order.
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[0] != w.shape[1] or w.shape[0] == 0:
        raise InvalidArgument(f"weights must be a non-empty square (n, n) matrix, got shape {w.shape}")
    n = w.shape[0]
    if n > MAX_HELD_KARP_NODES:
        raise InvalidArgument(
            f"held_karp takes at most {MAX_HELD_KARP_NODES} nodes (its table doubles per node), got {n}"
        )
    if not np.all(np.isfinite(w)):
        raise InvalidArgument("weights must all be finite")
    if not (0 <= start < n):
        raise InvalidArgument(f"start must be a node index in [0, {n}), got {start}")
    others = [i for i in range(n) if i != start]
    m = len(others)
    if m == 0:
        return [start], 0.0

    wo = w[np.ix_(others, others)]  # weights among the other nodes, relabelled 0..m-1 in ascending id order
    bits = np.int64(1) << np.arange(m, dtype=np.int64)
    full = (1 << m) - 1
    g = np.full((1 << m, m), np.inf)
    g[full, :] = 0.0
    counts = _popcounts(m)
    for size in range(m - 1, 0, -1):
        layer = np.flatnonzero(counts == size)
        for j in range(m):
            masks = layer[(layer & bits[j]) != 0]
            nxt = masks[:, None] | bits[None, :]
            vals = wo[j][None, :] + g[nxt, np.arange(m)[None, :]]
            vals[(masks[:, None] & bits[None, :]) != 0] = np.inf
            g[masks, j] = vals.min(axis=1)

    first = w[start, others] + g[bits, np.arange(m)]
    k = int(np.flatnonzero(first == first.min())[0])
    order_rel = [k]
    mask = 1 << k
    while mask != full:
        j = order_rel[-1]
        vals = wo[j] + g[mask | bits, np.arange(m)]
        vals[(mask & bits) != 0] = np.inf
        k = int(np.flatnonzero(vals == g[mask, j])[0])
        order_rel.append(k)
        mask |= 1 << k
    order = [start] + [others[i] for i in order_rel]
    cost = float(sum(float(w[a, b]) for a, b in itertools.pairwise(order)))
    return order, cost


def order_views(
    initial_view: int,
    planned_views: Sequence[int],
    positions: npt.ArrayLike,
    centre: npt.ArrayLike,
    radius: float,
) -> tuple[list[int], float]:
    """Visiting order of a one-shot set and its movement cost in metres, as the authors' method 11 runs it.

    The initial view comes first (the camera is already there), then the planned views along the shortest open
    path. The initial view is dropped from the planned set if the planner returned it, and duplicates are
    dropped. The planned views are sorted by id before the DP so that ties resolve by view id, whatever order
    the planner listed them in. `positions[v]` is the camera position of view id v.
    """
    pts = _points(positions, "positions")
    n_views = pts.shape[0]
    ids = [int(initial_view), *(int(v) for v in planned_views)]
    bad = [v for v in ids if not (0 <= v < n_views)]
    if bad:
        raise InvalidArgument(f"view id {bad[0]} is out of range: there are {n_views} view positions")
    nodes = [ids[0], *sorted(set(ids[1:]) - {ids[0]})]
    weights = path_matrix(pts[nodes], centre, radius)
    order, cost = held_karp(weights, start=0)
    return [nodes[i] for i in order], cost


def open_path_heuristic(weights: npt.ArrayLike, start: int = 0) -> tuple[list[int], float]:
    """A short open path from `start` through every node when Held-Karp's table is too large.

    Nearest neighbour (ties to the lower index), then 2-opt reversals of any stretch after the start and
    relocations of single nodes, until no such move shortens the path. Deterministic; not proven optimal,
    so callers report it as approximate.
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.ndim != 2 or w.shape[0] != w.shape[1] or w.shape[0] == 0 or not np.all(np.isfinite(w)):
        raise InvalidArgument(f"weights must be a non-empty square matrix of finite numbers, got shape {w.shape}")
    n = w.shape[0]
    if not (0 <= start < n):
        raise InvalidArgument(f"start must be a node index in [0, {n}), got {start}")
    order = [start]
    left = set(range(n)) - {start}
    while left:
        here = order[-1]
        nearest = min(left, key=lambda j: (w[here, j], j))
        order.append(nearest)
        left.remove(nearest)

    def length(path: list[int]) -> float:
        return float(sum(float(w[a, b]) for a, b in itertools.pairwise(path)))

    best = length(order)
    improved = True
    while improved:
        improved = False
        for candidate in _neighbours(order):
            cost = length(candidate)
            if cost < best - 1e-12:
                order, best, improved = candidate, cost, True
                break
    return order, best


def _neighbours(order: list[int]) -> Iterator[list[int]]:
    """Paths one move away, the start kept first: 2-opt reversals, then single-node relocations."""
    n = len(order)
    for i in range(1, n - 1):
        for j in range(i + 1, n):
            yield order[:i] + order[i : j + 1][::-1] + order[j + 1 :]
    for i in range(1, n):
        rest = order[:i] + order[i + 1 :]
        for k in range(1, n):
            if k != i:
                yield [*rest[:k], order[i], *rest[k:]]


def visit_order(
    initial_view: int,
    planned_views: Sequence[int],
    positions: npt.ArrayLike,
    centre: npt.ArrayLike,
    radius: float,
) -> tuple[list[int], float, bool]:
    """`order_views` when Held-Karp can take the set (exact: True), else `open_path_heuristic` (False)."""
    nodes = [int(initial_view), *sorted({int(v) for v in planned_views} - {int(initial_view)})]
    if len(nodes) <= MAX_HELD_KARP_NODES:
        order, cost = order_views(initial_view, planned_views, positions, centre, radius)
        return order, cost, True
    pts = _points(positions, "positions")
    order_idx, cost = open_path_heuristic(path_matrix(pts[nodes], centre, radius), start=0)
    return [nodes[i] for i in order_idx], cost, False
