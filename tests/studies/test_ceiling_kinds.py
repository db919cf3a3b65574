"""studies/planners/ceiling_kinds.py's table on made-up margins (the evaluation itself is
`datagen evaluate --margins`, tested in tests/evaluate/test_margins.py): kinds ordered by the ceiling's
margin at 4 views, mean and largest over their objects."""

from __future__ import annotations

from types import ModuleType

import pytest
from support.benchmarks import load_study


@pytest.fixture(scope="module")
def ceiling_kinds() -> ModuleType:
    return load_study("planners.ceiling_kinds")


def row(name: str, views: int, margin: float | None, planner: str = "gain") -> dict[str, object]:
    return {"object": name, "planner": planner, "views": views, "ceiling_margin": margin}


def test_kinds_are_ordered_by_the_room_at_4_views(ceiling_kinds: ModuleType) -> None:
    margins = [
        row("synth_0001_bowl", 4, 1.0),
        row("synth_0002_bowl", 4, 3.0),
        row("shared-cow", 4, 5.0),
        row("shared-cow", 2, 9.0),
        row("all", 4, 2.0),  # the mean over objects is not a kind
        row("shared-cow", 4, 99.0, planner="osvp:x.pt"),  # another planner's row is not the ceiling's
        row("synth_0003_cup", 4, None),
    ]
    kinds = {"synth_0001_bowl": "synthetic: bowl", "synth_0002_bowl": "synthetic: bowl", "shared-cow": "shared: cow"}
    kinds["synth_0003_cup"] = "synthetic: cup"
    lines = ceiling_kinds.report(margins, kinds, "cmd", ["x.obj: not a readable mesh"])
    table = [line for line in lines if line.startswith("| shared") or line.startswith("| synthetic")]
    assert table == [
        "| shared: cow | 1 | 9.00 / 9.00 | - | 5.00 / 5.00 | - |",
        "| synthetic: bowl | 2 | - | - | 2.00 / 3.00 | - |",
    ]
    assert lines[-1] == "- x.obj: not a readable mesh"
