"""Candidate view positions on the upper hemisphere (docs/pipeline.md section 2).

Three sources: the authors' 32 Tammes-problem positions (embedded), a view-space file, or a seeded
spread for any n that maximises the minimum angular separation. Positions are always rescaled to the
configured radius; the views look at the origin, which is the object's bounding-box centre.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import numpy.typing as npt

from datagen.errors import ViewSpaceError
from schemas.config import BUILTIN_VIEW_SPACE, GENERATED_VIEW_SPACE, MAX_VIEWS, ViewSpaceConfig


@dataclass(frozen=True)
class ViewSpace:
    """n camera positions (n, 3) in metres, in the task frame."""

    positions: npt.NDArray[np.float64]

    @property
    def count(self) -> int:
        return int(self.positions.shape[0])

    def min_separation_degrees(self) -> float:
        return min_separation_degrees(self.positions)


def build_view_space(config: ViewSpaceConfig) -> ViewSpace:
    """The view space a config describes."""
    if config.source == BUILTIN_VIEW_SPACE:
        unit = _normalise(builtin_positions())
    elif config.source == GENERATED_VIEW_SPACE:
        unit = generate_directions(config.count, config.generator_seed)
    else:
        unit = _normalise(read_view_space_file(Path(config.source)))
        if unit.shape[0] != config.count:
            raise ViewSpaceError(
                f"{config.source}: holds {unit.shape[0]} views but view_space.count = {config.count}; "
                "set view_space.count to the file's count"
            )
    return ViewSpace(positions=unit * config.radius)


def builtin_positions() -> npt.NDArray[np.float64]:
    """The authors' 32 positions (radius 0.4 m), as shipped in ``datagen/data``."""
    text = resources.files("datagen").joinpath("data", "view_space_32.txt").read_text()
    return _parse_view_space(text, "built-in view space")


def read_view_space_file(path: Path) -> npt.NDArray[np.float64]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ViewSpaceError(f"{path}: cannot read view-space file ({exc.strerror}); check the path") from None
    return _parse_view_space(text, str(path))


def _parse_view_space(text: str, origin: str) -> npt.NDArray[np.float64]:
    lines = [line.split() for line in text.splitlines() if line.strip()]
    if not lines or len(lines[0]) != 1 or not lines[0][0].isdigit():
        raise ViewSpaceError(f"{origin}: first line must be the view count (an integer)")
    count = int(lines[0][0])
    if not (1 <= count <= MAX_VIEWS):
        raise ViewSpaceError(f"{origin}: view count {count} is outside the allowed range 1..{MAX_VIEWS}")
    rows = lines[1:]
    if len(rows) != count:
        raise ViewSpaceError(f"{origin}: the first line says {count} views but {len(rows)} follow")
    try:
        positions = np.array([[float(v) for v in row] for row in rows], dtype=np.float64)
    except ValueError:
        raise ViewSpaceError(f"{origin}: every view line must be three numbers 'x y z'") from None
    if positions.shape != (count, 3) or not np.isfinite(positions).all():
        raise ViewSpaceError(f"{origin}: every view line must be three finite numbers 'x y z'")
    if (np.linalg.norm(positions, axis=1) == 0).any():
        raise ViewSpaceError(f"{origin}: a view at the origin has no direction")
    if (positions[:, 2] < 0).any():
        raise ViewSpaceError(f"{origin}: views must lie on the upper hemisphere (z >= 0)")
    return positions


def generate_directions(count: int, seed: int, iterations: int = 3000) -> npt.NDArray[np.float64]:
    """A seeded spread of unit directions on the upper hemisphere with a large minimum separation.

    Repulsion whose exponent grows over the run (so the end game is the max-min problem itself),
    with the step shrinking to zero; the best iterate by minimum separation is returned.
    Deterministic for a given (count, seed) on a given numpy.
    """
    if not (1 <= count <= MAX_VIEWS):
        raise ViewSpaceError(f"view count {count} is outside the allowed range 1..{MAX_VIEWS}")
    rng = np.random.default_rng(np.random.SeedSequence([seed, count]))
    points = rng.normal(size=(count, 3))
    points[:, 2] = np.abs(points[:, 2])
    points = _normalise(points)
    if count == 1:
        return np.array([[0.0, 0.0, 1.0]])
    best, best_separation = points, -1.0
    for step_index in range(iterations):
        progress = step_index / iterations
        exponent = 2.0 + 60.0 * progress
        diff = points[:, None, :] - points[None, :, :]
        dist = np.linalg.norm(diff, axis=2)
        np.fill_diagonal(dist, np.inf)
        closest = dist.min()
        weights = (closest / dist) ** (exponent + 2.0)
        force = (diff * weights[:, :, None]).sum(axis=1)
        force -= (force * points).sum(axis=1)[:, None] * points
        largest = max(float(np.linalg.norm(force, axis=1).max()), 1e-12)
        step = 0.05 * closest * (1.0 - progress) + 1e-4
        points = points + step * force / largest
        points[:, 2] = np.maximum(points[:, 2], 0.0)
        points = _normalise(points)
        separation = min_separation_degrees(points)
        if separation > best_separation:
            best, best_separation = points.copy(), separation
    return best


def min_separation_degrees(positions: npt.ArrayLike) -> float:
    """Smallest angle between two views, seen from the origin."""
    unit = _normalise(np.asarray(positions, dtype=np.float64))
    if unit.shape[0] < 2:
        return 180.0
    gram = np.clip(unit @ unit.T, -1.0, 1.0)
    np.fill_diagonal(gram, -1.0)
    return float(np.degrees(np.arccos(gram.max())))


def _normalise(points: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return points / np.linalg.norm(points, axis=1, keepdims=True)
