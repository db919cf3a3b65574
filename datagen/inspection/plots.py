"""Pictures for ``shards show --png`` and ``shards stats --png``, rendered headless.

Figures are built on matplotlib's Agg canvas directly (never pyplot), so drawing needs no display,
keeps no global state between calls and is safe in threads. Figure size and dpi are fixed, so every
PNG has a known pixel size; colours are module constants, drawn unshaded and opaque, so a picture can
be checked for what it shows.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgb
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import MaxNLocator
from mpl_toolkits.mplot3d import Axes3D

from datagen.inspection.stats import DatasetStats

DPI = 100
SAMPLE_FIGSIZE = (12.0, 5.0)
"""Inches: a sample PNG is 1200 x 500 pixels."""
STATS_FIGSIZE = (12.0, 4.5)
"""Inches: a statistics PNG is 1200 x 450 pixels."""
CAMERA_ELEVATION = 25.0
CAMERA_AZIMUTH = -60.0
"""One fixed camera (degrees) for every 3D panel, so pictures of two samples compare at a glance."""

OBSERVED_COLOUR = "#8e44ad"
REFINED_COLOUR = "#2a9d3f"
INPUT_VIEW_COLOUR = "#1f5fd6"
LABEL_VIEW_COLOUR = "#e8341c"
OTHER_VIEW_COLOUR = "#a0a0a0"
SPHERE_COLOUR = "#d0d0d0"
LEGEND_FACE_COLOUR = "#fff5d6"
POINTS_HIST_COLOUR = "#3b7dd8"
SOLVER_HIST_COLOUR = "#d9822b"
LABEL_HISTOGRAM_CMAP = "Blues"
"""Colour map of the label-size-per-case-size panel; the largest count gets its top colour."""

MAX_DRAWN_POINTS = 20_000
"""Clouds larger than this are thinned by a fixed stride (deterministic, no RNG) before drawing."""
MAX_ANNOTATED_CELLS = 400


def rgb(colour: str) -> tuple[int, int, int]:
    """A colour constant as 8-bit RGB, as it appears in the PNG."""
    red, green, blue = (round(c * 255) for c in to_rgb(colour))
    return red, green, blue


def _png(figure: Figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=DPI, facecolor="white")
    return buffer.getvalue()


def _thin(points: npt.NDArray[np.floating], limit: int = MAX_DRAWN_POINTS) -> npt.NDArray[np.floating]:
    stride = max(1, -(-len(points) // limit))
    return points[::stride]


def _cube_limits(axes: Axes3D, points: npt.NDArray[np.floating], margin: float = 1.05) -> None:
    """Equal scales on all three axes around ``points`` (a distorted cloud would mislead)."""
    if len(points) == 0:
        low, high = np.full(3, -1.0), np.full(3, 1.0)
    else:
        low, high = points.min(axis=0), points.max(axis=0)
    centre = (low + high) / 2
    half = max(float((high - low).max()) / 2 * margin, 1e-3)
    axes.set_xlim(centre[0] - half, centre[0] + half)
    axes.set_ylim(centre[1] - half, centre[1] + half)
    axes.set_zlim(centre[2] - half, centre[2] + half)
    axes.set_box_aspect((1, 1, 1))


def _panel(figure: Figure, position: int, title: str) -> Axes3D:
    axes = figure.add_subplot(1, 3, position, projection="3d")
    assert isinstance(axes, Axes3D)
    axes.view_init(elev=CAMERA_ELEVATION, azim=CAMERA_AZIMUTH)
    axes.set_title(title, fontsize=10)
    axes.tick_params(labelsize=6, pad=0)
    for name in ("x", "y", "z"):
        getattr(axes, f"set_{name}label")(f"{name} (m)", fontsize=7, labelpad=-4)
        getattr(axes, f"{name}axis").set_major_locator(MaxNLocator(5))
    return axes


def _cloud(axes: Axes3D, points: npt.NDArray[np.floating], colour: str, size: float) -> None:
    if len(points):
        drawn = _thin(points)
        axes.scatter(
            drawn[:, 0], drawn[:, 1], drawn[:, 2], s=size, color=colour, depthshade=False, linewidths=0, zorder=3
        )


def _sphere(axes: Axes3D, radius: float, upper_only: bool) -> None:
    """A wire sphere (or upper hemisphere) through the view positions, to read their directions."""
    lowest = 0.0 if upper_only else -np.pi / 2
    for latitude in np.linspace(lowest, np.pi / 2, 5)[:-1]:
        angle = np.linspace(0, 2 * np.pi, 73)
        ring = radius * np.cos(latitude)
        z = np.full_like(angle, radius * np.sin(latitude))
        axes.plot(ring * np.cos(angle), ring * np.sin(angle), z, color=SPHERE_COLOUR, linewidth=0.6, zorder=1)
    for longitude in np.linspace(0, 2 * np.pi, 9)[:-1]:
        latitudes = np.linspace(lowest, np.pi / 2, 25)
        axes.plot(
            radius * np.cos(latitudes) * np.cos(longitude),
            radius * np.cos(latitudes) * np.sin(longitude),
            radius * np.sin(latitudes),
            color=SPHERE_COLOUR,
            linewidth=0.6,
            zorder=1,
        )


def _views(
    axes: Axes3D, positions: npt.NDArray[np.floating], chosen: Sequence[int], colour: str, radius: float
) -> None:
    """Views of one kind: a marker, a line towards the object and the view's bit number above it."""
    for view in chosen:
        x, y, z = (float(c) for c in positions[view])
        axes.plot([x, 0.0], [y, 0.0], [z, 0.0], color=colour, linewidth=0.8, alpha=0.5, zorder=2)
        axes.text(x, y, z + 0.09 * radius, str(view), color="black", fontsize=8, ha="center", zorder=6)
    if len(chosen):
        picked = positions[list(chosen)]
        axes.scatter(
            picked[:, 0], picked[:, 1], picked[:, 2], s=80, color=colour, depthshade=False, linewidths=0, zorder=5
        )


def _sphere_limits(axes: Axes3D, radius: float, upper_only: bool) -> None:
    """Equal scales, with the z range cut to the upper half when every view is above the object."""
    reach = radius * 1.08
    low = -0.05 * radius if upper_only else -reach
    axes.set_xlim(-reach, reach)
    axes.set_ylim(-reach, reach)
    axes.set_zlim(low, reach)
    axes.set_box_aspect((1, 1, (reach - low) / (2 * reach)))


def _marker(colour: str, label: str, size: float) -> Line2D:
    return Line2D(
        [], [], linestyle="", marker="o", markersize=size, markerfacecolor=colour, markeredgecolor=colour, label=label
    )


def draw_sample(
    points: npt.NDArray[np.floating],
    observed: npt.NDArray[np.floating],
    view_positions: npt.ArrayLike,
    input_views: Sequence[int],
    label_views: Sequence[int],
    title: str,
) -> bytes:
    """PNG of one sample: the observed cloud keys(O_S) and the refined cloud P(O_S) (same scale, same
    camera), and the view sphere with input views S and label views L marked, plus a legend."""
    positions = np.asarray(view_positions, dtype=np.float64).reshape(-1, 3)
    figure = Figure(figsize=SAMPLE_FIGSIZE, dpi=DPI)
    FigureCanvasAgg(figure)
    figure.suptitle(title, fontsize=11)
    figure.subplots_adjust(left=0.0, right=0.97, top=0.88, bottom=0.13, wspace=0.02)

    both = np.concatenate([observed.reshape(-1, 3), points.reshape(-1, 3)])
    for position, cloud, colour, name in (
        (1, observed, OBSERVED_COLOUR, "observed keys(O_S)"),
        (2, points, REFINED_COLOUR, "refined P(O_S)"),
    ):
        axes = _panel(figure, position, f"{name}: {len(cloud)} points")
        _cloud(axes, cloud, colour, size=2.0)
        _cube_limits(axes, both)

    axes = _panel(figure, 3, f"views: {len(input_views)} input, {len(label_views)} label, {len(positions)} in all")
    axes.computed_zorder = False  # draw in zorder: sphere, object, other views, chosen views, numbers
    radius = float(np.linalg.norm(positions, axis=1).max()) if len(positions) else 1.0
    upper_only = bool(len(positions)) and bool((positions[:, 2] >= -1e-9).all())
    _sphere(axes, radius, upper_only)
    _cloud(axes, points, REFINED_COLOUR, size=0.5)
    others = [v for v in range(len(positions)) if v not in set(input_views) | set(label_views)]
    if others:
        rest = positions[others]
        axes.scatter(
            rest[:, 0], rest[:, 1], rest[:, 2], s=18, color=OTHER_VIEW_COLOUR, depthshade=False, linewidths=0, zorder=4
        )
    _views(axes, positions, input_views, INPUT_VIEW_COLOUR, radius)
    _views(axes, positions, label_views, LABEL_VIEW_COLOUR, radius)
    _sphere_limits(axes, radius, upper_only)

    handles = [
        _marker(OBSERVED_COLOUR, "observed cloud keys(O_S)", 8),
        _marker(REFINED_COLOUR, "refined cloud P(O_S)", 8),
        _marker(INPUT_VIEW_COLOUR, "input views S", 11),
        _marker(LABEL_VIEW_COLOUR, "label views L", 11),
        _marker(OTHER_VIEW_COLOUR, "other views", 8),
    ]
    figure.legend(
        handles=handles,
        loc="lower center",
        ncol=len(handles),
        fontsize=10,
        facecolor=LEGEND_FACE_COLOUR,
        edgecolor="#888888",
        framealpha=1.0,
    )
    return _png(figure)


# -- statistics -----------------------------------------------------------------------------------


def _no_data(axes: Axes) -> None:
    axes.text(0.5, 0.5, "no samples", ha="center", va="center", transform=axes.transAxes)


def _label_histogram(axes: Axes, stats: DatasetStats) -> None:
    axes.set_title("label size per case size (samples)", fontsize=10)
    axes.set_xlabel("label size |L|")
    axes.set_ylabel("case size |S|")
    if not stats.label_sizes:
        _no_data(axes)
        return
    case_sizes = sorted(stats.label_sizes)
    widest = max(max(h) for h in stats.label_sizes.values())
    counts = np.zeros((len(case_sizes), widest + 1), dtype=np.int64)
    for r, case_size in enumerate(case_sizes):
        for label_size, count in stats.label_sizes[case_size].items():
            counts[r, label_size] = count
    cmap = colormaps[LABEL_HISTOGRAM_CMAP].with_extremes(bad="white")
    axes.imshow(
        np.ma.masked_equal(counts, 0),
        cmap=cmap,
        vmin=0,
        vmax=int(counts.max()),
        origin="lower",
        aspect="auto",
        interpolation="nearest",
        extent=(-0.5, widest + 0.5, -0.5, len(case_sizes) - 0.5),
    )
    axes.set_yticks(range(len(case_sizes)), [str(c) for c in case_sizes], fontsize=7)
    axes.set_xticks(range(widest + 1))
    if counts.size <= MAX_ANNOTATED_CELLS:
        for (row, column), cell in np.ndenumerate(counts):
            if cell:
                colour = "white" if cell > counts.max() / 2 else "black"
                axes.text(column, row, str(cell), ha="center", va="center", fontsize=6, color=colour)


def _histogram(axes: Axes, values: npt.NDArray[np.floating], colour: str, logarithmic: bool) -> None:
    if values.size == 0:
        _no_data(axes)
        return
    positive = values[values > 0]
    if logarithmic and positive.size == values.size and positive.max() > 10 * positive.min():
        bins: int | list[float] = np.geomspace(positive.min(), positive.max(), 31).tolist()
        axes.set_xscale("log")
    else:
        bins = 30
    axes.hist(values, bins=bins, color=colour, edgecolor="white", linewidth=0.4)
    for q in (5, 50, 95):
        axes.axvline(float(np.percentile(values, q)), color="black", linestyle="--", linewidth=0.7)
    axes.set_ylabel("samples")


def draw_stats(stats: DatasetStats) -> bytes:
    """PNG of three panels: the label-size histogram per case size (a count per cell), points per
    sample and solver time per sample (dashed lines at p5, p50 and p95)."""
    figure = Figure(figsize=STATS_FIGSIZE, dpi=DPI)
    FigureCanvasAgg(figure)
    figure.suptitle(f"{stats.samples} samples, {stats.committed_tasks} tasks, {len(stats.failed)} failed", fontsize=11)
    left, middle, right = figure.subplots(1, 3)
    _label_histogram(left, stats)
    middle.set_title("points per sample (refined cloud; dashed: p5, p50, p95)", fontsize=10)
    middle.set_xlabel("points")
    _histogram(middle, stats.points_per_sample.astype(np.float64), POINTS_HIST_COLOUR, logarithmic=False)
    right.set_title("solver time per sample (dashed: p5, p50, p95)", fontsize=10)
    right.set_xlabel("seconds")
    _histogram(right, stats.solver_seconds, SOLVER_HIST_COLOUR, logarithmic=True)
    figure.subplots_adjust(left=0.05, right=0.99, top=0.85, bottom=0.14, wspace=0.25)
    return _png(figure)
