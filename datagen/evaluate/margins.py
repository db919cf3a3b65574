"""What a planner captures of the room there is: its margin over an honest floor, against the ceiling's.

At a budget of V views (the initial one included) and in one situation (object, rotation, initial
view), the **floor** is the better of two plans that need no trained planner: the best fixed view
set chosen on the training data (``fixed``) and views spread from the initial one (``spread``); the
**ceiling** is the true gains played step by step (``gain``), which no planner that only sees the
scan should pass. A planner's **margin** is its coverage minus the floor's, and its **captured
share** the ratio of its mean margin to the ceiling's over the same runs: 1 plays as well as the true
gains, 0 no better than a plan that needs no data, below 0 worse (and with a ceiling margin of a
point or two, the share moves fast: read it beside the margins themselves).

A run's coverage at V views comes from its answer at every count (`Episode.count_curve`, one-shot
planners that answer for any count) or, for a planner that decided its order (step-by-step players,
`Episode.ordered`), from its coverage after its first V views (all of it past the point where it
stopped having seen everything); other runs have none at V.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass

from datagen.errors import InvalidArgument
from datagen.evaluate.episode import Episode

CEILING = "gain"
FLOORS = ("fixed", "spread")
SHARES = (0.95, 0.99)
"""The shares of the reference whose views-to-reach the margin table reports per planner."""


def kind_of(planner: str) -> str:
    """The planner's kind: ``gain`` of ``gain:10``, ``fixed`` of ``fixed:4``, ``osvp`` of ``osvp+tuned:...``."""
    return planner.split(":", 1)[0].split("+", 1)[0]


def coverage_at(episode: Episode, views: int) -> float:
    """The run's coverage (fraction) with ``views`` views in all; NaN where the run cannot say."""
    if episode.count_curve is not None and 1 <= views <= len(episode.count_curve):
        return episode.count_curve[views - 1]
    curve = episode.coverage_curve
    if episode.ordered and 1 <= views <= len(curve):
        return curve[views - 1]
    if episode.ordered and curve and curve[-1] >= 1.0 - 1e-12 and views >= 1:
        return curve[-1]  # it stopped because no view adds anything: every further view sees all there is
    return math.nan


def views_to_share(episode: Episode, share: float) -> float:
    """Views (the initial one included) the run needs to see ``share`` of the reference; NaN where it
    never does or cannot say."""
    curve = episode.count_curve if episode.count_curve is not None else episode.coverage_curve
    if episode.count_curve is None and not episode.ordered:
        return math.nan
    reached = [count for count, coverage in enumerate(curve) if coverage >= share - 1e-12]
    return float(reached[0] + 1) if reached else math.nan


@dataclass(frozen=True)
class MarginRow:
    """One (object, planner, budget) of the margin table; object "all" is the mean over objects."""

    object_name: str
    planner: str
    views: int
    runs: int
    """Situations where the planner, the ceiling and a floor all had a coverage at this budget."""
    coverage: float
    """The planner's mean coverage, percent."""
    floor: float
    ceiling: float
    margin: float
    """Planner minus floor, percent points (mean over the runs)."""
    ceiling_margin: float
    """Ceiling minus floor, percent points: the room there is."""
    captured: float
    """margin / ceiling_margin (NaN when the ceiling has no room)."""
    views_to: dict[float, float]
    """Mean views to reach each of `SHARES`, over the runs that reach it."""
    reached: dict[float, int] | None = None
    """How many of the runs reach each of `SHARES` at all (None: every run)."""

    def as_dict(self) -> dict[str, object]:
        data: dict[str, object] = {
            "object": self.object_name,
            "planner": self.planner,
            "views": self.views,
            "runs": self.runs,
        }
        for name in ("coverage", "floor", "ceiling", "margin", "ceiling_margin", "captured"):
            value = getattr(self, name)
            data[name] = None if math.isnan(value) else round(value, 6)
        for share, value in self.views_to.items():
            data[f"views_to_{share:g}"] = None if math.isnan(value) else round(value, 4)
            data[f"reached_{share:g}"] = self.runs if self.reached is None else self.reached[share]
        return data


def margin_rows(episodes: Sequence[Episode], budgets: Sequence[int]) -> list[MarginRow]:
    """Per object and over all objects, per planner (the floors apart; the ceiling's own rows give the
    room there is) and budget: margins and captured share. Raises `InvalidArgument` naming the planners
    to add when the ceiling or both floors were not played."""
    kinds = {kind_of(e.planner) for e in episodes}
    missing = [name for name in (CEILING,) if name not in kinds]
    if missing or not kinds.intersection(FLOORS):
        raise InvalidArgument(
            "--margins needs the ceiling and a floor among the planners: add -p gain, -p spread and "
            "-p fixed (with --fixed-from)"
        )
    by_situation: dict[tuple[str, int, int], dict[str, Episode]] = defaultdict(dict)
    for episode in episodes:
        by_situation[(episode.object_name, episode.rotation, episode.initial_view)][_label(episode)] = episode
    planners = list(dict.fromkeys(_label(e) for e in episodes if kind_of(e.planner) not in FLOORS))
    objects = list(dict.fromkeys(e.object_name for e in episodes))
    rows: list[MarginRow] = []
    for planner in planners:
        for views in budgets:
            per_object = [_object_row(name, planner, views, by_situation) for name in objects]
            rows.extend(row for row in per_object if row is not None)
            rows.append(_all_row(planner, views, [row for row in per_object if row is not None]))
    return rows


def _label(episode: Episode) -> str:
    """The planner, with its refiner where it reads one (``osvp:model.pt@poco``)."""
    return episode.planner if episode.refiner == "-" else f"{episode.planner}@{episode.refiner}"


def _object_row(
    name: str, planner: str, views: int, by_situation: dict[tuple[str, int, int], dict[str, Episode]]
) -> MarginRow | None:
    planned, floors, ceilings, reach = [], [], [], defaultdict(list)
    for (object_name, _, _), runs in sorted(by_situation.items()):
        if object_name != name or planner not in runs:
            continue
        episode = runs[planner]
        floor = max(
            (coverage_at(e, views) for e in runs.values() if kind_of(e.planner) in FLOORS),
            default=math.nan,
            key=lambda value: -math.inf if math.isnan(value) else value,
        )
        ceiling = next((coverage_at(e, views) for e in runs.values() if kind_of(e.planner) == CEILING), math.nan)
        value = coverage_at(episode, views)
        if math.isnan(floor) or math.isnan(ceiling) or math.isnan(value):
            continue
        planned.append(value)
        floors.append(floor)
        ceilings.append(ceiling)
        for share in SHARES:
            reached = views_to_share(episode, share)
            if not math.isnan(reached):
                reach[share].append(reached)
    if not planned:
        return None
    return _row(name, planner, views, planned, floors, ceilings, reach)


def _row(
    name: str,
    planner: str,
    views: int,
    planned: list[float],
    floors: list[float],
    ceilings: list[float],
    reach: dict[float, list[float]],
) -> MarginRow:
    coverage, floor, ceiling = (100.0 * sum(v) / len(v) for v in (planned, floors, ceilings))
    margin, room = coverage - floor, ceiling - floor
    return MarginRow(
        object_name=name,
        planner=planner,
        views=views,
        runs=len(planned),
        coverage=coverage,
        floor=floor,
        ceiling=ceiling,
        margin=margin,
        ceiling_margin=room,
        captured=margin / room if room > 1e-9 else math.nan,
        views_to={share: (sum(reach[share]) / len(reach[share]) if reach[share] else math.nan) for share in SHARES},
        reached={share: len(reach[share]) for share in SHARES},
    )


def _all_row(planner: str, views: int, rows: list[MarginRow]) -> MarginRow:
    """The mean over objects (each object weighs one), captured as the ratio of the mean margins."""
    if not rows:
        nan = math.nan
        return MarginRow("all", planner, views, 0, nan, nan, nan, nan, nan, nan, {share: nan for share in SHARES})

    def mean(values: list[float]) -> float:
        present = [v for v in values if not math.isnan(v)]
        return sum(present) / len(present) if present else math.nan

    margin = mean([r.margin for r in rows])
    room = mean([r.ceiling_margin for r in rows])
    return MarginRow(
        object_name="all",
        planner=planner,
        views=views,
        runs=sum(r.runs for r in rows),
        coverage=mean([r.coverage for r in rows]),
        floor=mean([r.floor for r in rows]),
        ceiling=mean([r.ceiling for r in rows]),
        margin=margin,
        ceiling_margin=room,
        captured=margin / room if room > 1e-9 else math.nan,
        views_to={share: mean([r.views_to[share] for r in rows]) for share in SHARES},
        reached={share: sum(r.runs if r.reached is None else r.reached[share] for r in rows) for share in SHARES},
    )


MARGIN_LEGEND = (
    "floor: per run, the better of the best fixed view set (chosen on the training data) and views spread "
    "from the initial one, at the same number of views",
    "ceiling: the true gains played step by step (gain): what a planner that knew the unseen surface would see",
    "margin: the planner's coverage minus the floor's, in points; room: the ceiling's margin",
    "captured: margin / room over the objects: 100 % plays as well as the true gains, 0 % no better than a plan "
    "needing no data, below 0 worse",
    "views to 0.95 / 0.99: mean views (the initial one included) to see that share, over the runs that do; "
    "(k/n): only k of its n runs ever do",
)
"""What the margin table's words mean, printed above it."""

MARGIN_COLUMNS = ["object", "planner", "views", "runs", "coverage %", "floor %", "ceiling %", "margin", "room"]
MARGIN_COLUMNS += ["captured", *(f"views to {share:g}" for share in SHARES)]


def margin_cells(rows: Sequence[MarginRow]) -> list[list[str]]:
    """The table's cells, one list per row, in `MARGIN_COLUMNS`' order."""
    found = []
    for row in rows:
        cells = [row.object_name, row.planner, str(row.views), str(row.runs)]
        cells += [_number(v, 2) for v in (row.coverage, row.floor, row.ceiling, row.margin, row.ceiling_margin)]
        cells.append("-" if math.isnan(row.captured) else f"{row.captured:.0%}")
        cells += [_reach(row, share) for share in SHARES]
        found.append(cells)
    return found


def _reach(row: MarginRow, share: float) -> str:
    """Views to ``share``, with how many runs reach it where some never do: ``10.0 (3/48)``, ``-`` for none."""
    reached = row.runs if row.reached is None else row.reached[share]
    value = _number(row.views_to[share], 1)
    if reached == 0:
        return f"- (0/{row.runs})"
    return value if reached >= row.runs else f"{value} ({reached}/{row.runs})"


def margin_table(rows: Sequence[MarginRow]) -> str:
    """The rows as Markdown: coverage, floor, ceiling and margins in percent points, captured share."""
    lines = ["| " + " | ".join(MARGIN_COLUMNS) + " |", "|" + "---|" * 2 + "---:|" * (len(MARGIN_COLUMNS) - 2)]
    lines += ["| " + " | ".join(cells) + " |" for cells in margin_cells(rows)]
    return "\n".join(lines)


def _number(value: float, decimals: int) -> str:
    return "-" if math.isnan(value) else f"{value:.{decimals}f}"
