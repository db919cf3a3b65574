"""Tables of an evaluation: mean +- std over objects, as the paper reports them.

Each object's figures are first averaged over its runs (rotations x initial views), then the table gives
the mean and the population standard deviation of those per-object means. Rows keep the order in which
refiners and planners were asked for. The lifts (coverage points above random views and above the best
fixed set at equal views) and the views needed to reach a share are averaged the same way over the runs
that have them; a table shows such a column only when some row has it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from datagen.evaluate.episode import Episode

FIGURES: tuple[tuple[str, str, int], ...] = (
    ("coverage", "coverage %", 2),
    ("lift", "lift vs random %", 2),
    ("lift_fixed", "lift vs fixed %", 2),
    ("lift_spread", "lift vs spread %", 2),
    ("coverage_gt", "of P_gt %", 2),
    ("views", "views", 2),
    ("movement", "movement m", 2),
    ("coverage_per_view", "cov./view", 2),
    ("coverage_per_metre", "cov./m", 2),
    ("chamfer_mm", "Chamfer mm", 2),
    ("planning_seconds", "plan s", 3),
    ("input_seconds", "input s", 2),
    ("views_to_tau", "views to tau", 2),
)
"""(key of `Episode.figures`, column heading, decimals)."""
OPTIONAL_FIGURES = frozenset({"lift", "lift_fixed", "lift_spread", "views_to_tau"})
"""Columns left out of a table where no row has a value (no lifts, no fixed plans, no share asked for)."""

K = TypeVar("K", bound=Hashable)


@dataclass(frozen=True)
class Row:
    """One (refiner, planner) row, or one (object, refiner, planner) row."""

    refiner: str
    planner: str
    objects: int
    runs: int
    approximate_paths: int
    mean: dict[str, float]
    std: dict[str, float]
    object_name: str = ""

    def as_dict(self) -> dict[str, object]:
        data: dict[str, object] = {
            "refiner": self.refiner,
            "planner": self.planner,
            "objects": self.objects,
            "runs": self.runs,
            "approximate_paths": self.approximate_paths,
        }
        if self.object_name:
            data["object"] = self.object_name
        for key, _, _ in FIGURES:
            data[key] = _json_number(self.mean[key])
            data[f"{key}_std"] = _json_number(self.std[key])
        return data


def summarise(episodes: Sequence[Episode], tau: float | None = None) -> list[Row]:
    """One row per (refiner, planner): per-object means, then mean and std over objects (``tau``: with the
    views each planner needs to see that share, where it can say)."""
    rows = []
    for (refiner, planner), group in _groups(episodes, lambda e: (e.refiner, e.planner)).items():
        per_object = [_means(runs, tau) for runs in _groups(group, lambda e: e.object_id).values()]
        rows.append(
            Row(
                refiner=refiner,
                planner=planner,
                objects=len(per_object),
                runs=len(group),
                approximate_paths=sum(not e.exact_path for e in group),
                mean={k: _nanmean([m[k] for m in per_object]) for k, _, _ in FIGURES},
                std={k: _nanstd([m[k] for m in per_object]) for k, _, _ in FIGURES},
            )
        )
    return rows


def per_object_rows(episodes: Sequence[Episode], tau: float | None = None) -> list[Row]:
    """One row per (object, refiner, planner): mean and std over that object's runs."""
    rows = []
    for (_, refiner, planner), group in _groups(episodes, lambda e: (e.object_id, e.refiner, e.planner)).items():
        figures = [e.figures(tau) for e in group]
        rows.append(
            Row(
                refiner=refiner,
                planner=planner,
                objects=1,
                runs=len(group),
                approximate_paths=sum(not e.exact_path for e in group),
                mean={k: _nanmean([f[k] for f in figures]) for k, _, _ in FIGURES},
                std={k: _nanstd([f[k] for f in figures]) for k, _, _ in FIGURES},
                object_name=group[0].object_name,
            )
        )
    return rows


def table_cells(rows: Sequence[Row]) -> tuple[list[str], list[list[str]]]:
    """The table's header and cells (`markdown_table`; a terminal draws them as a table of its own)."""
    named = any(row.object_name for row in rows)
    figures = _shown_figures(rows)
    head = [*(["object"] if named else []), "refiner", "planner", *(h for _, h, _ in figures), "objects", "runs"]
    found = []
    for row in rows:
        cells = [*([row.object_name] if named else []), row.refiner, row.planner]
        cells += [_mean_std(row.mean[k], row.std[k], d) for k, _, d in figures]
        runs = f"{row.runs}" + (f" ({row.approximate_paths} heuristic paths)" if row.approximate_paths else "")
        cells += [str(row.objects), runs]
        found.append(cells)
    return head, found


def markdown_table(rows: Sequence[Row]) -> str:
    """A Markdown table (pastes into a README)."""
    head, found = table_cells(rows)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(cells) + " |" for cells in found]
    return "\n".join(lines)


def _shown_figures(rows: Sequence[Row]) -> list[tuple[str, str, int]]:
    """The table's columns: every figure, less the optional ones no row has a value for."""
    return [f for f in FIGURES if f[0] not in OPTIONAL_FIGURES or any(not math.isnan(r.mean[f[0]]) for r in rows)]


def _groups(episodes: Sequence[Episode], key: Callable[[Episode], K]) -> dict[K, list[Episode]]:
    """Episodes grouped by ``key``, groups in order of first appearance."""
    groups: dict[K, list[Episode]] = {}
    for episode in episodes:
        groups.setdefault(key(episode), []).append(episode)
    return groups


def _means(runs: Sequence[Episode], tau: float | None = None) -> dict[str, float]:
    figures = [e.figures(tau) for e in runs]
    return {k: _nanmean([f[k] for f in figures]) for k, _, _ in FIGURES}


def _nanmean(values: Sequence[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _nanstd(values: Sequence[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.std(finite)) if finite else float("nan")


def _mean_std(mean: float, std: float, decimals: int) -> str:
    if math.isnan(mean):
        return "-"
    return f"{mean:.{decimals}f} ± {std:.{decimals}f}"


def _json_number(value: float) -> float | None:
    return None if math.isnan(value) else round(value, 6)
