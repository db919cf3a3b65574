"""Which augmentations keep a sample's labels true? (issue 49): the view space's own symmetries.

    python -m studies.planners.real_objects.view_symmetry [--config FILE] \\
        [--out studies/planners/real_objects/results/view-symmetry.md --replace]

A stored sample is an occupancy grid (or cloud), a view state and one label per candidate view. Turning
the grid by a rotation R keeps the labels true only if R also carries every candidate view onto a
candidate view: then the sample of the turned object is the stored one with its grid turned and its
views renamed, and no ray needs casting again. A turn is exact on the voxel grid only when it permutes
the grid's axes (with signs); any other turn resamples voxels and moves surface between them. This
measures, for the config's view space, how far each candidate turn leaves the views from the nearest
candidate view: the 48 signed axis permutations (exact on the grid), every turn about the vertical axis
in half-degree steps, and every vertical mirror. A symmetry would leave every view on a view (0 degrees);
anything near the views' own spacing renames views that see other things.
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from benchmarks.common import add_report_options, check_report
from datagen.config_io import load_config
from datagen.pipeline.viewspace import build_view_space
from studies.planners.runs import write_markdown

STEP_DEGREES = 0.5
"""The turns about the vertical axis and the mirrors' planes are tried at this spacing."""
EXACT_DEGREES = 1e-6
"""A candidate that leaves no view further than this from a view is a symmetry."""
SMALLEST_TURN = 10.0
"""Turns closer to the identity than this are left out: they move each view by about the turn itself."""


@dataclass(frozen=True)
class Candidate:
    """One turn or mirror and how far it leaves the views from the nearest candidate view (degrees)."""

    name: str
    worst: float
    mean: float


def unit_rows(positions: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return positions / np.linalg.norm(positions, axis=1, keepdims=True)


def displacement(views: npt.NDArray[np.float64], moved: npt.NDArray[np.float64]) -> tuple[float, float]:
    """The worst and the mean angle (degrees) from each moved view to its nearest candidate view."""
    chords = np.linalg.norm(moved[:, None, :] - views[None, :, :], axis=2).min(axis=1)
    nearest = np.degrees(2.0 * np.arcsin(np.clip(chords / 2.0, 0.0, 1.0)))  # exact near 0, unlike arccos
    return float(nearest.max()), float(nearest.mean())


def vertical_turn(degrees: float) -> npt.NDArray[np.float64]:
    t = np.radians(degrees)
    return np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])


def vertical_mirror(degrees: float) -> npt.NDArray[np.float64]:
    """The reflection through the vertical plane whose normal points at ``degrees`` in the ground plane."""
    t = np.radians(degrees)
    normal = np.array([np.cos(t), np.sin(t), 0.0])
    return np.eye(3) - 2.0 * np.outer(normal, normal)


def axis_permutations() -> list[tuple[str, npt.NDArray[np.float64]]]:
    """The 47 signed axis permutations other than the identity: the turns and mirrors exact on a voxel grid."""
    found = []
    for order in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            matrix = np.zeros((3, 3))
            for row, (column, sign) in enumerate(zip(order, signs, strict=True)):
                matrix[row, column] = sign
            if not np.array_equal(matrix, np.eye(3)):
                axes = (("-" if s < 0 else "") + "xyz"[c] for c, s in zip(order, signs, strict=True))
                found.append(("(" + ", ".join(axes) + ")", matrix))
    return found


def best_of(views: npt.NDArray[np.float64], named: Sequence[tuple[str, npt.NDArray[np.float64]]]) -> Candidate:
    """The candidate that leaves the views closest to views (by the worst view, then the mean)."""
    scored = [Candidate(name, *displacement(views, views @ matrix.T)) for name, matrix in named]
    return min(scored, key=lambda c: (c.worst, c.mean))


def symmetry_rows(positions: npt.NDArray[np.float64]) -> list[tuple[str, Candidate]]:
    """The closest candidate of each family for the view space at ``positions``."""
    views = unit_rows(np.asarray(positions, dtype=np.float64))
    turns = np.arange(SMALLEST_TURN, 360.0 - SMALLEST_TURN + STEP_DEGREES / 2, STEP_DEGREES)
    mirrors = np.arange(0.0, 180.0, STEP_DEGREES)
    families = {
        "signed axis permutations (exact on the grid), 47": axis_permutations(),
        f"turns about the vertical axis, {SMALLEST_TURN:g} to {360 - SMALLEST_TURN:g} degrees": [
            (f"{d:g} degrees", vertical_turn(float(d))) for d in turns
        ],
        "vertical mirrors": [(f"plane at {d:g} degrees", vertical_mirror(float(d))) for d in mirrors],
    }
    return [(family, best_of(views, named)) for family, named in families.items()]


def spacing(positions: npt.NDArray[np.float64]) -> float:
    """The mean angle (degrees) from a view to its nearest other view."""
    views = unit_rows(np.asarray(positions, dtype=np.float64))
    cosines = np.clip(views @ views.T, -1.0, 1.0)
    np.fill_diagonal(cosines, -1.0)
    return float(np.degrees(np.arccos(cosines.max(axis=1))).mean())


def report(positions: npt.NDArray[np.float64], source: str) -> list[str]:
    rows = symmetry_rows(positions)
    lines = [
        f"# The view space's symmetries ({source}: {len(positions)} views)",
        "",
        f"A view's nearest other view is {spacing(positions):.1f} degrees away on average.",
        "",
        "| family | closest to a symmetry | worst view off (degrees) | mean view off (degrees) |",
        "|---|---|---:|---:|",
    ]
    lines += [f"| {family} | {c.name} | {c.worst:.2f} | {c.mean:.2f} |" for family, c in rows]
    exact = [c for _, c in rows if c.worst < EXACT_DEGREES]
    lines += [
        "",
        "A symmetry leaves every view on a view (0 degrees). "
        + (
            "This view space has one, so the samples can be augmented with it and their labels stay true."
            if exact
            else "This view space has none besides the identity: no turn of a stored sample keeps its "
            "labels true, and the only label-true augmentation is imaging the object again at another "
            "rotation (the config's `rotations`), which the pipeline does."
        ),
    ]
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, help="a generation config (default: the default config)")
    add_report_options(parser)
    args = parser.parse_args(argv)
    check_report(parser, args.out, args.replace)
    config = load_config(args.config)
    positions = build_view_space(config.view_space).positions
    lines = report(np.asarray(positions), str(config.view_space.source))
    print("\n".join(lines))
    if args.out is not None:
        write_markdown(args.out, "studies.planners.real_objects.view_symmetry", argv, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
