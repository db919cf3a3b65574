"""Pictures of `datagen evaluate` runs: coverage against a movement budget (the paper's Fig. 6; a planner
with a matched random shows its lift in the legend) and, for one scene, each planner's route around the
object and what it observed.

Built on matplotlib's Agg canvas directly (never pyplot), like `datagen.inspection.plots`: headless,
no global state between calls, safe in threads. No RNG: clouds are thinned by a fixed stride.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import numpy.typing as npt
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d import Axes3D

from datagen.errors import InvalidArgument
from datagen.evaluate.episode import Episode
from datagen.evaluate.report import summarise
from datagen.evaluate.scene import Scene

DPI = 100
BUDGET_POINTS = 101
"""Budgets sampled from 0 m to the longest run's movement."""
MAX_CLOUD_POINTS = 3000
"""Observed clouds larger than this are thinned by a fixed stride before drawing."""
ARC_POINTS = 33
"""Samples of each great-circle arc: the polyline is shorter than the arc by under 0.1 %."""
BUDGET_TOLERANCE = 1e-12
"""Metres; matches the episode's own budget cut, so a run's total movement reaches its last view."""
CAMERA_ELEVATION, CAMERA_AZIMUTH = 25.0, -60.0
CANDIDATE_COLOUR = "#a0a0a0"
OBSERVED_COLOUR = "#8e44ad"
PATH_COLOUR = "#e8341c"
INITIAL_COLOUR = "#000000"
VISIT_CMAP = "viridis"
"""Visited views are coloured by their place in the visiting order."""
CURVE_CMAP = "tab10"


def row_label(episode: Episode) -> str:
    """The table's row name: the planner, with its refiner when one was used."""
    return episode.planner if episode.refiner == "-" else f"{episode.planner} ({episode.refiner})"


def legend_label(episodes: Sequence[Episode]) -> str:
    """A curve's legend entry: its row label, with the mean lift over its matched random when it has one (the
    table's figure: per-object means, then their mean), so the gain over chance at equal views is read
    without the table."""
    label = row_label(episodes[0])
    lift = summarise(episodes)[0].mean["lift"]
    return label if math.isnan(lift) else f"{label} ({lift:+.1f} vs random at equal views)"


def coverage_at_budgets(episode: Episode, budgets: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """Coverage (fraction) the run had reached within each movement budget (metres): the value after the last
    visited view whose cumulative movement is <= the budget. The initial view costs nothing, so a budget of
    0 m (or less) gives the first value of the curve."""
    curve = np.asarray(episode.coverage_curve, dtype=np.float64)
    if curve.size != len(episode.step_metres) + 1:
        raise InvalidArgument(
            f"episode has {curve.size} coverage values for {len(episode.step_metres)} moves; "
            "expected one value per visited view"
        )
    spent = np.concatenate([[0.0], np.cumsum(np.asarray(episode.step_metres, dtype=np.float64))])
    b = np.asarray(budgets, dtype=np.float64)
    reached = np.searchsorted(spent, b + BUDGET_TOLERANCE, side="right") - 1
    return np.asarray(curve[np.clip(reached, 0, None)], dtype=np.float64)


def draw_budget_curves(episodes: Sequence[Episode], path: Path) -> None:
    """PNG of mean surface coverage (%) against movement budget (m), one line per planner row: how far each
    planner must move to see what it sees (the paper's Fig. 6)."""
    if not episodes:
        raise InvalidArgument("no episodes to draw budget curves for")
    longest = max(e.movement for e in episodes)
    budgets = np.linspace(0.0, longest if longest > 0 else 1.0, BUDGET_POINTS)
    rows: dict[str, list[Episode]] = {}
    for episode in episodes:
        rows.setdefault(row_label(episode), []).append(episode)
    figure = Figure(figsize=(8.0, 5.0), dpi=DPI)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot(1, 1, 1)
    cmap = colormaps[CURVE_CMAP]
    for index, (_, runs) in enumerate(sorted(rows.items())):
        mean = np.mean([coverage_at_budgets(e, budgets) for e in runs], axis=0)
        colour = cmap(index % cmap.N)
        axes.plot(budgets, 100.0 * mean, color=colour, linewidth=1.6, drawstyle="steps-post", label=legend_label(runs))
    axes.set_xlabel("movement budget (m)")
    axes.set_ylabel("surface coverage (%)")
    axes.set_xlim(budgets[0], budgets[-1])
    axes.set_ylim(0.0, 100.0)
    axes.grid(True, linewidth=0.4, alpha=0.6)
    axes.set_title(f"coverage within a movement budget ({len(episodes)} runs)", fontsize=11)
    axes.legend(fontsize=8, loc="lower right")
    figure.tight_layout()
    _save(figure, path)


def draw_object(scene: Scene, episodes: Sequence[Episode], path: Path) -> None:
    """PNG of one scene, one 3D panel per run: candidate views, the visited ones in order, the camera's
    local path around the obstacle sphere and the cloud it observed, to see why planners differ. With no
    runs (every planner failed) one panel shows the candidate views, so the picture still appears."""
    runs: list[Episode | None] = list(episodes) or [None]
    columns = min(len(runs), 3)
    rows = math.ceil(len(runs) / columns)
    height = 4.5 * rows + 0.8
    figure = Figure(figsize=(4.5 * columns, height), dpi=DPI)
    FigureCanvasAgg(figure)
    initial = ", ".join(str(v) for v in sorted({e.initial_view for e in episodes}))
    figure.suptitle(f"{scene.object_name}, rotation {scene.rotation}, initial view {initial or '-'}", fontsize=11)
    positions = np.asarray(scene.positions, dtype=np.float64)
    reach = 1.08 * (float(np.linalg.norm(positions, axis=1).max()) if len(positions) else 1.0)
    for index, episode in enumerate(runs, start=1):
        axes = figure.add_subplot(rows, columns, index, projection="3d")
        assert isinstance(axes, Axes3D)
        _draw_run(axes, scene, positions, episode)
        axes.set_xlim(-reach, reach)
        axes.set_ylim(-reach, reach)
        axes.set_zlim(-reach, reach)
        axes.set_box_aspect((1, 1, 1))
    figure.subplots_adjust(left=0.0, right=1.0, bottom=0.02, top=1.0 - 1.1 / height, wspace=0.0)
    _save(figure, path)


def _draw_run(axes: Axes3D, scene: Scene, positions: npt.NDArray[np.float64], episode: Episode | None) -> None:
    axes.computed_zorder = False  # draw in zorder: candidates, cloud, path, visited views
    axes.view_init(elev=CAMERA_ELEVATION, azim=CAMERA_AZIMUTH)
    axes.tick_params(labelsize=6, pad=0)
    if len(positions):
        axes.scatter(*positions.T, s=4, color=CANDIDATE_COLOUR, depthshade=False, linewidths=0, zorder=1)
    if episode is None:
        axes.set_title("no runs", fontsize=9)
        return
    axes.set_title(
        f"{row_label(episode)}\n{100.0 * episode.coverage:.1f} % coverage, {episode.views} views, "
        f"{episode.movement:.2f} m",
        fontsize=9,
    )
    cloud = scene.observed_points(episode.visited)
    if len(cloud):
        thinned = cloud[:: max(1, math.ceil(len(cloud) / MAX_CLOUD_POINTS))]
        axes.scatter(*thinned.T, s=1.0, color=OBSERVED_COLOUR, depthshade=False, linewidths=0, zorder=2)
    visited = positions[list(episode.visited)]
    if len(visited) > 1:
        route = np.concatenate(
            [_local_path_points(a, b, scene.obstacle_radius) for a, b in itertools.pairwise(visited)]
        )
        axes.plot(*route.T, color=PATH_COLOUR, linewidth=1.0, zorder=3)
        order = np.linspace(0.0, 1.0, len(visited) - 1)
        axes.scatter(
            *visited[1:].T, s=30, c=order, cmap=VISIT_CMAP, vmin=0.0, vmax=1.0, depthshade=False, linewidths=0, zorder=4
        )
    if len(visited):
        axes.scatter(*visited[:1].T, s=70, marker="*", color=INITIAL_COLOUR, depthshade=False, linewidths=0, zorder=5)


def _local_path_points(
    start: npt.NDArray[np.float64], end: npt.NDArray[np.float64], radius: float, arc_points: int = ARC_POINTS
) -> npt.NDArray[np.float64]:
    """A polyline along `datagen.evaluate.path.local_path_length`'s path around the sphere at the origin:
    the straight segment, or segment to the entry point, the shorter great-circle arc, segment to `end`."""
    a, b = np.asarray(start, dtype=np.float64), np.asarray(end, dtype=np.float64)
    d = b - a
    length2 = float(d @ d)
    t = float(-a @ d) / length2 if length2 > 0.0 else 0.0
    foot = a + t * d
    p = float(np.linalg.norm(foot))
    if not (length2 > 0.0 and 0.0 < t < 1.0 and p < radius):
        return np.stack([a, b])
    h = math.sqrt((radius - p) * (radius + p))
    unit = d / math.sqrt(length2)
    entry, exit_ = foot - h * unit, foot + h * unit
    u = entry / radius
    v = exit_ / radius - float(u @ exit_ / radius) * u
    if np.linalg.norm(v) < 1e-9:  # antipodal entry and exit: every great circle through them is as long
        v = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
    v = v / np.linalg.norm(v)
    angles = np.linspace(0.0, 2.0 * math.atan2(h, p), arc_points)
    arc = radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
    return np.concatenate([a[None], arc, b[None]])


def _save(figure: Figure, path: Path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        figure.savefig(path, format="png", dpi=DPI, facecolor="white")
    finally:
        figure.clear()
